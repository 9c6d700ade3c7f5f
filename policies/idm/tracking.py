"""Following a route (torch, per step, batched over [B, N] agents): where the agent is along
its route, and the pure-pursuit curvature that steers it back onto it.

Routes are ``ROUTE_POINTS`` points ``ROUTE_SPACING`` apart in arc length, so a point at arc s
is an interpolation between points floor(s / spacing) and the next, without a search.
"""

from __future__ import annotations

import torch

from policies.idm.params import ROUTE_SPACING
from tbsim_env.sim.geometry import to_local_xy

PROGRESS_WINDOW = 4
"""Route segments searched for the agent's projection each step, from the one before its last
progress (10 m: more than a step's travel at any speed)."""


def points_at(route: torch.Tensor, arc: torch.Tensor) -> torch.Tensor:
    """Points of routes at arc lengths, linearly extrapolated past either end.

    Args:
        route: [B, N, P, 2] m.
        arc: [B, N, K] m.

    Returns:
        [B, N, K, 2] m.
    """
    p = route.shape[2]
    pos = arc / ROUTE_SPACING
    idx = pos.floor().clamp(0, p - 2)
    frac = (pos - idx).unsqueeze(-1)
    i = idx.long().unsqueeze(-1).expand(*idx.shape, 2)
    a = route.gather(2, i)
    b = route.gather(2, i + 1)
    return a + frac * (b - a)


def advance_progress(route: torch.Tensor, progress: torch.Tensor, xy: torch.Tensor) -> torch.Tensor:
    """The arc length of each agent's projection onto its route, searched over
    ``PROGRESS_WINDOW`` segments from the one before the last progress; never backwards.

    Args:
        route: [B, N, P, 2] m.
        progress: [B, N] m, the last progress.
        xy: [B, N, 2] m, positions now.

    Returns:
        [B, N] m.
    """
    p = route.shape[2]
    first = (progress / ROUTE_SPACING).floor().long() - 1
    k = first.unsqueeze(-1) + torch.arange(PROGRESS_WINDOW + 1, device=route.device)
    k = k.clamp(0, p - 1)  # [B, N, W + 1] point indices
    pts = route.gather(2, k.unsqueeze(-1).expand(*k.shape, 2))
    a, ab = pts[..., :-1, :], pts[..., 1:, :] - pts[..., :-1, :]
    len2 = (ab * ab).sum(-1).clamp_min(1e-12)
    t = (((xy.unsqueeze(-2) - a) * ab).sum(-1) / len2).clamp(0.0, 1.0)
    off = xy.unsqueeze(-2) - (a + t.unsqueeze(-1) * ab)
    dist2 = (off * off).sum(-1)
    best = dist2.argmin(-1, keepdim=True)
    seg = k[..., :-1].gather(-1, best)[..., 0].to(progress.dtype)
    arc = (seg + t.gather(-1, best)[..., 0]) * ROUTE_SPACING
    return torch.maximum(arc, progress)


def pursuit_curvature(
    route: torch.Tensor, progress: torch.Tensor, pose: torch.Tensor, lookahead: torch.Tensor
) -> torch.Tensor:
    """Pure pursuit: the curvature of the circle through the agent, tangent to its heading,
    that reaches the route point ``lookahead`` ahead of its progress, 2 y / d^2 with (x, y)
    that point in the agent's frame and d its distance.

    Args:
        route: [B, N, P, 2] m.
        progress: [B, N] m.
        pose: [B, N, 3] (x m, y m, yaw rad).
        lookahead: [B, N] m (> 0).

    Returns:
        [B, N] 1/m, positive to the left.
    """
    target = points_at(route, (progress + lookahead).unsqueeze(-1))[..., 0, :]
    x, y = to_local_xy(target[..., 0], target[..., 1], pose)
    return 2.0 * y / (x * x + y * y).clamp_min(1e-6)


__all__ = ["PROGRESS_WINDOW", "advance_progress", "points_at", "pursuit_curvature"]
