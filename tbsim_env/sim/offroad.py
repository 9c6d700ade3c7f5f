"""Signed distance to road edges (positive = off-road), with the WOSAC sign convention.

Road edges are oriented with the road on their left. For a query point the closest segment over
all road edges is found; the sign is that of ``cross(q - a, b - a)`` (positive on the right),
corrected at polyline joints by the convexity rule of the WOSAC reference (docs/metrics.md).
This is the environment's fast 2-D check (over road edges simplified to within
``EDGE_SIMPLIFY_TOLERANCE``, looked up in the scenario's ``EdgeGrid``);
``tbsim_env.metrics`` carries the exact WOSAC feature.
"""

from __future__ import annotations

import torch

from tbsim_env.core import constants as C
from tbsim_env.core.torch_utils import cached_arange, gather_rows
from tbsim_env.sim.edge_grid import grid_signed_distance, nearest_signed, signed_over
from tbsim_env.sim.geometry import segment_projection
from tbsim_env.sim.state import RoadEdges

NO_EDGE_DISTANCE = C.NO_EDGE_DISTANCE
"""Distance reported when a scenario has no road edge (always on-road)."""


def point_segment_distance(
    points: torch.Tensor, edges: RoadEdges, segment_index: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Distance of each point to each (candidate) segment and the projection parameter.

    Args:
        points: [B, K, 2].
        edges: road edges.
        segment_index: optional [B, K, C] candidate segments per point (all E by default).

    Returns:
        (distance [B, K, C or E] with +inf for invalid segments, t [B, K, C or E]).
    """
    if segment_index is None:
        a, b, valid = edges.start[:, None], edges.end[:, None], edges.valid[:, None]
    else:
        a = gather_rows(edges.start, segment_index)
        b = gather_rows(edges.end, segment_index)
        valid = gather_rows(edges.valid, segment_index)
    t, dist = segment_projection(points[:, :, None], a, b - a)
    return torch.where(valid, dist, torch.full_like(dist, float("inf"))), t


def signed_distance_to_edges(
    points: torch.Tensor, edges: RoadEdges, segment_index: torch.Tensor | None = None
) -> torch.Tensor:
    """Signed distance of points to the nearest road edge.

    Args:
        points: [B, K, 2] m.
        edges: road-edge segments of the B scenarios.
        segment_index: optional [B, K, C] candidate segments per point; the nearest segment
            must be among them for the result to be exact.

    Returns:
        [B, K] m; positive off-road, negative on-road, ``NO_EDGE_DISTANCE`` without edges.
    """
    return _signed_and_unsigned(points, edges, segment_index)[0]


def _signed_and_unsigned(
    points: torch.Tensor, edges: RoadEdges, segment_index: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """(signed distance [B, K], unsigned distance to the nearest candidate [B, K])."""
    dist, t = point_segment_distance(points, edges, segment_index)
    return nearest_signed(points, edges, (dist, t), segment_index)


def grid_exact_signed_distance(
    points: torch.Tensor, edges: RoadEdges, rows: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Signed road-edge distance of points [B, K, 2] through the edges' grid.

    The points the grid cannot vouch for are recomputed over every segment of their scenario:
    eagerly all of them; under ``torch.compile`` (no data-dependent shapes) a budget of points
    fixed by their count (``recompute_budget``), the stale ones first. ``rows`` (eager only): point
    row b lies in the scenario of edge row ``rows[b]`` (``edge_grid.grid_signed_distance``).

    Returns:
        (signed distance [B, K] m, unresolved [B, K] bool: stale points beyond the budget,
        whose distance may be wrong; never set eagerly).
    """
    if edges.grid is None:
        out = signed_distance_to_edges(points, edges if rows is None else _edge_rows(edges, rows))
        return out, torch.zeros(out.shape, dtype=torch.bool, device=out.device)
    out, stale = grid_signed_distance(points, edges, edges.grid, rows)
    if not torch.compiler.is_compiling():
        if not bool(stale.any()):
            return out, stale  # all False
        bi, ki = stale.nonzero(as_tuple=True)
        out = out.index_put((bi, ki), _recompute(points, edges, bi, ki, rows))
        return out, torch.zeros_like(stale)
    k = points.shape[1]
    flat = stale.reshape(-1)
    budget = recompute_budget(flat.numel())
    pick = torch.topk(flat.to(points.dtype), budget, sorted=False).indices
    exact = _recompute(points, edges, pick // k, pick % k)
    out = out.reshape(-1).scatter(0, pick, exact).view_as(out)
    return out, flat.scatter(0, pick, False).view_as(stale)


def recompute_budget(points: int) -> int:
    """Points of ``points`` a compiled step recomputes over every segment: one in
    ``OFFROAD_RECOMPUTE_SHARE``, at least ``OFFROAD_RECOMPUTE_MIN``, at most
    ``OFFROAD_RECOMPUTE_BUDGET`` (and ``points``)."""
    share = max(C.OFFROAD_RECOMPUTE_MIN, points // C.OFFROAD_RECOMPUTE_SHARE)
    return min(points, C.OFFROAD_RECOMPUTE_BUDGET, share)


def _recompute(
    points: torch.Tensor,
    edges: RoadEdges,
    bi: torch.Tensor,
    ki: torch.Tensor,
    rows: torch.Tensor | None = None,
) -> torch.Tensor:
    """[P] signed distance of the points ``(bi, ki)`` [P] over every segment of their scene
    (edge row ``bi``, or ``rows[bi]`` with a row map)."""
    scene = bi if rows is None else rows[bi]
    every = cached_arange(edges.valid.shape[1], points.device).expand(len(bi), 1, -1)  # [P, 1, E]
    usable = edges.valid.index_select(0, scene).unsqueeze(1)
    return signed_over(points[bi, ki][:, None], edges, every, scene, usable)[0][:, 0]


def _edge_rows(edges: RoadEdges, rows: torch.Tensor) -> RoadEdges:
    """The segments of the edge rows ``rows`` [P] (no grid)."""
    return RoadEdges(
        start=edges.start[rows],
        end=edges.end[rows],
        valid=edges.valid[rows],
        prev_index=edges.prev_index[rows],
        next_index=edges.next_index[rows],
    )


def box_offroad_distance(
    corners: tuple[torch.Tensor, torch.Tensor], edges: RoadEdges, rows: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Max signed road-edge distance over the 4 box corners (positive: a corner is off-road).

    Args:
        corners: (x, y) [B, K, 4] box corners (``box_corner_xy``), m.
        edges: road edges of the scenarios.
        rows: optional [B] int64 (eager only): box row b lies in the scenario of edge row
            ``rows[b]``; row b itself by default.

    Returns:
        ([B, K] m, unresolved [B, K] bool: see ``grid_exact_signed_distance``).
    """
    b, k = corners[0].shape[:2]
    points = torch.stack(corners, -1).view(b, k * 4, 2)
    dist, stale = grid_exact_signed_distance(points, edges, rows)
    if torch.compiler.is_compiling():
        stale = stale.view(b, k, 4).any(-1)
    else:  # eagerly never stale
        stale = torch.zeros((b, k), dtype=torch.bool, device=dist.device)
    return dist.view(b, k, 4).amax(-1), stale
