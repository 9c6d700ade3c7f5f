"""Signed distance to road edges (positive = off-road), with the WOSAC sign convention.

Road edges are oriented with the road on their left. For a query point the closest segment over
all road edges is found; the sign is that of ``cross(q - a, b - a)`` (positive on the right),
corrected at polyline joints by the convexity rule of the WOSAC reference (docs/wosac.md 4.4).
This is the environment's fast 2-D check; ``tbsim_env.metrics`` carries the exact WOSAC feature.
"""

from __future__ import annotations

import torch

from tbsim_env.sim.collision import box_corners
from tbsim_env.sim.state import RoadEdges

NO_EDGE_DISTANCE = -1.0e10
"""Distance reported when a scenario has no road edge (always on-road)."""


def _cross(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def _take(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """x: [B, E, ...], idx: [B, K] -> [B, K, ...]."""
    if x.dim() == 2:
        return x.gather(1, idx)
    return x.gather(1, idx[..., None].expand(-1, -1, x.shape[-1]))


def signed_distance_to_edges(points: torch.Tensor, edges: RoadEdges) -> torch.Tensor:
    """Signed distance of points to the nearest road edge.

    Args:
        points: [B, K, 2] m.
        edges: road-edge segments of the B scenarios.

    Returns:
        [B, K] m; positive off-road, negative on-road, ``NO_EDGE_DISTANCE`` without edges.
    """
    a, b = edges.start[:, None], edges.end[:, None]  # [B, 1, E, 2]
    ab = b - a
    q = points[:, :, None]  # [B, K, 1, 2]
    len2 = (ab * ab).sum(-1)
    t = torch.where(
        len2 > 0, ((q - a) * ab).sum(-1) / len2.clamp_min(1e-12), torch.zeros_like(len2)
    )
    closest = a + t.clamp(0.0, 1.0)[..., None] * ab
    dist = torch.linalg.vector_norm(q - closest, dim=-1)
    dist = torch.where(edges.valid[:, None], dist, torch.full_like(dist, float("inf")))
    best = dist.argmin(-1)  # [B, K]
    d = dist.gather(2, best[..., None])[..., 0]
    t_best = t.gather(2, best[..., None])[..., 0]

    def side(seg: torch.Tensor) -> torch.Tensor:
        sa, sab = _take(edges.start, seg), _take(edges.end, seg) - _take(edges.start, seg)
        return torch.sign(_cross(points - sa, sab)), sab

    n, dir_this = side(best)
    prev = _take(edges.prev_index, best)
    nxt = _take(edges.next_index, best)
    n_prev, dir_prev = side(prev)
    n_next, dir_next = side(nxt)
    convex_prev = _cross(dir_prev, dir_this) > 0
    convex_next = _cross(dir_this, dir_next) > 0
    with_prev = torch.where(convex_prev, torch.maximum(n, n_prev), torch.minimum(n, n_prev))
    with_next = torch.where(convex_next, torch.maximum(n, n_next), torch.minimum(n, n_next))
    sign = torch.where((t_best < 0) & (prev != best), with_prev, n)
    sign = torch.where((t_best > 1) & (nxt != best), with_next, sign)
    out = sign * d
    has_edge = edges.valid.any(-1, keepdim=True)
    return torch.where(has_edge, out, torch.full_like(out, NO_EDGE_DISTANCE))


def box_offroad_distance(pose: torch.Tensor, size: torch.Tensor, edges: RoadEdges) -> torch.Tensor:
    """Max signed road-edge distance over the 4 box corners (positive: a corner is off-road).

    Args:
        pose: [B, K, 3]; size: [B, K, 2] (length, width).
        edges: road edges.

    Returns:
        [B, K] m.
    """
    corners = box_corners(pose, size[..., 0], size[..., 1])  # [B, K, 4, 2]
    bsz, k = pose.shape[:2]
    dist = signed_distance_to_edges(corners.reshape(bsz, k * 4, 2), edges)
    return dist.view(bsz, k, 4).amax(-1)
