"""The nearest map pieces of many observers, without measuring every piece.

A real WOMD scene keeps up to 1,024 map pieces and an observer sees its 64 nearest, so the plain
search (``sim.knn.k_nearest`` over every piece) measures and ranks ~15x more pieces than it
keeps; at all agents controlled it was the largest part of an env step. Two indexes narrow it
down, both exact:

* ``PieceGrid`` (the observations: a bank's maps, shared by its rows): the road-edge grid's
  ``CellLists`` over the pieces' anchor points (``sim.edge_grid``; points are zero-length
  segments): every ``MAP_GRID_CELL`` cell lists its ``MAP_GRID_CANDIDATES`` pieces nearest to
  its centre. An observer measures its cell's list.
* ``PieceClusters`` (TrafficBots' per-scene cache, which joins single scenes into batches by
  concatenation and so needs fixed shapes): the pieces of a scene grouped into compact clusters
  (a k-d split of their anchor points into leaves of at most ``MAP_KNN_CLUSTER_SIZE``); per
  observer, the ``MAP_KNN_CLUSTERS`` clusters with the smallest lower bound on their pieces'
  distance are measured.

``nearest_pieces`` is the search: the observations' nearest map pieces and TrafficBots' map
neighbours of each agent. The result is the plain search's, exactly: no piece outside the
measured ones is nearer than a bound (the grid cell's, or the next cluster's), and the search
checks that its k-th distance stays below that bound (by ``MAP_KNN_MARGIN``, far more than
float rounding, so ranking buckets cannot tie across it). For an observer where it does not
hold (a sparse map beyond the listed pieces, or an observer far from every piece) it searches
every piece.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from tbsim_env.core import constants as C
from tbsim_env.core.torch_utils import gather_columns, gather_rows
from tbsim_env.sim.edge_grid import (
    cell_index,
    cell_rows,
    scene_edge_grid,
    slack_at,
    stack_cell_lists,
)
from tbsim_env.sim.knn import k_nearest, planar_distances, planar_distances_xy
from tbsim_env.sim.state import CellLists, Shared


@dataclass(frozen=True)
class PieceClusters:
    """Clusters of the valid map pieces of each row (padding: no member, +inf centre).

    Attributes:
        members: [B, G, S] int64 piece indices, ``M`` (one past the last piece: the
            sentinel of ``MapContext.knn_xy``-style arrays) for empty member slots; S is the
            largest cluster of the batch (at most the build's ``size``).
        center: [B, G, 2] float32 m, the mean of the members' anchor points (+inf: padding).
        radius: [B, G] float32 m, the largest member distance from the centre, rounded up.
        member_xy: [B, G, S, 2] float32 m, the members' anchor points (+inf for empty slots),
            so that a search gathers a cluster's points as one block.
    """

    members: torch.Tensor
    center: torch.Tensor
    radius: torch.Tensor
    member_xy: torch.Tensor

    @property
    def num_clusters(self) -> int:
        return int(self.members.shape[1])


@dataclass(frozen=True)
class PieceGrid(CellLists):
    """``CellLists`` of the valid map pieces of B maps (``build_piece_grid``): ``cells`` lists
    piece indices, and ``M`` (one past the last piece: the sentinel, +inf away) where a map
    has fewer pieces than a list holds.

    Attributes:
        xy: Shared [K, 2, M + 1] float32 m, the pieces' anchor points, a row each of x and y
            (+inf for invalid pieces and the sentinel column).
    """

    xy: Shared


def build_piece_grid(
    xy: torch.Tensor,
    valid: torch.Tensor,
    cell: float = C.MAP_GRID_CELL,
    count: int = C.MAP_GRID_CANDIDATES,
    margin: float = C.MAP_GRID_MARGIN,
) -> PieceGrid:
    """``PieceGrid`` of B maps (a bank's: its rows share the tables).

    Args:
        xy: [B, M, 2] float32 piece anchor points (as the search measures them).
        valid: [B, M] bool.
        cell, count, margin: cell size (m), pieces listed per cell, extent beyond the pieces
            (m); constants in ``tbsim_env.core.constants``.
    """
    xy_np, valid_np = xy.detach().cpu().float().numpy(), valid.detach().cpu().numpy()
    b, m = valid_np.shape
    grids = []
    for i in range(b):
        ids = np.flatnonzero(valid_np[i])
        pts = xy_np[i, ids]
        grid = scene_edge_grid(pts, pts, cell, count, margin)  # points: zero-length segments
        cells = ids[grid["cells"]] if len(ids) else np.full_like(grid["cells"], m)
        cells[:, len(ids) :] = m  # fewer pieces than a list: the sentinel, not repeats
        grids.append({**grid, "cells": cells})
    inf = torch.full((b, 1, 2), float("inf"), device=xy.device)
    points = torch.cat([xy.float().masked_fill(~valid[..., None], float("inf")), inf], 1)
    return PieceGrid(
        **stack_cell_lists(grids, cell, xy.device),
        xy=Shared(points.transpose(1, 2).contiguous()),
    )


def grid_candidates(
    grid: PieceGrid, me_xy: torch.Tensor, rows: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The pieces listed in each observer's grid cell.

    Args:
        grid: the maps' ``PieceGrid``.
        me_xy: [B, Q, 2] observer positions.
        rows: optional [B] int64: observer row b is in the map of grid row ``rows[b]``.

    Returns:
        (candidates [B, Q, Cc] int32 piece indices (``M`` for the sentinel), their distances
        [B, Q, Cc] m (+inf: the sentinel, invalid pieces), bound [B, Q] m: no piece left out
        is nearer; +inf when none is left).
    """
    flat = cell_index(grid, me_xy, rows)  # [B, Q]
    cand = cell_rows(grid.cells, flat)  # [B, Q, Cc] int32
    x, y = gather_columns(grid.xy.value, cand, grid.row if rows is None else grid.row[rows])
    return cand, planar_distances_xy(x, y, me_xy), slack_at(grid, me_xy, flat)


def _kd_leaves(xy: np.ndarray, ids: np.ndarray, size: int) -> list[np.ndarray]:
    """Indices ``ids`` split at the median of the wider axis until leaves hold <= ``size``."""
    if len(ids) <= size:
        return [ids]
    pts = xy[ids]
    axis = int(np.argmax(pts.max(0) - pts.min(0)))
    order = ids[np.argsort(pts[:, axis], kind="stable")]
    half = len(order) // 2
    return _kd_leaves(xy, order[:half], size) + _kd_leaves(xy, order[half:], size)


def scene_clusters(xy: np.ndarray, valid: np.ndarray, size: int) -> list[np.ndarray]:
    """Clusters of one scene's valid pieces: lists of piece indices (at most ``size`` each).

    Args:
        xy: [M, 2] float32 piece anchor points (as the search measures them).
        valid: [M] bool.
        size: members per cluster at most.
    """
    ids = np.flatnonzero(valid)
    return _kd_leaves(xy.astype(np.float64), ids, size) if len(ids) else []


def clusters_pay(num_pieces: int, width: int = C.MAP_KNN_CLUSTER_SIZE) -> bool:
    """Whether the clustered search measures fewer pieces than the plain one on a map of
    ``num_pieces`` pieces with clusters of ``width`` member slots (half of them at most)."""
    return num_pieces > 2 * C.MAP_KNN_CLUSTERS * width


def max_clusters(num_pieces: int, size: int = C.MAP_KNN_CLUSTER_SIZE) -> int:
    """The most clusters ``scene_clusters`` makes of at most ``num_pieces`` valid pieces."""
    if num_pieces <= size:
        return 1
    half = num_pieces // 2
    return max_clusters(half, size) + max_clusters(num_pieces - half, size)


def build_piece_clusters(
    xy: torch.Tensor,
    valid: torch.Tensor,
    size: int = C.MAP_KNN_CLUSTER_SIZE,
    fixed_shape: bool = False,
) -> PieceClusters:
    """``PieceClusters`` of a batch of maps.

    Args:
        xy: [B, M, 2] float32 piece anchor points.
        valid: [B, M] bool.
        size: members per cluster at most.
        fixed_shape: pad to ``max_clusters(M, size)`` clusters of ``size`` slots (the same
            shapes for every map of M pieces, so that single maps' clusters can be cached and
            joined into batches) instead of the batch's largest.
    """
    xy_np, valid_np = xy.detach().cpu().numpy(), valid.detach().cpu().numpy()
    b, m = valid_np.shape
    scenes = [scene_clusters(xy_np[i], valid_np[i], size) for i in range(b)]
    g = max(max((len(s) for s in scenes), default=0), 1)
    # Member slots: the largest leaf (median splits leave most leaves well under ``size``;
    # every padded slot would be measured and ranked by each search).
    width = max((len(ids) for leaves in scenes for ids in leaves), default=1)
    if fixed_shape:
        g, width = max_clusters(m, size), size
    members = np.full((b, g, width), m, np.int64)
    center = np.full((b, g, 2), np.inf, np.float32)
    radius = np.zeros((b, g), np.float32)
    for i, leaves in enumerate(scenes):
        for j, ids in enumerate(leaves):
            pts = xy_np[i, ids].astype(np.float64)
            mid = pts.mean(0).astype(np.float32)
            far = np.sqrt(((pts - mid.astype(np.float64)) ** 2).sum(-1)).max()
            members[i, j, : len(ids)] = ids
            center[i, j] = mid
            radius[i, j] = np.float32(far) + np.float32(C.MAP_KNN_RADIUS_PAD)
    dev = xy.device
    members_t = torch.from_numpy(members).to(dev)
    inf = torch.full((b, 1, 2), float("inf"), device=dev)
    points = torch.cat([xy.float().masked_fill(~valid[..., None], float("inf")), inf], 1)
    member_xy = gather_rows(points, members_t.flatten(1)).view(b, g, width, 2)
    return PieceClusters(
        members=members_t,
        center=torch.from_numpy(center).to(dev),
        radius=torch.from_numpy(radius).to(dev),
        member_xy=member_xy,
    )


def candidate_pieces(
    clusters: PieceClusters,
    me_xy: torch.Tensor,
    searched: int,
    rows: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The pieces of the ``searched`` clusters nearest (by lower bound) to each observer.

    Args:
        clusters: the batch's clusters (more than ``searched`` of them).
        me_xy: [B, Q, 2] observer positions.
        searched: clusters searched per observer.
        rows: optional [B] int64: observer row b searches the clusters of row ``rows[b]``
            (observers gathered from several rows; ``torch_utils.gather_rows``).

    Returns:
        (candidates [B, Q, searched * S] int64 piece indices (``M`` for empty slots),
        bound [B, Q] m: no piece outside the candidates is nearer; +inf when none is left,
        the candidates' anchor points [B, Q, searched * S, 2] m, +inf for empty slots).
    """
    center, radius = clusters.center, clusters.radius
    if rows is not None:
        center, radius = center.index_select(0, rows), radius.index_select(0, rows)
    d = torch.hypot(
        center[:, None, :, 0] - me_xy[:, :, None, 0],
        center[:, None, :, 1] - me_xy[:, :, None, 1],
    )
    lower = (d - radius[:, None]).clamp_min(0.0)  # [B, Q, G], +inf for padding
    lower, order = torch.topk(lower, searched + 1, dim=-1, largest=False, sorted=True)
    near = order[..., :searched]
    members = gather_rows(clusters.members, near, rows)  # [B, Q, searched, S]
    xy = gather_rows(clusters.member_xy, near, rows)  # [B, Q, searched, S, 2]
    return members.flatten(-2), lower[..., searched], xy.flatten(-3, -2)


def nearest_pieces(
    points: torch.Tensor,
    index: PieceGrid | PieceClusters | None,
    me_xy: torch.Tensor,
    k: int,
    within: float,
    rows: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """The k nearest map pieces of each observer ``me_xy`` [B, Q, 2]: (indices, distances)
    [B, Q, k], ranked by ``sim.knn.k_nearest`` over every piece. With ``rows`` [B] int64,
    observer row b is in the scene of map row ``rows[b]``.

    Eagerly on the CPU, the ``index`` narrows the search where it measures fewer pieces than
    there are (``_index_pays``); the observers it does not hold for (none on the real samples
    with the grid, ~1% with the clusters) are searched in full. A compiled graph cannot size
    tensors by that; it searches every piece (fused, that costs less there than the gathers
    of the narrowed search). Neither does a GPU, where finding those observers would cost a
    host sync every call, and measuring every piece costs idle lanes rather than time (the
    rule of ``torch_utils.listed``).

    Args:
        points: [B', 1, M, 2] piece anchor points, +inf for invalid pieces.
        index: their ``PieceGrid`` or ``PieceClusters`` (None: search every piece).
        me_xy: [B, Q, 2] observer positions.
        k: pieces per observer.
        within: the radius the caller masks beyond, metres (``k_nearest``).
        rows: optional [B] int64 map row of each observer row (default: row b itself).
    """
    m = points.shape[2]
    if not uses_index(index, m, me_xy):
        return _all_pieces(points if rows is None else points[rows], me_xy, k, within)
    if isinstance(index, PieceGrid):
        cand, dist, bound = grid_candidates(index, me_xy, rows)
    else:
        cand, bound, xy = candidate_pieces(index, me_xy, C.MAP_KNN_CLUSTERS, rows)
        dist = planar_distances(xy, me_xy)
    idx, top = k_nearest(dist, None, k, within, ids=(cand, m))
    fail_rows, cols = (~search_holds(top[..., -1], bound)).nonzero(as_tuple=True)
    if len(fail_rows):  # the few observers it does not hold for: every piece
        scene = fail_rows if rows is None else rows[fail_rows]
        full_idx, full_top = _all_pieces(points[scene], me_xy[fail_rows, cols, None], k, within)
        idx = idx.long().index_put((fail_rows, cols), full_idx[:, 0])
        top = top.index_put((fail_rows, cols), full_top[:, 0])
    return idx, top


def uses_index(index: PieceGrid | PieceClusters | None, m: int, me_xy: torch.Tensor) -> bool:
    """Whether ``nearest_pieces`` of the observers ``me_xy`` [B, Q, 2] among ``m`` pieces
    searches through ``index`` (else it measures every piece)."""
    eager_cpu = me_xy.device.type == "cpu" and not torch.compiler.is_compiling()
    observers = me_xy.shape[0] * me_xy.shape[1]
    return eager_cpu and _index_pays(index, m, observers, me_xy.shape[0])


def _index_pays(index: PieceGrid | PieceClusters | None, m: int, observers: int, maps: int) -> bool:
    """Whether searching through ``index`` costs less than measuring all ``m`` pieces for
    ``observers`` observers of ``maps`` maps."""
    if isinstance(index, PieceGrid):
        return m > index.cells.value.shape[-1] and observers * m >= C.MAP_GRID_MIN_WORK
    return (
        index is not None
        and index.num_clusters > C.MAP_KNN_CLUSTERS
        and clusters_pay(m, index.members.shape[-1])
        and observers >= C.MAP_KNN_MIN_OBSERVERS * maps
    )


def _all_pieces(
    points: torch.Tensor, me_xy: torch.Tensor, k: int, within: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """``k_nearest`` over every piece ``points`` [R, 1, M, 2] (+inf for padding) of the
    observers ``me_xy`` [R, Q, 2]: (indices, distances) [R, Q, k]."""
    return k_nearest(planar_distances(points, me_xy), None, k, within)


def search_holds(kth: torch.Tensor, bound: torch.Tensor) -> torch.Tensor:
    """[B, Q] bool: the candidates' k-th distance ``kth`` stays ``MAP_KNN_MARGIN`` below the
    ``bound`` on every other piece (or no other piece is left), so the candidates' k nearest
    are the k nearest of all pieces. Never where ``kth`` is +inf: fewer than k valid pieces
    were measured, and the plain search fills such entries with pieces, not the sentinel."""
    return torch.isfinite(kth) & (torch.isinf(bound) | (kth + C.MAP_KNN_MARGIN <= bound))


__all__ = [
    "PieceClusters",
    "PieceGrid",
    "build_piece_grid",
    "grid_candidates",
    "build_piece_clusters",
    "candidate_pieces",
    "clusters_pay",
    "max_clusters",
    "nearest_pieces",
    "scene_clusters",
    "search_holds",
    "uses_index",
]
