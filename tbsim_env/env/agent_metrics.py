"""Per-agent step metrics of the controlled agents: collision, off-road, progress, goal, log gap.

Pure functions over a ``SimState`` and a set of query agents ``[B, Q]``; they feed both the
rewards and the ``infos`` of ``TrafficEnv``. Collision and off-road need no log. Progress, goal
and log divergence compare with the log: where it has no state (past an agent's last logged
step, or every step after the current one in a history-only scene) they are masked to finite
values (no progress, no goal, zero divergence) instead of failing.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import torch

from tbsim_env.core.boxes import corner_offsets, corners_from_offsets
from tbsim_env.core.torch_utils import cached_arange, const, gather_rows, listed, valid_first
from tbsim_env.sim.collision import (
    agent_distances,
    collided_with_others,
    near_limits,
)
from tbsim_env.sim.geometry import cos_sin
from tbsim_env.sim.offroad import box_offroad_distance
from tbsim_env.sim.state import RoadEdges, SimState


@dataclass(frozen=True)
class Route:
    """The logged route of each query agent, and what ``step_metrics`` needs of it that does not
    change in an episode (the ``build_route`` fields after ``segment_arc``; None in a route
    built by hand, then ``step_metrics`` derives them on every call).

    Attributes:
        points: [B, Q, T, 2] logged positions (invalid steps repeat the previous valid one).
        arc: [B, Q, T] cumulative arc length m.
        goal: [B, Q, 2] last valid logged position.
        valid: [B, Q] the agent has at least one valid logged position.
        segments: [B, Q, 2, T - 1] derived from ``points`` when not given: segment vectors
            (point t + 1 - point t) m, x and y apart (contiguous rows: what the per-step
            projection reads fastest).
        segment_length2: [B, Q, T - 1] derived: squared segment lengths clamped at 1e-9 m^2.
        segment_length: [B, Q, T - 1] derived: segment lengths m.
        segment_start: [B, Q, 2, T - 1] derived: ``points[..., :-1, :]``, x and y apart.
        segment_arc: [B, Q, T - 1] derived: ``arc[..., :-1]``.
        size: [B, Q, 2] (length, width) m of the agent.
        radius: [B, Q] m, half diagonal (bounding-circle radius) of its box.
        near_limit: [B, Q, N] m, ``collision.near_limits`` of the agent against every slot
            (the prefilter where the step measures every slot, ``valid_first``).
        corner_along: [B, Q, 4] m, its box corners along the heading (``corner_offsets``).
        corner_across: [B, Q, 4] m, across the heading.
        log_xy: [B, Q, T, 2] logged positions (not filled), m.
        log_valid: [B, Q, T] bool, the log has the agent.
    """

    points: torch.Tensor
    arc: torch.Tensor
    goal: torch.Tensor
    valid: torch.Tensor
    segments: torch.Tensor | None = field(default=None)
    segment_length2: torch.Tensor | None = field(default=None)
    segment_length: torch.Tensor | None = field(default=None)
    segment_start: torch.Tensor | None = field(default=None)
    segment_arc: torch.Tensor | None = field(default=None)
    size: torch.Tensor | None = field(default=None)
    radius: torch.Tensor | None = field(default=None)
    near_limit: torch.Tensor | None = field(default=None)
    corner_along: torch.Tensor | None = field(default=None)
    corner_across: torch.Tensor | None = field(default=None)
    log_xy: torch.Tensor | None = field(default=None)
    log_valid: torch.Tensor | None = field(default=None)

    def __post_init__(self) -> None:
        if self.segments is None:
            ab = self.points[..., 1:, :] - self.points[..., :-1, :]
            len2 = (ab * ab).sum(-1)
            object.__setattr__(self, "segments", ab.transpose(-1, -2).contiguous())
            object.__setattr__(self, "segment_length2", len2.clamp_min(1e-9))
            object.__setattr__(self, "segment_length", len2.clamp_min(0).sqrt())
        if self.segment_start is None:
            start = self.points[..., :-1, :].transpose(-1, -2).contiguous()
            object.__setattr__(self, "segment_start", start)
            object.__setattr__(self, "segment_arc", self.arc[..., :-1])


@dataclass(frozen=True)
class StepMetrics:
    """Metrics of the query agents at one step, each [B, Q].

    Attributes:
        collision: bool, overlaps another present agent.
        offroad: bool, a box corner is beyond a road edge.
        offroad_distance: m, signed (positive off-road); 0 for an agent no longer present
            (it left the scene), which is then not off-road either.
        progress: m, arc length of the projection on the logged route (history included:
            where the log ends at the start, e.g. a history-only scene, it stays at the
            route's end and gains nothing).
        goal_distance: m, to the last valid logged position (see ``goal_mask`` for when that
            counts as a goal).
        log_divergence: m, distance to the logged position at this step, 0 where the log has
            no state (``log_valid`` False: after the agent's log ends, or after a history-only
            scene's current step).
        log_valid: bool, the log has the agent at this step.
        agent_distance: (distances [B, Q, C] m, slots [B, C] int64 or None): centre distances
            to the agent slots ``slots`` (``torch_utils.valid_first``: every valid slot, then
            invalid ones), or to every slot (C = N) where ``slots`` is None;
            ``observe_indexed`` of the same poses reuses them. None when not computed.
        offroad_stale: [B, Q] bool, set only under ``torch.compile``: present agents with a
            box corner the road-edge grid could not vouch for beyond the graph's recompute
            budget (``OFFROAD_RECOMPUTE_BUDGET``), whose off-road distance may be wrong; the
            caller must redo the step eagerly (``env.fused``). Eagerly None: always exact.
    """

    collision: torch.Tensor
    offroad: torch.Tensor
    offroad_distance: torch.Tensor
    progress: torch.Tensor
    goal_distance: torch.Tensor
    log_divergence: torch.Tensor
    log_valid: torch.Tensor
    agent_distance: tuple[torch.Tensor, torch.Tensor | None] | None = None
    offroad_stale: torch.Tensor | None = None


def build_route(state: SimState, query: torch.Tensor) -> Route:
    """Routes of the query agents from the log.

    Args:
        state: any state of the rollout (only the log is read).
        query: [B, Q] int64 agent slots.
    """
    pts = state.log.of_slots("pose", query)[..., :2]  # [B, Q, T, 2]
    valid = state.log.of_slots("valid", query)  # [B, Q, T]
    n_t = valid.shape[-1]
    steps = torch.arange(n_t, device=state.device)
    # Forward-fill invalid steps with the last valid one (backward-fill before the first).
    last = torch.where(valid, steps, torch.full_like(steps, -1)).cummax(-1).values
    first = torch.where(valid, steps, torch.full_like(steps, n_t)).min(-1, keepdim=True).values
    idx = torch.where(last >= 0, last, first.clamp(max=n_t - 1))
    filled = pts.gather(2, idx[..., None].expand(-1, -1, -1, 2))
    seg = torch.linalg.vector_norm(filled[..., 1:, :] - filled[..., :-1, :], dim=-1)
    arc = torch.cat([torch.zeros_like(seg[..., :1]), seg.cumsum(-1)], dim=-1)
    return Route(
        points=filled,
        arc=arc,
        goal=filled[..., -1, :],
        valid=valid.any(-1),
        **_query_fields(state, query),
    )


def goal_mask(route: Route, start_step: int, goal_radius: float) -> torch.Tensor:
    """[B, Q] bool: the query agents that have a goal to reach.

    The goal is the last logged position. An agent has one when its log goes on after
    ``start_step`` and its logged route is longer than ``goal_radius``; one whose log ends at
    the start (every agent of a history-only scene, e.g. the WOSAC test split) has none, since
    its goal would be where it starts. Without a goal, ``goal_reached`` stays False and the
    goal reward and termination never happen.

    Args:
        route: ``build_route`` of the query agents.
        start_step: the episode's first step.
        goal_radius: m, distance that counts as reaching the goal.
    """
    steps = cached_arange(route.log_valid.shape[-1], route.log_valid.device)
    logged_after = (route.log_valid & (steps > start_step)).any(-1)
    return (route.arc[..., -1] > goal_radius) & logged_after


def _query_fields(state: SimState, query: torch.Tensor) -> dict[str, torch.Tensor]:
    """The per-episode fields of ``Route`` after ``segment_arc`` for the query agents."""
    b_idx = torch.arange(state.batch_size, device=state.device)[:, None]
    size = state.agents.size[b_idx, query, :2]
    length, width = size.unbind(-1)
    along, across = corner_offsets(length, width)
    return {
        "size": size,
        "radius": const(0.5, size) * torch.linalg.vector_norm(size, dim=-1),
        "near_limit": near_limits(query, size, state.agents.size[..., :2]),
        "corner_along": along,
        "corner_across": across,
        "log_xy": state.log.of_slots("pose", query)[..., :2],
        "log_valid": state.log.of_slots("valid", query),
    }


def progress_along(route: Route, xy: torch.Tensor) -> torch.Tensor:
    """Arc length of the projection of ``xy`` [B, Q, 2] on the route polyline, [B, Q] m."""
    # x and y apart, each a contiguous row: no sums over a dim of 2, no strided reads.
    (ax, ay), (bx, by) = route.segment_start.unbind(-2), route.segments.unbind(-2)
    qx, qy = xy[..., 0:1], xy[..., 1:2]
    t = (((qx - ax) * bx + (qy - ay) * by) / route.segment_length2).clamp(0.0, 1.0)
    d = torch.hypot(qx - (ax + t * bx), qy - (ay + t * by))
    best = d.argmin(-1, keepdim=True)
    along = t.gather(-1, best) * route.segment_length.gather(-1, best)
    return (route.segment_arc.gather(-1, best) + along).squeeze(-1)


def step_metrics(state: SimState, query: torch.Tensor, route: Route) -> StepMetrics:
    """Metrics of the query agents in ``state``.

    Args:
        state: current state.
        query: [B, Q] int64 agent slots.
        route: their logged routes (``build_route``).
    """
    if route.size is None:
        route = dataclasses.replace(route, **_query_fields(state, query))
    pose = gather_rows(state.pose, query)
    present = gather_rows(state.valid, query)
    size = route.size
    x0, y0, yaw = pose.unsqueeze(-2).unbind(-1)  # [B, Q, 1]
    trig = cos_sin(yaw)
    # The other agents as columns: each row's valid slots (``valid_first``), or every slot.
    slots = valid_first(state.valid, query.shape[1])  # [B, C] or None
    other_pose, usable, other_size = state.pose, state.valid, state.agents.size[..., :2]
    if slots is not None:
        other_pose, usable = gather_rows(other_pose, slots), gather_rows(usable, slots)
        other_size = gather_rows(other_size, slots)
    gap = agent_distances(pose, other_pose)  # [B, Q, C or N]
    limit = route.near_limit if slots is None else near_limits(query, size, other_size, slots)
    coll = collided_with_others(pose, size, other_pose, other_size, usable, limit, trig, gap)
    corners = corners_from_offsets(x0, y0, trig, (route.corner_along, route.corner_across))
    off_d, stale = _offroad(corners, state.road_edges, present)
    log_valid, log_xy = _log_at(route, state.step)
    xy = pose[..., :2]
    log_gap = torch.linalg.vector_norm(xy - log_xy, dim=-1) * log_valid
    metrics = StepMetrics(
        collision=coll & present,
        offroad=(off_d > const(0.0, off_d)) & present,
        offroad_distance=off_d,
        progress=progress_along(route, xy),
        goal_distance=torch.linalg.vector_norm(xy - route.goal, dim=-1),
        log_divergence=log_gap,
        log_valid=log_valid,
        agent_distance=(gap, slots),
        offroad_stale=(stale & present) if torch.compiler.is_compiling() else None,
    )
    return metrics


def _offroad(
    corners: tuple[torch.Tensor, torch.Tensor], edges: RoadEdges, present: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``box_offroad_distance`` of the query boxes; of the ``present`` [B, Q] ones only where
    that pays (``torch_utils.listed``; with a grid): the others, agents that left, get 0."""
    pairs = listed(present) if edges.grid is not None else None
    if pairs is None:
        return box_offroad_distance(corners, edges)
    b, q = pairs
    boxes = (corners[0][b, q].unsqueeze(1), corners[1][b, q].unsqueeze(1))  # [R, 1, 4]
    part, _ = box_offroad_distance(boxes, edges, b)  # eagerly never stale
    out = part.new_zeros(present.shape).index_put_((b, q), part[:, 0])
    return out, torch.zeros_like(present)


def _log_at(route: Route, step: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(log_valid [B, Q], log_xy [B, Q, 2]) of the query agents at ``step`` [B] (clamped to T - 1).

    A batch of one on the CPU reads the step as a number (views instead of indexing), except
    under ``torch.compile``, where reading it would break the graph.
    """
    n_t = route.log_valid.shape[-1]
    if step.shape[0] == 1 and step.device.type == "cpu" and not torch.compiler.is_compiling():
        t = min(int(step.item()), n_t - 1)
        return route.log_valid[:, :, t], route.log_xy[:, :, t]
    at = (
        cached_arange(step.shape[0], step.device)[:, None],
        cached_arange(route.log_valid.shape[1], step.device),
        step.clamp(max=n_t - 1)[:, None],
    )
    return route.log_valid[at], route.log_xy[at]
