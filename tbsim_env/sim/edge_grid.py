"""Road-edge lookup for the off-road check: a uniform grid of per-cell candidate segments.

Each scenario's road-edge segments are bucketed once, when the scenario bank is built: for every
cell of a uniform grid over the map, the ``EDGE_GRID_CANDIDATES`` segments nearest to the cell
centre, sorted, and the distance ``bound`` of the next one. A query point p in (or clamped to) a
cell with centre c whose nearest listed segment is at distance d has its true nearest segment in
the list whenever ``d + |p - c| <= bound`` (triangle inequality). That holds for almost every
point; the rest are flagged ``stale`` and recomputed over every segment of their scenario
(``grid_offroad_distance`` does it eagerly; a compiled step reports them), so the result is
always the exact signed distance to the scenario's edges.

A step therefore costs a fixed 4 corners x C candidates per agent, with no per-agent cache to
carry or refresh: the cost grows linearly with the agents and does not depend on their history.

The grid itself (``CellLists``: ``scene_edge_grid``, ``stack_cell_lists``, ``cell_of``,
``cell_slack``) also lists the observations' nearest map pieces (``map_knn.PieceGrid``; a point
is a segment of length zero).
"""

from __future__ import annotations

import hashlib

import numpy as np
import torch

from tbsim_env.core import constants as C
from tbsim_env.core.lru import LRU
from tbsim_env.core.torch_utils import cast, const, gather_rows, row_offsets, scalar, select_rows
from tbsim_env.sim.geometry import segment_projection_xy
from tbsim_env.sim.state import CellLists, EdgeGrid, RoadEdges, Shared


def scene_edge_grid(
    start: np.ndarray, end: np.ndarray, cell: float, count: int, margin: float
) -> dict[str, np.ndarray]:
    """The grid of one scenario, see ``EdgeGrid`` (kept: ``EDGE_GRID_CACHE_SCENES``; a call
    with the same arguments gets a copy).

    Args:
        start, end: [E, 2] segment ends (m, state frame); E may be 0.
        cell: cell size (m).
        count: candidates kept per cell.
        margin: m the grid extends beyond the segments' bounding box.

    Returns:
        dict of numpy arrays: ``lower`` [2], ``shape`` [2], ``cells`` [G, count], ``bound``
        [G] (lowered by ``_BOUND_SLACK`` against rounding), ``center`` [G, 2].
    """
    digest = hashlib.blake2b(digest_size=16)
    for x in (start, end):
        x = np.ascontiguousarray(x)
        digest.update(f"{x.dtype.str}{x.shape}".encode())
        digest.update(x.tobytes())
    tiling = (_TILE_CELLS, _LEAF_CELLS, _TILE_WORK)  # the same grid however tiled, but keyed
    key = (digest.digest(), float(cell), int(count), float(margin), tiling)
    grid = _GRIDS.get(key)
    if grid is None:
        grid = _GRIDS.put(key, _scene_edge_grid(start, end, cell, count, margin))
    return {k: v.copy() for k, v in grid.items()}


_GRIDS: LRU[tuple, dict[str, np.ndarray]] = LRU(C.EDGE_GRID_CACHE_SCENES)
"""``scene_edge_grid``'s kept grids."""


def forget_grids() -> None:
    """Drop every grid ``scene_edge_grid`` keeps (a benchmark timing a first build)."""
    _GRIDS.clear()


