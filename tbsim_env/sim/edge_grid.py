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

import numpy as np
import torch

from tbsim_env import constants as C
from tbsim_env.sim.geometry import segment_projection_xy
from tbsim_env.sim.state import CellLists, EdgeGrid, RoadEdges, Shared
from tbsim_env.torch_utils import gather_columns, gather_rows


def scene_edge_grid(
    start: np.ndarray, end: np.ndarray, cell: float, count: int, margin: float
) -> dict[str, np.ndarray]:
    """The grid of one scenario, see ``EdgeGrid``.

    Args:
        start, end: [E, 2] segment ends (m, state frame); E may be 0.
        cell: cell size (m).
        count: candidates kept per cell.
        margin: m the grid extends beyond the segments' bounding box.

    Returns:
        dict of numpy arrays: ``lower`` [2], ``shape`` [2], ``cells`` [G, count], ``bound``
        [G] (lowered by ``_BOUND_SLACK`` against rounding), ``center`` [G, 2].
    """
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
    a = torch.from_numpy(start).float()
    ab = torch.from_numpy(end).float() - a
    ax, ay, abx, aby = a[:, 0], a[:, 1], ab[:, 0], ab[:, 1]
    len2 = (ab * ab).sum(-1).clamp_min(1e-12)
    k = min(count + 1, e)
    cells, bound = [], []
    for q in torch.from_numpy(center).float().split(max(1, (1 << 20) // e)):
        dx, dy = q[:, :1] - ax, q[:, 1:] - ay  # [g, E]
        t = ((dx * abx + dy * aby) / len2).clamp_(0.0, 1.0)
        d = torch.hypot(dx - t * abx, dy - t * aby)
        top, idx = torch.topk(d, k, dim=-1, largest=False, sorted=True)
        cells.append(idx[:, :count])
        bound.append(top[:, count] if k > count else torch.full_like(top[:, 0], float("inf")))
    near = torch.cat(cells).numpy()
    if near.shape[1] < count:  # fewer segments than candidates: repeat the farthest
        near = np.concatenate([near, np.repeat(near[:, -1:], count - near.shape[1], 1)], 1)
    return {
        "lower": lo,
        "shape": shape,
        "cells": near,
        "bound": torch.cat(bound).numpy() - _BOUND_SLACK,
        "center": center,
    }


_BOUND_SLACK = 1e-3
"""m taken off every cell's bound, so that float32 rounding of the per-step distances never
vouches for a point whose nearest segment is not listed."""


def build_edge_grid(
    segments: list[tuple[np.ndarray, np.ndarray]],
    device: torch.device | str = "cpu",
    cell: float = C.EDGE_GRID_CELL,
    count: int = C.EDGE_GRID_CANDIDATES,
    margin: float = C.EDGE_GRID_MARGIN,
) -> EdgeGrid:
    """Batch the grids of B scenarios.

    Args:
        segments: per scenario (start [E_i, 2], end [E_i, 2]) in the state frame (m), in the
            order of the rows of its ``RoadEdges``.
        device: torch device.
        cell, count, margin: grid cell size (m), candidates per cell, extent beyond the edges
            (m); constants in ``tbsim_env.constants``.
    """
    grids = [scene_edge_grid(s, e, cell, count, margin) for s, e in segments]
    table = np.zeros((len(grids), max(max(len(s) for s, _ in segments), 1), 4), np.float32)
    for i, (s, e) in enumerate(segments):
        start = np.asarray(s, np.float32)  # the RoadEdges' float32 values
        table[i, : len(start), :2] = start
        table[i, : len(start), 2:] = np.asarray(e, np.float32) - start
    dev = torch.device(device)
    return EdgeGrid(
        **stack_cell_lists(grids, cell, dev),
        segments=Shared(torch.from_numpy(table).transpose(1, 2).contiguous().to(dev)),
    )


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
    return {
        "cell": torch.full((b, 1, 1), float(cell), dtype=torch.float32, device=device),
        "lower": torch.from_numpy(np.stack([x["lower"] for x in grids]).astype(np.float32)).to(
            device
        ),
        "shape": torch.from_numpy(np.stack([x["shape"] for x in grids])).to(device),
        "row": torch.arange(b, device=device),
        "cells": Shared(torch.from_numpy(cells).to(device)),
        "bound": Shared(torch.from_numpy(bound).to(device)),
        "center": Shared(torch.from_numpy(center).to(device)),
    }


def cell_of(grid: CellLists, xy: torch.Tensor, rows: torch.Tensor | None) -> torch.Tensor:
    """[B, K] flat cell index of points [B, K, 2] (clamped into the grid) of the grid rows
    ``rows`` [B] (each row its own by default)."""
    lower, cell, shape = grid.lower, grid.cell, grid.shape
    if rows is not None:
        lower, cell, shape = lower[rows], cell[rows], shape[rows]
    ij = torch.floor((xy - lower[:, None]) / cell).long()
    ij = torch.minimum(ij.clamp_min(0), shape[:, None] - 1)
    return ij[..., 0] * shape[:, None, 1] + ij[..., 1]


def cell_slack(
    grid: CellLists, xy: torch.Tensor, cell: torch.Tensor, table: torch.Tensor
) -> torch.Tensor:
    """[B, K] m, ``bound - |p - c|`` of points ``xy`` [B, K, 2] in their cells ``cell`` [B, K]
    (``cell_of``) of the shared-table rows ``table`` [B]: no target missing from the cell's
    list is nearer to the point (+inf: every target is listed)."""
    centre = gather_rows(grid.center.value, cell, table)
    bound = gather_rows(grid.bound.value, cell, table)
    return bound - torch.hypot(xy[..., 0] - centre[..., 0], xy[..., 1] - centre[..., 1])


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
    cell = cell_of(grid, points, rows)  # [B, K]
    table = grid.row if rows is None else grid.row[rows]
    cand = gather_rows(grid.cells.value, cell, table)  # [B, K, Cc]
    out, d = signed_over(points, edges, cand, rows)
    return out, d > cell_slack(grid, points, cell, table)


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
    edges: RoadEdges, seg: torch.Tensor, rows: torch.Tensor | None
) -> tuple[torch.Tensor, ...]:
    """(start x, start y, (end - start) x, (end - start) y) of the segments ``seg`` [B, ...] of
    edge row b (or ``rows[b]``), each [B, ...]: from the grid's column table when there is one
    (one index for all four, contiguous results), else from the edges."""
    if edges.grid is not None:
        table = edges.grid.row if rows is None else edges.grid.row[rows]
        return gather_columns(edges.grid.segments.value, seg, table)
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
    "cell_of",
    "cell_slack",
    "grid_signed_distance",
    "joint_sign",
    "nearest_signed",
    "scene_edge_grid",
    "signed_over",
    "stack_cell_lists",
]
