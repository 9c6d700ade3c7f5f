"""The road-keeping rule around the TrafficBots network (``InferenceConfig.road_keeping``).

A vehicle on the road whose action would carry a front corner across a road edge, from the
road side to the outside, within ``RoadKeeping.horizon`` seconds (constant action) gets the
nearest yaw rate among ``RoadKeeping.yaw_offsets`` that does not, or brakes if none does.

The test needs no global on/off-road status: a road-edge segment (a -> a + d) has the road on
its left (WOSAC's sign rule: a point p is outside where cross(p - a, d) > 0, as
``tbsim_env.sim.edge_grid.joint_sign``), so a corner path c0 -> c1 leaves the road across it
where cross(c0 - a, d) < 0 < cross(c1 - a, d) and the path meets the segment. A vehicle that
stands in a lot and drives onto the road crosses edges the other way and is left alone.

The edges are the road-edge map tokens the network sees (``MapTokens.node_pose``, classes
``ROAD_EDGE_BOUNDARY`` / ``ROAD_EDGE_MEDIAN``); each vehicle tests the segments of its
``RoadKeeping.pieces`` edge pieces nearest (by first node) to the middle of its path.

Off in the shipped config (``InferenceConfig(road_keeping=RoadKeeping())`` turns it on): it
breaks the NPC's frame invariance (``RoadKeeping`` says by how much and why).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from tbsim_env.core import constants as C
from tbsim_env.core.boxes import corners_from_offsets
from tbsim_env.core.torch_utils import const, gather_rows
from tbsim_env.sim.dynamics import action_limits
from tbsim_env.sim.geometry import cos_sin

if TYPE_CHECKING:
    from policies.trafficbots.config import RoadKeeping
    from policies.trafficbots.map_encoder import MapTokens

_EDGE_CLASSES = (int(C.MapClass.ROAD_EDGE_BOUNDARY), int(C.MapClass.ROAD_EDGE_MEDIAN))


def _cross(ux: torch.Tensor, uy: torch.Tensor, vx: torch.Tensor, vy: torch.Tensor):
    return ux * vy - uy * vx


def front_corner_paths(
    pose: torch.Tensor, speed: torch.Tensor, action: torch.Tensor, size: torch.Tensor, t: float
) -> tuple[torch.Tensor, torch.Tensor]:
    """Where the two front corners of each box are now and after ``t`` seconds of a constant
    action (unicycle, speed not below zero; the midpoint heading over the interval).

    Args:
        pose: [B, N, 3] (x m, y m, yaw rad).
        speed: [B, N] m/s.
        action: [B, N, A, 2] A candidate (acceleration m/s^2, yaw rate rad/s) each.
        size: [B, N, 2] (length, width) m.
        t: seconds.

    Returns:
        (now, then): [B, N, A, 2 corners, 2] m.
    """
    x, y, yaw = (v[..., None] for v in pose.unbind(-1))  # [B, N, 1]
    half_l, half_w = (0.5 * v[..., None, None] for v in size.unbind(-1))  # [B, N, 1, 1]
    front = (half_l, const((1.0, -1.0), pose) * half_w)  # left and right front corner offsets

    def corners(cx, cy, heading):  # [B, N, A] each -> [B, N, A, 2, 2]
        at = corners_from_offsets(cx[..., None], cy[..., None], cos_sin(heading[..., None]), front)
        return torch.stack(at, -1)

    travelled = (speed[..., None] + 0.5 * t * action[..., 0]).clamp_min(0.0) * t
    mid = yaw + 0.5 * t * action[..., 1]
    end_x, end_y = x + travelled * torch.cos(mid), y + travelled * torch.sin(mid)
    now = corners(x, y, yaw).expand(-1, -1, action.shape[2], -1, -1)
    return now, corners(end_x, end_y, yaw + t * action[..., 1])


def nearest_edge_segments(
    mp: MapTokens, at: torch.Tensor, pieces: int, rows: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The road-edge segments of the ``pieces`` edge pieces nearest to each point.

    Args:
        mp: the map tokens (B rows, M pieces of P nodes).
        at: [R, N, 2] query points m.
        pieces: pieces per point.
        rows: optional [R] int64 map row of each query row (default: row r itself).

    Returns:
        (start [R, N, S, 2], direction [R, N, S, 2] m, valid [R, N, S] bool), S = pieces *
        (P - 1); invalid where the piece is not a road edge or a node is missing.
    """
    node = mp.node_pose[..., :2]  # [B, M, P, 2]
    edge = torch.zeros_like(mp.valid)
    for c in _EDGE_CLASSES:
        edge |= mp.cls == c
    anchor = torch.where(edge[..., None], node[..., 0, :], float("inf"))  # [B, M, 2]
    if rows is not None:
        anchor = anchor.index_select(0, rows)
    d = torch.hypot(
        anchor[:, None, :, 0] - at[..., 0, None], anchor[:, None, :, 1] - at[..., 1, None]
    )  # [R, N, M]
    k = min(pieces, d.shape[-1])
    near = torch.topk(d, k, dim=-1, largest=False).indices  # [R, N, k]
    # Only the pieces found are cut into segments.
    xy = gather_rows(node.flatten(2), near, rows).unflatten(-1, node.shape[-2:])  # [R, N, k, P, 2]
    ok = gather_rows(mp.node_valid, near, rows) & gather_rows(edge, near, rows)[..., None]
    start = xy[..., :-1, :]
    return (
        start.flatten(2, 3),
        (xy[..., 1:, :] - start).flatten(2, 3),
        (ok[..., :-1] & ok[..., 1:]).flatten(2),
    )


