"""Where an IDM agent must stand (torch, per step): red and yellow signals, stop signs (a
full stop at the line, then go when the junction is clear) and crosswalks with a pedestrian
on them. Each gives the distance (m) from the agent's front bumper to the line that holds it,
+inf where none does (the policy stands ``IDMConfig.stop_gap`` before it). Functions take L
agents (``tracking``): [L, K] per stop line.
"""

from __future__ import annotations

import torch

from policies.idm.params import MOVING_SPEED, SIGN_STOP_ZONE, STOPPED_SPEED
from policies.idm.tracking import points_at
from tbsim_env.core.constants import TLState


def _per_agent(table: torch.Tensor, row: torch.Tensor, col: torch.Tensor) -> torch.Tensor:
    """``table[row[l], col[l, k]]`` [L, K] of a [B, S] table (``col`` -1 reads column 0)."""
    s = table.shape[1]
    flat = row.unsqueeze(-1) * s + col.clamp_min(0)
    return table.flatten().index_select(0, flat.flatten()).view_as(col)


def signal_distance(
    line_gap: torch.Tensor,
    line: tuple[torch.Tensor, torch.Tensor],
    tl: tuple[torch.Tensor, torch.Tensor],
    speed: torch.Tensor,
    comfort_decel: torch.Tensor,
) -> torch.Tensor:
    """Distance to stand before the first signal stop line that holds the agent.

    A stop line holds the agent while it lies ahead and its light is red, or yellow and the
    agent can stop before it braking at no more than twice its comfortable deceleration (else
    it goes on through the yellow).

    Args:
        line_gap: [L, K] m from the front bumper to each stop line.
        line: (batch row [L] int64 of each agent, signal row [L, K] int64 of each line,
            -1 padding).
        tl: (state [B, S] ``TLState``, valid [B, S] bool) of the signals now.
        speed: [L] m/s.
        comfort_decel: [L] m/s^2.

    Returns:
        [L] m.
    """
    row, sig = line
    light = _per_agent(tl[0], row, sig)
    known = _per_agent(tl[1], row, sig) & (sig >= 0)
    ahead = line_gap > 0.0
    need = speed.unsqueeze(-1).clamp_min(0.0) ** 2 / (2.0 * line_gap.clamp_min(0.1))
    can_stop = need <= 2.0 * comfort_decel.unsqueeze(-1)
    red = light == int(TLState.STOP)
    yellow = (light == int(TLState.CAUTION)) & can_stop
    holds = known & ahead & (red | yellow)
    return torch.where(holds, line_gap, float("inf")).amin(-1)


def sign_progress(
    line_gap: torch.Tensor, stopped: torch.Tensor, cleared: torch.Tensor, speed: torch.Tensor
) -> torch.Tensor:
    """[L, K] bool: the stop-sign lines the agent has now made its full stop at (slower
    than ``STOPPED_SPEED`` within ``SIGN_STOP_ZONE`` of the line), or had before."""
    close = (line_gap > -1.0) & (line_gap < SIGN_STOP_ZONE)
    return stopped | (close & (speed.unsqueeze(-1).abs() < STOPPED_SPEED)) | cleared


def junction_clear(
    waiting: torch.Tensor,
    lines: tuple[torch.Tensor, torch.Tensor],
    agent: torch.Tensor,
    others: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    radius: float,
) -> torch.Tensor:
    """[L, K] bool: no other agent moves (faster than ``MOVING_SPEED``) within ``radius``
    of the stop lines where agents wait (False elsewhere).

    Args:
        waiting: [L, K] bool, stopped at the line and not yet cleared.
        lines: (route [B, N, P, 2] m of every slot, arc [L, K] m of each stop line along the
            agent's route; +inf padding); only the lines waited at are looked up.
        agent: [L] int64 flat slot indices (b * N + n) of the L agents.
        others: (xy [B, N, 2] m, speed [B, N] m/s, valid [B, N] bool) of every slot.
        radius: m.
    """
    out = torch.zeros_like(waiting)
    if not bool(waiting.any()):
        return out
    xy, speed, valid = others
    n = valid.shape[1]
    li, k = waiting.nonzero(as_tuple=True)
    route, arc = lines
    slot = agent.index_select(0, li)
    line = points_at(route, slot, arc[li, k].clamp(max=1e6).unsqueeze(-1))  # [W, 1, 2]
    b, i = slot // n, slot % n
    d = xy[b] - line  # [W, N, 2]
    near = (d * d).sum(-1) < radius * radius
    moving = valid[b] & (speed[b].abs() > MOVING_SPEED)
    moving[torch.arange(b.shape[0], device=b.device), i] = False
    out[li, k] = ~(near & moving).any(-1)
    return out