def _scene_edge_grid(
    start: np.ndarray, end: np.ndarray, cell: float, count: int, margin: float
) -> dict[str, np.ndarray]:
    """``scene_edge_grid`` computed."""
    e = len(start)
    if e == 0:
        return {
            "lower": np.zeros(2),
            "shape": np.ones(2, np.int64),
            "cells": np.zeros((1, count), np.int64),
            "bound": np.full(1, np.inf),
            "center": np.zeros((1, 2)),
        }
    lo = np.minimum(start.min(0), end.min(0)) - margin
    hi = np.maximum(start.max(0), end.max(0)) + margin
    shape = np.maximum(np.ceil((hi - lo) / cell), 1).astype(np.int64)
    ix, iy = np.meshgrid(np.arange(shape[0]), np.arange(shape[1]), indexing="ij")
    center = lo + (np.stack([ix, iy], -1).reshape(-1, 2) + 0.5) * cell
    # float32 is enough: the bound keeps a slack far above its rounding at map coordinates.
    seg = _Segments.of(start, end)
    k = min(count + 1, e)
    near, kth = _nearest_by_tiles(torch.from_numpy(center).float(), shape, cell, seg, k)
    near = near[:, :count].numpy()
    bound = kth.numpy() if k > count else np.full(len(center), np.inf, np.float32)
    if near.shape[1] < count:  # fewer segments than candidates: repeat the farthest
        near = np.concatenate([near, np.repeat(near[:, -1:], count - near.shape[1], 1)], 1)
    return {
        "lower": lo,
        "shape": shape,
        "cells": near,
        "bound": bound - _BOUND_SLACK,
        "center": center,
    }


_TILE_CELLS = 8
"""Cells per side of the tiles that ``scene_edge_grid`` narrows the candidates for first."""

_LEAF_CELLS = 4
"""Cells per side of the blocks whose cells measure their candidates (tiles are quartered
down to it)."""

_TILE_WORK = 1 << 20
"""Cell-segment distances ``_nearest_by_tiles`` measures at once (bounds its memory)."""