def leaves_road(
    now: torch.Tensor,
    then: torch.Tensor,
    segments: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
) -> torch.Tensor:
    """Whether a corner path crosses a road-edge segment from the road side to the outside.

    Args:
        now, then: [B, N, A, 2, 2] corner positions (``front_corner_paths``).
        segments: (start, direction, valid) [B, N, S, ...] (``nearest_edge_segments``).

    Returns:
        [B, N, A] bool.
    """
    a, d, ok = (s[:, :, None, None] for s in segments)  # [B, N, 1, 1, S, ...]
    c0, c1 = now[..., None, :], then[..., None, :]  # [B, N, A, 2, 1, 2]
    ax, ay, dx, dy = a[..., 0], a[..., 1], d[..., 0], d[..., 1]
    side0 = _cross(c0[..., 0] - ax, c0[..., 1] - ay, dx, dy)
    side1 = _cross(c1[..., 0] - ax, c1[..., 1] - ay, dx, dy)
    ex, ey = c1[..., 0] - c0[..., 0], c1[..., 1] - c0[..., 1]
    u0 = _cross(ax - c0[..., 0], ay - c0[..., 1], ex, ey)
    u1 = _cross(ax + dx - c0[..., 0], ay + dy - c0[..., 1], ex, ey)
    crossing = ok & (side0 < 0) & (side1 > 0) & (u0 * u1 <= 0)
    return crossing.flatten(-2).any(-1)


def keep_on_road(
    action: torch.Tensor,
    speed: torch.Tensor,
    now: tuple[torch.Tensor, torch.Tensor],
    agents: tuple[torch.Tensor, torch.Tensor, MapTokens],
    rule: RoadKeeping,
) -> torch.Tensor:
    """Vehicle actions that keep their front corners on the road for ``rule.horizon`` s.

    Vehicles below ``rule.min_speed`` and other agents keep their actions. A vehicle whose
    action leaves the road takes the first yaw rate ``action + offset`` (``rule.yaw_offsets``,
    each tried with both signs, within the type's limit) that does not; if none does, it
    keeps its yaw rate and brakes at the type's limit.

    Args:
        action: [B, N, 2] (acceleration m/s^2, yaw rate rad/s).
        speed: [B, N] signed speed m/s.
        now: (pose [B, N, 3], valid [B, N] bool) at this step.
        agents: (``ObjectType`` [B, N], (length, width) [B, N, 2] m, the map tokens).
        rule: the rule's parameters.

    Returns:
        [B, N, 2].
    """
    (pose, valid), (ag_type, size, mp) = now, agents
    moving = valid & (ag_type == int(C.ObjectType.VEHICLE)) & (speed >= rule.min_speed)
    b, n = moving.nonzero(as_tuple=True)
    if len(b) == 0:
        return action
    # The moving vehicles as rows of their own, [V, 1, ...] (map row b of vehicle row v).
    p, v, sz = pose[b, n][:, None], speed[b, n][:, None], size[b, n][:, None]
    base = action[b, n]  # [V, 2]
    mid = front_corner_paths(p, v, base[:, None, None], sz, 0.5 * rule.horizon)[1]
    segments = nearest_edge_segments(mp, mid[:, :, 0].mean(-2), rule.pieces, b)  # [V, 1, S]
    paths = front_corner_paths(p, v, base[:, None, None], sz, rule.horizon)
    go = leaves_road(*paths, segments)[:, 0, 0].nonzero()[:, 0]  # [L] leaving vehicle rows
    if len(go) == 0:
        return action
    max_acc, max_yaw = (x[b[go], n[go]] for x in action_limits(ag_type))
    base = base[go]
    offsets = const(rule.yaw_offsets, action)
    offsets = torch.stack([offsets, -offsets], -1).flatten()  # +o1, -o1, +o2, ...
    yaw = torch.maximum(torch.minimum(base[:, 1:] + offsets, max_yaw[:, None]), -max_yaw[:, None])
    tried = torch.stack([base[:, :1].expand_as(yaw), yaw], -1)  # [L, A, 2]
    paths = front_corner_paths(p[go], v[go], tried[:, None], sz[go], rule.horizon)
    ok = ~leaves_road(*paths, tuple(x[go] for x in segments))[:, 0]  # [L, A]
    fixed = tried[torch.arange(len(go), device=go.device), ok.to(torch.uint8).argmax(-1)]
    brake = torch.stack([-max_acc, base[:, 1]], -1)
    out = action.clone()
    out[b[go], n[go]] = torch.where(ok.any(-1, keepdim=True), fixed, brake)
    return out