def sign_distance(line_gap: torch.Tensor, cleared: torch.Tensor) -> torch.Tensor:
    """[L] m to stand before the first stop-sign line ahead not yet cleared."""
    holds = (line_gap > -1.0) & ~cleared
    return torch.where(holds, line_gap, float("inf")).amin(-1)


def crosswalks_occupied(
    polygons: torch.Tensor, walkers: tuple[torch.Tensor, torch.Tensor], xy: torch.Tensor
) -> torch.Tensor:
    """[B, W] bool: a pedestrian stands inside each crosswalk polygon.

    Args:
        polygons: [B, W, V, 2] m (padding: repeated vertices or all-zero polygons).
        walkers: (row [P], slot [P]) int64 of the valid pedestrians.
        xy: [B, N, 2] m of every slot.
    """
    b, w = polygons.shape[:2]
    count = torch.zeros(b * w, dtype=torch.int32, device=polygons.device)
    row, slot = walkers
    if row.numel() == 0:
        return count.view(b, w) > 0
    # Only the (walker, crosswalk) pairs inside the crosswalk's bounding box are tested.
    n = xy.shape[1]
    p = xy.reshape(-1, 2).index_select(0, row * n + slot)  # [P, 2]
    x, y = p[:, 0:1], p[:, 1:2]  # [P, 1]
    lo, hi = polygons.amin(2), polygons.amax(2)  # [B, W, 2]
    box = torch.stack([lo[..., 0], lo[..., 1], hi[..., 0], hi[..., 1]]).index_select(1, row)
    inbox = (x >= box[0]) & (y >= box[1]) & (x <= box[2]) & (y <= box[3])  # [P, W]
    k, c = inbox.nonzero(as_tuple=True)
    poly = polygons.flatten(0, 1).index_select(0, row.index_select(0, k) * w + c)  # [K, V, 2]
    nxt = poly.roll(-1, dims=1)
    px, py = x.index_select(0, k), y.index_select(0, k)  # [K, 1]
    ay, by = poly[..., 1], nxt[..., 1]
    crosses = (ay > py) != (by > py)
    dy = torch.where(by == ay, torch.full_like(ay, 1e-9), by - ay)
    x_at = poly[..., 0] + (py - ay) * (nxt[..., 0] - poly[..., 0]) / dy
    inside = ((crosses & (px < x_at)).sum(-1) % 2) == 1  # [K]
    count.index_add_(0, row.index_select(0, k) * w + c, inside.to(torch.int32))
    return count.view(b, w) > 0


def crosswalk_distance(
    entry_gap: torch.Tensor, line: tuple[torch.Tensor, torch.Tensor], occupied: torch.Tensor
) -> torch.Tensor:
    """[L] m to stand before the first occupied crosswalk ahead.

    Args:
        entry_gap: [L, K] m from the front bumper to where the route enters each crosswalk.
        line: (batch row [L] int64, crosswalk row [L, K] int64, -1 padding).
        occupied: [B, W] bool.
    """
    row, cw = line
    busy = _per_agent(occupied, row, cw) & (cw >= 0)
    return torch.where(busy & (entry_gap > 0.0), entry_gap, float("inf")).amin(-1)


__all__ = [
    "crosswalk_distance",
    "crosswalks_occupied",
    "junction_clear",
    "sign_distance",
    "sign_progress",
    "signal_distance",
]
