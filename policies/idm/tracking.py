"""Following a route (torch, per step, batched over [B, N] agents): where the agent is along
its route, and the pure-pursuit curvature that steers it back onto it.

Routes are ``ROUTE_POINTS`` points ``ROUTE_SPACING`` apart in arc length, so a point at arc s
is an interpolation between points floor(s / spacing) and the next, without a search. The
functions work on a list of L agents (flat slot indices ``b * N + n`` into the [B, N] routes):
the present ones only, a fraction of the slots of real scenes.
"""

from __future__ import annotations

import torch

from policies.idm.params import ROUTE_SPACING
from tbsim_env.sim.geometry import to_local_xy

PROGRESS_WINDOW = 3
"""Route segments searched for the agent's projection each step, from the one of its last
progress on (7.5 m: more than a step's travel at any speed; progress never goes back)."""


def points_at(route: torch.Tensor, agent: torch.Tensor, arc: torch.Tensor) -> torch.Tensor:
    """Points of agents' routes at arc lengths, linearly extrapolated past either end.

    Args:
        route: [B, N, P, 2] m, every slot's route.
        agent: [L] int64 flat slot indices (b * N + n) of the agents asked about.
        arc: [L, K] m.

    Returns:
        [L, K, 2] m.
    """
    p = route.shape[2]
    pos = arc / ROUTE_SPACING
    idx = pos.floor().clamp(0, p - 2)
    frac = (pos - idx).unsqueeze(-1)
    flat = agent.unsqueeze(-1) * p + idx.long()  # [L, K]
    both = torch.cat([flat, flat + 1], -1).flatten()
    # Each (x, y) pair read as one complex word: a 1-d gather of words is about 4x faster on
    # the CPU than one of [R, 2] rows (a per-row copy), and the route table is large (B N P).
    words = torch.view_as_complex(route.reshape(-1, 2)).index_select(0, both)
    ab = torch.view_as_real(words).view(*arc.shape[:-1], 2, arc.shape[-1], 2)
    a, b = ab[..., 0, :, :], ab[..., 1, :, :]
    return a + frac * (b - a)


def advance_progress(
    route: torch.Tensor, agent: torch.Tensor, progress: torch.Tensor, xy: torch.Tensor
) -> torch.Tensor:
    """The arc length of each agent's projection onto its route, searched over
    ``PROGRESS_WINDOW`` segments from the one of the last progress; never backwards.

    Args:
        route: [B, N, P, 2] m.
        agent: [L] int64 flat slot indices.
        progress: [L] m, the last progress.
        xy: [L, 2] m, positions now.

    Returns:
        [L] m.
    """
    first = (progress / ROUTE_SPACING).floor()
    arcs = (first.unsqueeze(-1) + _WINDOW.to(xy.device)).clamp_min(0.0) * ROUTE_SPACING
    pts = points_at(route, agent, arcs)  # [L, W + 1, 2]
    px, py = pts[..., 0], pts[..., 1]  # x and y apart: no reductions over a dim of 2
    ax, ay = px[:, :-1], py[:, :-1]
    bx, by = px[:, 1:] - ax, py[:, 1:] - ay
    qx, qy = xy[:, 0:1] - ax, xy[:, 1:2] - ay
    t = ((qx * bx + qy * by) / (bx * bx + by * by).clamp_min(1e-12)).clamp(0.0, 1.0)
    ox, oy = qx - t * bx, qy - t * by
    best = (ox * ox + oy * oy).argmin(-1, keepdim=True)
    arc = arcs.gather(-1, best)[:, 0] + t.gather(-1, best)[:, 0] * ROUTE_SPACING
    return torch.maximum(arc, progress)


_WINDOW = torch.arange(PROGRESS_WINDOW + 1, dtype=torch.float32)


def pursuit_curvature(
    route: torch.Tensor,
    agent: torch.Tensor,
    progress: torch.Tensor,
    pose: torch.Tensor,
    lookahead: torch.Tensor,
) -> torch.Tensor:
    """Pure pursuit: the curvature of the circle through the agent, tangent to its heading,
    that reaches the route point ``lookahead`` ahead of its progress, 2 y / d^2 with (x, y)
    that point in the agent's frame and d its distance.

    Args:
        route: [B, N, P, 2] m.
        agent: [L] int64 flat slot indices.
        progress: [L] m.
        pose: [L, 3] (x m, y m, yaw rad).
        lookahead: [L] m (> 0).

    Returns:
        [L] 1/m, positive to the left.
    """
    target = points_at(route, agent, (progress + lookahead).unsqueeze(-1))[:, 0]
    x, y = to_local_xy(target[:, 0], target[:, 1], pose)
    return 2.0 * y / (x * x + y * y).clamp_min(1e-6)


__all__ = ["PROGRESS_WINDOW", "advance_progress", "points_at", "pursuit_curvature"]