def _nearest_by_tiles(
    q: torch.Tensor, shape: np.ndarray, cell: float, seg: _Segments, k: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """The k nearest segments of every cell centre, measured tile by tile, tiles batched.

    A point p's k nearest segments lie within (k-th distance from a hub h + 2 |p - h|) of h
    (triangle inequality). So a tile of ``_TILE_CELLS``^2 cells keeps the segments within
    that cutoff of its centre (its radius reaching the farthest cell centre), each of its four
    quarters keeps those of the tile's within the cutoff of the quarter's centre (quartered
    again down to ``_LEAF_CELLS`` cells a side), and each cell measures its block's
    candidates alone.

    Args:
        q: [G, 2] cell centres (row-major over ``shape``); cell: m; k: segments kept.

    Returns:
        (indices [G, k] int64 sorted by distance, distance of the k-th [G] m).
    """
    side = _TILE_CELLS
    cells, hubs = _tiles(shape, side, q, cell)  # [T, side^2] (-1: none), [T, 2]
    padded = seg.with_sentinel()  # lists are padded with the sentinel (index E)
    sentinel = len(seg.ax)
    d_hub = seg.squared_distance(hubs).sqrt()  # [T, E]
    cand, n_cand = _within_cutoff(d_hub, k, _radius(side, cell), sentinel)
    while side > _LEAF_CELLS:
        cells, hubs, cand, n_cand = _quarters(cells, hubs, cand, padded, (side, cell, k))
        side //= 2
    keep = (cells >= 0).any(1)
    cells, cand, n_cand = cells[keep], cand[keep], n_cand[keep]
    near = torch.empty(len(q), k, dtype=torch.int64)
    kth2 = torch.empty(len(q))
    # Quarters in order of their candidate counts, so that a chunk pads little.
    by_count = n_cand.argsort()
    cells, n_cand, cand = cells[by_count], n_cand[by_count], cand[by_count]
    for t0, t1, width in _chunks(n_cand.tolist(), side * side, _TILE_WORK):
        tc, cc = cells[t0:t1], cand[t0:t1, :width]  # [t, side^2], [t, W]
        d2 = padded.take(cc).squared_distance(q[tc.clamp_min(0)])  # [t, side^2, W]
        # numpy's (SIMD) argsort beats torch.topk several times over on these short rows.
        idx = torch.from_numpy(np.argsort(d2.numpy(), axis=-1)[..., :k])
        top = d2.gather(-1, idx)
        ok = tc >= 0
        near[tc[ok]] = cc.gather(1, idx.flatten(1)).view(idx.shape)[ok]
        kth2[tc[ok]] = top[..., -1][ok]
    return near, kth2.sqrt()


def _quarters(
    cells: torch.Tensor,
    hubs: torch.Tensor,
    cand: torch.Tensor,
    segments: _Segments,
    block: tuple[int, float, int],
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """The four quarters of R blocks of ``side`` x ``side`` cells (``block``: side, cell m,
    k): their cells [4 R, (side / 2)^2], centres [4 R, 2], and candidates of the block's
    ``cand`` [R, W] within the quarter's cutoff ([4 R, W'] padded with the sentinel, counts
    [4 R]). Quarter (a, b) holds cells (a side / 2 + i, b side / 2 + j) of its block."""
    side, cell, k = block
    half, r = side // 2, len(cells)
    quarter_cells = cells.view(r, 2, half, 2, half).permute(0, 1, 3, 2, 4).reshape(4 * r, -1)
    shift = (torch.tensor([[-1, -1], [-1, 1], [1, -1], [1, 1]]) * (0.5 * half * cell)).float()
    quarter_hubs = hubs[:, None] + shift  # [R, 4, 2]
    d = segments.take(cand).squared_distance(quarter_hubs).sqrt()  # [R, 4, W]
    cols, count = _within_cutoff(d.view(4 * r, -1), k, _radius(half, cell), -1)
    sentinel = len(segments.ax) - 1
    out = cand.repeat_interleave(4, 0).gather(1, cols.clamp_min(0))
    return quarter_cells, quarter_hubs.view(-1, 2), torch.where(cols >= 0, out, sentinel), count


def _radius(side: int, cell: float) -> float:
    """m from the centre of a ``side`` x ``side`` block of cells to its farthest cell centre."""
    return float(np.hypot(*(0.5 * (side - 1) * cell,) * 2))


def _within_cutoff(
    d: torch.Tensor, k: int, radius: float, pad: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Per row of hub distances ``d`` [R, C], the columns within (its k-th distance +
    2 ``radius``), nearest first: ([R, W] int64 padded with ``pad``, W the largest count;
    counts [R])."""
    order = torch.from_numpy(np.argsort(d.numpy(), axis=1))
    cutoff = d.gather(1, order[:, k - 1 : k]) + (2.0 * radius + 1e-3)
    count = (d <= cutoff).sum(1)
    width = int(count.max())
    order = order[:, :width]
    return torch.where(torch.arange(width) < count[:, None], order, pad), count


def _chunks(counts: list[int], cells: int, work: int) -> list[tuple[int, int, int]]:
    """(first tile, end, width) of chunks of tiles with ascending candidate ``counts``, each
    measuring at most ``work`` cell-candidate pairs (a single tile may exceed it)."""
    out, t0 = [], 0
    while t0 < len(counts):
        t1 = t0 + 1
        while t1 < len(counts) and (t1 + 1 - t0) * counts[t1] * cells <= work:
            t1 += 1
        out.append((t0, t1, counts[t1 - 1]))
        t0 = t1
    return out


def _tiles(
    shape: np.ndarray, side: int, q: torch.Tensor, cell: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """The ``side`` x ``side`` tiles of a grid of ``shape`` [2] cells with centres ``q``
    [G, 2]: their flat cell indices [T, side^2] (row-major; -1 past the grid's edge) and the
    centres [T, 2] of the full tiles."""
    nx, ny = int(shape[0]), int(shape[1])
    tx, ty = -(-nx // side), -(-ny // side)
    flat = torch.full((tx * side, ty * side), -1, dtype=torch.int64)
    flat[:nx, :ny] = torch.arange(nx * ny).view(nx, ny)
    cells = flat.view(tx, side, ty, side).permute(0, 2, 1, 3).reshape(tx * ty, side * side)
    corner = q[0] - 0.5 * cell  # the grid's lower corner
    i, j = torch.meshgrid(torch.arange(tx), torch.arange(ty), indexing="ij")
    hubs = corner + (torch.stack([i, j], -1).reshape(-1, 2).float() + 0.5) * (side * cell)
    return cells, hubs


class _Segments:
    """Segments (start a, vector ab, |ab|^2) as float32 columns, for point distances."""

    def __init__(self, ax, ay, abx, aby, len2):
        self.ax, self.ay, self.abx, self.aby, self.len2 = ax, ay, abx, aby, len2

    @classmethod
    def of(cls, start: np.ndarray, end: np.ndarray) -> _Segments:
        a = torch.from_numpy(start).float()
        ab = torch.from_numpy(end).float() - a
        return cls(a[:, 0], a[:, 1], ab[:, 0], ab[:, 1], (ab * ab).sum(-1).clamp_min(1e-12))

    def take(self, rows: torch.Tensor) -> _Segments:
        """The segments ``rows`` (any shape [..., W])."""
        return _Segments(*(v[rows] for v in (self.ax, self.ay, self.abx, self.aby, self.len2)))

    def with_sentinel(self) -> _Segments:
        """These segments and one more of length zero, ``_FAR`` m away from every map."""
        far = torch.tensor([_FAR])
        ext = lambda v, x: torch.cat([v, x])  # noqa: E731
        return _Segments(
            ext(self.ax, far),
            ext(self.ay, far),
            ext(self.abx, far * 0),
            ext(self.aby, far * 0),
            ext(self.len2, torch.ones(1)),
        )

    def squared_distance(self, q: torch.Tensor) -> torch.Tensor:
        """[..., g, W] squared distances (m^2) of points ``q`` [..., g, 2] to these segments
        (of shape [..., W]: a ``take`` per leading index, e.g. tile i's segments for tile i's
        points; or [W], every point to every segment)."""
        col = lambda v: v.unsqueeze(-2)  # noqa: E731
        dx, dy = q[..., :1] - col(self.ax), q[..., 1:] - col(self.ay)
        t = ((dx * col(self.abx) + dy * col(self.aby)) / col(self.len2)).clamp_(0.0, 1.0)
        ex, ey = dx - t * col(self.abx), dy - t * col(self.aby)
        return ex * ex + ey * ey


_FAR = 1.0e9
"""m: where the padding segment of ``_nearest_by_tiles`` lies (its square fits float32)."""


_BOUND_SLACK = 1e-3
"""m taken off every cell's bound, so that float32 rounding of the per-step distances never
vouches for a point whose nearest segment is not listed."""


def build_edge_grid(
    segments: list[tuple[np.ndarray, np.ndarray]],
    device: torch.device | str = "cpu",
    cell: float = C.EDGE_GRID_CELL,
    count: int = C.EDGE_GRID_CANDIDATES,
    margin: float = C.EDGE_GRID_MARGIN,
    links: list[tuple[np.ndarray, np.ndarray]] | None = None,
) -> EdgeGrid:
    """Batch the grids of B scenarios.

    Args:
        segments: per scenario (start [E_i, 2], end [E_i, 2]) in the state frame (m), in the
            order of the rows of its ``RoadEdges``.
        device: torch device.
        cell, count, margin: grid cell size (m), candidates per cell, extent beyond the edges
            (m); constants in ``tbsim_env.core.constants``.
        links: optional, per scenario (previous [E_i], next [E_i]) segment indices as in
            ``RoadEdges``: the grid then carries the joint table (``EdgeGrid.joints``).
    """
    grids = [scene_edge_grid(s, e, cell, count, margin) for s, e in segments]
    n_e = max(max(len(s) for s, _ in segments), 1)
    table = np.zeros((len(grids), n_e, 4), np.float32)
    for i, (s, e) in enumerate(segments):
        start = np.asarray(s, np.float32)  # the RoadEdges' float32 values
        table[i, : len(start), :2] = start
        table[i, : len(start), 2:] = np.asarray(e, np.float32) - start
    dev = torch.device(device)
    columns = torch.from_numpy(table).to(dev)  # [K, E, 4]
    vec = columns[..., 2:]
    len2 = (vec[..., 0] * vec[..., 0] + vec[..., 1] * vec[..., 1]).clamp_min(1e-12)
    lookup = torch.cat([columns, len2[..., None]], -1).transpose(1, 2).contiguous()
    rows = torch.arange(len(grids), device=dev)
    joints = None
    if links is not None:
        joints = Shared(_joint_table(columns, links, dev))
    return EdgeGrid(
        **stack_cell_lists(grids, cell, dev),
        segments=Shared(lookup),
        row_columns=(rows * (5 * n_e)).view(-1, 1, 1),
        has_edge=torch.tensor([[len(s) > 0] for s, _ in segments], device=dev),
        joints=joints,
        row_joints=None if joints is None else (rows * (3 * n_e)).view(-1, 1),
    )


def _joint_table(
    columns: torch.Tensor, links: list[tuple[np.ndarray, np.ndarray]], device: torch.device
) -> torch.Tensor:
    """``EdgeGrid.joints`` [K, 3 E, 9] of the segments ``columns`` [K, E, 4] (start x, start y,
    vector x, vector y) and their ``links`` (previous, next per scenario)."""
    k, e = columns.shape[:2]
    prev = torch.arange(e, device=device).repeat(k, 1)
    nxt = prev.clone()
    for i, (pr, nx) in enumerate(links):
        prev[i, : len(pr)] = torch.as_tensor(np.asarray(pr), device=device)
        nxt[i, : len(nx)] = torch.as_tensor(np.asarray(nx), device=device)
    me = columns[..., [0, 1, 3, 2]]  # start x, start y, vector y, vector x
    rows = torch.arange(k, device=device)[:, None]
    before, after = me[rows, prev], me[rows, nxt]
    dx0, dy0 = columns[..., 2], columns[..., 3]
    # The convexity of joint_sign, in its arithmetic: cross(previous, this), cross(this, next).
    convex_prev = before[..., 3] * dy0 - before[..., 2] * dx0 > 0
    convex_next = dx0 * after[..., 2] - dy0 * after[..., 3] > 0
    sign = lambda convex: torch.where(convex, 1.0, -1.0)[..., None]  # noqa: E731
    cases = [
        torch.cat([me, before, sign(convex_prev)], -1),
        torch.cat([me, me, torch.ones_like(dx0)[..., None]], -1),
        torch.cat([me, after, sign(convex_next)], -1),
    ]
    return torch.stack(cases, 2).reshape(k, 3 * e, 9).contiguous()


def stack_cell_lists(
    grids: list[dict[str, np.ndarray]], cell: float, device: torch.device
) -> dict[str, torch.Tensor | Shared]:
    """The ``CellLists`` fields of B scenarios' ``scene_edge_grid`` outputs, padded to the
    largest grid (padding cells: candidates 0, bound +inf, centre 0; no point maps to them)."""
    b, g = len(grids), max(len(x["bound"]) for x in grids)
    count = grids[0]["cells"].shape[1]
    cells = np.zeros((b, g, count), np.int32)
    bound = np.full((b, g), np.inf, np.float32)
    center = np.zeros((b, g, 2), np.float32)
    for i, x in enumerate(grids):
        n = len(x["bound"])
        cells[i, :n], bound[i, :n], center[i, :n] = x["cells"], x["bound"], x["center"]
    lower = torch.from_numpy(np.stack([x["lower"] for x in grids]).astype(np.float32)).to(device)
    shape = torch.from_numpy(np.stack([x["shape"] for x in grids])).to(device)
    row = torch.arange(b, device=device)
    stride = torch.stack([shape[:, 1], torch.ones_like(shape[:, 1])], -1)
    info = np.concatenate([center, bound[..., None]], -1)
    return {
        "cell": torch.full((b, 1, 1), float(cell), dtype=torch.float32, device=device),
        "lower": lower,
        "shape": shape,
        "row": row,
        "cells": Shared(torch.from_numpy(cells).to(device)),
        "bound": Shared(torch.from_numpy(bound).to(device)),
        "center": Shared(torch.from_numpy(center).to(device)),
        "corner": lower[:, None].contiguous(),
        "last": (shape - 1).float()[:, None].contiguous(),
        "stride": stride.float()[:, None].contiguous(),
        "row_cells": (row * g)[:, None],
        "cell_info": Shared(torch.from_numpy(info).to(device)),
    }


def cell_index(grid: CellLists, xy: torch.Tensor, rows: torch.Tensor | None) -> torch.Tensor:
    """[B, K] int64 flat cell index, in the flattened [K' G] tables of ``grid`` (the row's
    offset included), of points [B, K, 2] (clamped into the grid) of the grid rows ``rows``
    [B] (each row its own by default)."""
    corner, cell, last, stride, base = (
        grid.corner,
        grid.cell,
        grid.last,
        grid.stride,
        grid.row_cells,
    )
    if rows is not None:
        corner, cell, last = corner[rows], cell[rows], last[rows]
        stride, base = stride[rows], base[rows]
    # Cell indices stay far below 2**24: exact in float32 (and the same as in int64).
    ij = torch.floor((xy - corner) / cell).clamp(min=scalar(0.0, xy.dtype, xy.device), max=last)
    return cast((ij * stride).sum(-1), torch.int64) + base


def cell_of(grid: CellLists, xy: torch.Tensor, rows: torch.Tensor | None) -> torch.Tensor:
    """[B, K] flat cell index of points [B, K, 2] (clamped into the grid) of the grid rows
    ``rows`` [B] (each row its own by default), within the row's own table."""
    base = grid.row_cells if rows is None else grid.row_cells[rows]
    return cell_index(grid, xy, rows) - base


def cell_rows(table: Shared, flat: torch.Tensor) -> torch.Tensor:
    """The rows ``flat`` [B, K] (``cell_index``) of a per-cell table [K', G, ...]:
    [B, K, ...]."""
    value = table.value
    return select_rows(value, flat.view(-1)).view(*flat.shape, *value.shape[2:])


def cell_slack(
    grid: CellLists, xy: torch.Tensor, cell: torch.Tensor, table: torch.Tensor
) -> torch.Tensor:
    """[B, K] m, ``bound - |p - c|`` of points ``xy`` [B, K, 2] in their cells ``cell`` [B, K]
    (``cell_of``) of the shared-table rows ``table`` [B]: no target missing from the cell's
    list is nearer to the point (+inf: every target is listed)."""
    centre = gather_rows(grid.center.value, cell, table)
    bound = gather_rows(grid.bound.value, cell, table)
    return bound - torch.hypot(xy[..., 0] - centre[..., 0], xy[..., 1] - centre[..., 1])


def slack_at(grid: CellLists, xy: torch.Tensor, flat: torch.Tensor) -> torch.Tensor:
    """``cell_slack`` of points ``xy`` [B, K, 2] in the cells ``flat`` [B, K]
    (``cell_index``), from one gather of ``cell_info``."""
    info = cell_rows(grid.cell_info, flat)  # [B, K, 3]
    away = xy - info[..., :2]
    return info[..., 2] - torch.hypot(away[..., 0], away[..., 1])


def grid_signed_distance(
    points: torch.Tensor, edges: RoadEdges, grid: EdgeGrid, rows: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed road-edge distance of points over their cell's candidates (WOSAC sign rule).

    Args:
        points: [B, K, 2] m.
        edges: road-edge segments of the scenarios.
        grid: their ``EdgeGrid``.
        rows: optional [B] int64: point row b lies in the scenario of edge row ``rows[b]``
            (points gathered from several rows); row b itself by default.

    Returns:
        (signed distance [B, K] m, positive off-road, ``NO_EDGE_DISTANCE`` without edges;
        stale [B, K] bool: the nearest segment may be outside the cell's list, so the value
        may be wrong there).
    """
    flat = cell_index(grid, points, rows)  # [B, K]
    # int64 once (the table keeps int32): no index arithmetic below mixes integer types.
    cand = cast(cell_rows(grid.cells, flat), torch.int64)  # [B, K, Cc]
    if grid.joints is None:
        out, d = signed_over(points, edges, cand, rows)
    else:
        out, d = _signed_by_joints(points, grid, cand, rows)
    return out, d > slack_at(grid, points, flat)


def _signed_by_joints(
    points: torch.Tensor, grid: EdgeGrid, cand: torch.Tensor, rows: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """``signed_over`` of a grid with its joint table: (signed, unsigned distance) [B, K] m
    of points [B, K, 2] to the nearest of their candidates ``cand`` [B, K, C] int64."""
    ax, ay, bx, by, len2 = _segment_columns(grid, cand, rows)  # [B, K, C] each
    qx, qy = points[..., :1], points[..., 1:]
    t = ((qx - ax) * bx + (qy - ay) * by) / len2  # 0 for a zero-length segment (b = 0)
    inside = t.clamp(const(0.0, t), const(1.0, t))
    far = torch.hypot(qx - (ax + inside * bx), qy - (ay + inside * by))
    at = far.argmin(-1, keepdim=True)  # [B, K, 1]: the first nearest, as ``min``'s index
    dist, t_best, best = far.gather(-1, at), t.gather(-1, at), cand.gather(-1, at)
    base = grid.row_joints if rows is None else grid.row_joints[rows]
    case = torch.bucketize(t_best, const(_JOINT_CASES, t_best), right=True)
    key = torch.add(case, best, alpha=3) + base.view(-1, 1, 1)
    b, k = points.shape[:2]
    joint = cell_rows(grid.joints, key).view(b, k, 9)
    seg = joint[..., :8].view(b, k, 2, 2, 2)  # (this, other) x (start, vector) x 2
    lever = (points.unsqueeze(-2) - seg[..., 0, :]) * seg[..., 1, :]  # [B, K, 2, 2]
    side = torch.sign(lever[..., 0] - lever[..., 1])  # [B, K, 2]: cross(p - a, vector)
    turn = joint[..., 8:]  # +1: the max of the two sides, -1: the min
    signed = ((side * turn).amax(-1, keepdim=True) * turn * dist).view(b, k)
    has_edge = grid.has_edge if rows is None else grid.has_edge[rows]
    return torch.where(has_edge, signed, const(C.NO_EDGE_DISTANCE, dist)), dist.view(b, k)


_JOINT_CASES = (0.0, float(np.nextafter(np.float32(1.0), np.float32(2.0))))
"""Bucket edges of a projection parameter t: t < 0, 0 <= t <= 1 (below the float32 after 1),
t > 1 (``EdgeGrid.joints``' cases)."""


def signed_over(
    points: torch.Tensor,
    edges: RoadEdges,
    cand: torch.Tensor,
    rows: torch.Tensor | None = None,
    usable: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed distance of points [B, K, 2] to the nearest of their candidate segments ``cand``
    [B, K, C] (indices, read through the edges' grid tables), and that unsigned distance,
    each [B, K] m (``NO_EDGE_DISTANCE`` without edges). ``usable``: optional [B, K, C] bool,
    candidates that count (the others are never nearest). ``rows``: as
    ``grid_signed_distance``'s."""
    ax, ay, bx, by = _segment_columns(edges, cand, rows)  # [B, K, C] each
    t, dist = segment_projection_xy(points[..., :1], points[..., 1:], ax, ay, bx, by)
    if usable is not None:
        dist = torch.where(usable, dist, float("inf"))
    return nearest_signed(points, edges, (dist, t), cand, rows)


def nearest_signed(
    points: torch.Tensor,
    edges: RoadEdges,
    measured: tuple[torch.Tensor, torch.Tensor],
    cand: torch.Tensor | None = None,
    rows: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(signed distance, unsigned distance) [B, K] m of points [B, K, 2] to the nearest of the
    segments they were measured to: ``measured`` = (distance, projection parameter)
    [B, K, C] to the segments ``cand`` [B, K, C] (None: column c is segment c). The sign is
    ``joint_sign``'s; ``NO_EDGE_DISTANCE`` where the scene has no edge. ``rows``: as
    ``grid_signed_distance``'s."""
    dist, t = measured
    local = dist.argmin(-1, keepdim=True)
    d = dist.gather(-1, local)[..., 0]
    t_best = t.gather(-1, local)[..., 0]
    best = local[..., 0] if cand is None else cand.gather(-1, local)[..., 0].long()  # [B, K]
    sign = joint_sign(points, edges, best, t_best, rows)
    has_edge = edges.valid.any(-1, keepdim=True)
    has_edge = has_edge if rows is None else has_edge[rows]
    return torch.where(has_edge, sign * d, C.NO_EDGE_DISTANCE), d


def _segment_columns(
    edges: RoadEdges | EdgeGrid, seg: torch.Tensor, rows: torch.Tensor | None
) -> tuple[torch.Tensor, ...]:
    """(start x, start y, (end - start) x, (end - start) y) of the segments ``seg`` [B, ...] of
    edge row b (or ``rows[b]``), each [B, ...]: from the grid's column table when there is one
    (one index for all, contiguous results; a grid also gives the clamped squared length as a
    fifth column), else from the edges."""
    grid = edges if isinstance(edges, EdgeGrid) else edges.grid
    if grid is not None:
        table = grid.segments.value  # [K, 5, E]
        c, e = table.shape[1:]
        base = grid.row_columns if rows is None else grid.row_columns[rows]
        base = base.view(-1, *([1] * (seg.dim() - 1)))
        if seg.numel() >= C.COLUMN_GATHER_MIN:  # a column at a time: no [C, ...] index
            at, words = (seg + base).view(-1), table.view(-1)
            n = c if isinstance(edges, EdgeGrid) else 4
            return tuple(words[k * e :].index_select(0, at).view(seg.shape) for k in range(n))
        flat = (seg + base).view(1, *seg.shape) + row_offsets(c, e, seg.dim() + 1, seg.device)
        cols = table.view(-1).index_select(0, flat.view(-1)).view(c, *seg.shape).unbind(0)
        return cols if isinstance(edges, EdgeGrid) else cols[:4]
    sa = gather_rows(edges.start, seg, rows)
    sab = gather_rows(edges.end, seg, rows) - sa
    return sa[..., 0], sa[..., 1], sab[..., 0], sab[..., 1]


def joint_sign(
    points: torch.Tensor,
    edges: RoadEdges,
    best: torch.Tensor,
    t_best: torch.Tensor,
    rows: torch.Tensor | None = None,
) -> torch.Tensor:
    """+1 / -1 side of ``points`` [B, K, 2] relative to their nearest segment ``best`` [B, K]
    (projection parameter ``t_best``), with the convexity rule at polyline joints. ``rows``:
    as ``grid_signed_distance``'s."""
    prev = gather_rows(edges.prev_index, best, rows)
    nxt = gather_rows(edges.next_index, best, rows)
    seg = torch.stack([best, prev, nxt], -1)  # [B, K, 3]
    ax, ay, dx, dy = _segment_columns(edges, seg, rows)  # [B, K, 3] each
    # The side of each segment: cross(p - a, b - a).
    n = torch.sign((points[..., 0:1] - ax) * dy - (points[..., 1:2] - ay) * dx)
    n_this, n_prev, n_next = n.unbind(-1)
    (dx0, dx1, dx2), (dy0, dy1, dy2) = dx.unbind(-1), dy.unbind(-1)
    convex_prev = dx1 * dy0 - dy1 * dx0 > 0  # cross(previous, this)
    convex_next = dx0 * dy2 - dy0 * dx2 > 0  # cross(this, next)
    with_prev = torch.where(
        convex_prev, torch.maximum(n_this, n_prev), torch.minimum(n_this, n_prev)
    )
    with_next = torch.where(
        convex_next, torch.maximum(n_this, n_next), torch.minimum(n_this, n_next)
    )
    sign = torch.where((t_best < 0) & (prev != best), with_prev, n_this)
    return torch.where((t_best > 1) & (nxt != best), with_next, sign)


__all__ = [
    "EdgeGrid",
    "build_edge_grid",
    "cell_index",
    "cell_of",
    "cell_rows",
    "cell_slack",
    "grid_signed_distance",
    "joint_sign",
    "nearest_signed",
    "scene_edge_grid",
    "signed_over",
    "slack_at",
    "stack_cell_lists",
]
