"""Routes of the ``idm`` policy (numpy, once per scenario): the path each agent follows, as
``ROUTE_POINTS`` points ``ROUTE_SPACING`` apart in arc length, and the speed its bends allow.

* ``route="log"``: the agent's logged path from the start step on (positions only; the speed
  is the policy's), continued past the log's end along the lane graph from the lane the agent
  ends on (seeded random branches); a vehicle that ends on no lane stops at the log's end, one
  that stands all along its log stays, one the log holds at the start step only takes the
  lanes.
* ``route="lanes"``: from the lane the agent is on along the lane graph; at a fork the branch
  that best matches the agent's logged future where the scene logs one, else a seeded random
  branch. A vehicle on no lane follows its log (or drives straight on without one); a lane
  with no successor ends the route (the agent stops there).
* Pedestrians and cyclists follow their logged path, or go straight on without one.

Every path is resampled uniformly and continued straight past its end (for steering only: an
agent stops at ``RoutePlan.end`` unless its path is open).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from policies.idm.lanes import LaneGraph, match_lanes
from policies.idm.params import ROUTE_POINTS, ROUTE_SPACING, Route
from tbsim_env.core.constants import ObjectType
from tbsim_env.data.scenario import Scenario, wrap_angle_np

LOG_POINT_SPACING = 0.5
"""m: logged positions closer than this to the last kept one are dropped (jitter of a
standing agent)."""
BRANCH_MATCH = 2.5
"""m: a fork branch matches the logged future when its points lie this near it (median)."""
BRANCH_SAMPLE = 20.0
"""m of a branch lane compared with the logged future."""
CURVATURE_BASES = (1, 2)
"""Route segments of the chords a bend's curvature is measured over (2.5 m and 5 m): the
smaller of the two counts. A bend turns the chords of both alike, while the jitter of logged
positions (centimetres) turns 2.5 m chords about four times as much as 5 m ones: alone, it
caps a fast car's speed on a straight logged path. (Over 10 m, vehicles kept more speed
into sharp bends and one left the road on the real samples.)"""
JOIN_BLEND_MIN = 20.0
"""m: the shortest stretch over which a logged path's continuation along its lane fades from
the log's end onto the lane's centre line (``blend_onto_lane``)."""
JOIN_BLEND_TIME = 4.0
"""s: that stretch is the distance covered at the log's end speed in this time when longer
(a highway vehicle 0.3 m off its lane's centre would otherwise meet a kink whose curvature
caps its speed near 7 m/s, and brake for it from the start)."""
MAX_LANES_PER_ROUTE = 256
"""Lanes walked at most per route (a guard against cycles of zero-length lanes)."""

Chooser = Callable[[np.ndarray], int]
"""Picks one of several successor lane rows [k] at a fork."""


@dataclass(frozen=True)
class RoutePlan:
    """Routes of all A tracks of a scenario.

    Attributes:
        points: [A, P, 2] float64 route points (scenario frame, m), ``ROUTE_SPACING`` apart.
        end: [A] float64 arc length (m) where the agent must stop: the end of a route that
            cannot go on; +inf for open routes.
        on_lane: [A] bool, the agent starts on a lane (its desired speed then draws on the
            lane's speed limit or the type's default).
        lane_speed: [A] float64 m/s, that lane's speed limit (0: unknown or no lane).
        backward: [A] bool, the logged path starts behind the agent (it reverses in the log,
            out of a parking space say; the policy does not reverse, so it holds such agents).
        valid: [A] bool, the agent has a route (it is valid at some step from the start on).
    """

    points: np.ndarray
    end: np.ndarray
    on_lane: np.ndarray
    lane_speed: np.ndarray
    backward: np.ndarray
    valid: np.ndarray


def resample(path: np.ndarray, yaw: float) -> tuple[np.ndarray, float]:
    """``ROUTE_POINTS`` points ``ROUTE_SPACING`` apart along ``path``, continued straight past
    its end (along ``yaw`` for a single point).

    Args:
        path: [n >= 1, 2] m, no two consecutive points equal.
        yaw: rad, the direction of a path of one point.

    Returns:
        (points [P, 2], the path's length m).
    """
    s = np.arange(ROUTE_POINTS) * ROUTE_SPACING
    if len(path) < 2:
        d = np.array([np.cos(yaw), np.sin(yaw)])
        return path[0] + s[:, None] * d, 0.0
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    total = float(arc[-1])
    out = np.stack([np.interp(s, arc, path[:, 0]), np.interp(s, arc, path[:, 1])], -1)
    d = path[-1] - path[-2]
    d = d / max(float(np.linalg.norm(d)), 1e-9)
    past = s > total
    out[past] = path[-1] + (s[past] - total)[:, None] * d
    return out, total


def thin(xy: np.ndarray) -> np.ndarray:
    """[n, 2] positions without those within ``LOG_POINT_SPACING`` of the last kept one."""
    if len(xy) == 0:
        return xy
    keep = [0]
    while True:  # the next kept: the first position far enough from the last kept one
        last = keep[-1]
        rest = xy[last + 1 :]
        far = np.hypot(rest[:, 0] - xy[last, 0], rest[:, 1] - xy[last, 1]) >= LOG_POINT_SPACING
        if not far.any():
            return xy[keep]
        keep.append(last + 1 + int(np.argmax(far)))


def lane_path(
    graph: LaneGraph, lane: int, arc: float, length: float, choose: Chooser
) -> tuple[np.ndarray, bool]:
    """The path along the lane graph from ``arc`` metres into lane ``lane``.

    Args:
        graph: the lane graph.
        lane: lane row; arc: m along it.
        length: m of path wanted.
        choose: picks the branch at a fork.

    Returns:
        (path [n, 2] with no repeated point, whether it reached a lane with no successor
        before ``length``).
    """
    poly = graph.polylines[lane]
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
    k = int(np.searchsorted(cum, arc, side="right"))
    first = np.array([np.interp(arc, cum, poly[:, 0]), np.interp(arc, cum, poly[:, 1])])
    pieces, total = [first[None], poly[k:]], float(cum[-1] - arc)
    for _ in range(MAX_LANES_PER_ROUTE):
        if total >= length:
            break
        succ = graph.successors[lane]
        if len(succ) == 0:
            return _joined(pieces), True
        lane = int(succ[0]) if len(succ) == 1 else choose(succ)
        poly = graph.polylines[lane]
        pieces.append(poly)
        total += float(np.linalg.norm(np.diff(poly, axis=0), axis=1).sum())
    return _joined(pieces), False


def _joined(pieces: list[np.ndarray]) -> np.ndarray:
    """The pieces end to end, consecutive repeats (shared lane end points) removed."""
    xy = np.concatenate(pieces)
    keep = np.concatenate([[True], np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-3])
    return xy[keep]


def fork_chooser(graph: LaneGraph, future: np.ndarray | None, rng: np.random.Generator) -> Chooser:
    """The branch whose first ``BRANCH_SAMPLE`` metres lie nearest the logged future (median
    distance within ``BRANCH_MATCH``), else a random one.

    Args:
        graph: the lane graph.
        future: [k, 2] the agent's logged future positions, or None.
        rng: draws the random branches.
    """

    def choose(branches: np.ndarray) -> int:
        if future is not None and len(future):
            score = np.array([_branch_distance(graph.polylines[b], future) for b in branches])
            if score.min() <= BRANCH_MATCH:
                return int(branches[int(np.argmin(score))])
        return int(branches[int(rng.integers(len(branches)))])

    return choose


def _branch_distance(poly: np.ndarray, future: np.ndarray) -> float:
    """Median distance (m) of a lane's first ``BRANCH_SAMPLE`` m (every 2 m) to the future."""
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
    s = np.linspace(0.0, min(BRANCH_SAMPLE, float(cum[-1])), 11)
    pts = np.stack([np.interp(s, cum, poly[:, 0]), np.interp(s, cum, poly[:, 1])], -1)
    d = np.linalg.norm(pts[:, None] - future[None], axis=-1).min(1)
    return float(np.median(d))


def speed_caps(points: np.ndarray, lateral_accel: float, decel: np.ndarray) -> np.ndarray:
    """The speed each route point allows: sqrt(lateral_accel / curvature) in bends, lowered
    ahead of a bend so that braking at ``decel`` reaches it. The curvature at a point is the
    turn between the chords k points before and after it over their midpoints' distance, the
    least over k in ``CURVATURE_BASES``.

    Args:
        points: [A, P, 2] routes, ``ROUTE_SPACING`` apart.
        lateral_accel: m/s^2.
        decel: [A] m/s^2, comfortable braking of each agent.

    Returns:
        [A, P] m/s.
    """
    curv = np.minimum.reduce([_curvature(points, k) for k in CURVATURE_BASES])
    cap = np.sqrt(lateral_accel / np.maximum(curv, 1e-6))
    out = cap.copy()
    for k in range(points.shape[1] - 2, -1, -1):  # braking ahead of bends
        out[:, k] = np.minimum(cap[:, k], np.sqrt(out[:, k + 1] ** 2 + 2 * decel * ROUTE_SPACING))
    return out


def _curvature(points: np.ndarray, k: int) -> np.ndarray:
    """[A, P] 1/m: the turn between the chords of k segments before and after each point of
    ``points`` [A, P, 2] over their midpoints' distance (the ends repeat their neighbours')."""
    d = points[:, k:] - points[:, :-k]  # [A, P - k, 2] chords of k segments
    heading = np.arctan2(d[..., 1], d[..., 0])
    turn = np.abs(wrap_angle_np(heading[:, k:] - heading[:, :-k])) / (k * ROUTE_SPACING)
    return np.pad(turn, ((0, 0), (k, k)), mode="edge")


def _log_points(scenario: Scenario, track: int, first: int) -> np.ndarray:
    """[k, 2] thinned logged positions of a track at its valid steps from ``first`` on."""
    t = scenario.tracks
    steps = np.flatnonzero(t.valid[track, first:]) + first
    return thin(t.xyz[track, steps, :2].astype(np.float64))


@dataclass(frozen=True)
class _Agent:
    """What one route is built from."""

    xy: np.ndarray  # [2] position at the first step of the route
    yaw: float
    lane: int  # lane row, -1 none
    arc: float  # m along that lane
    log: np.ndarray  # [k, 2] thinned logged path from the first step (k >= 1)
    logged: bool  # the log holds the agent at some step after the first
    vehicle: bool
    end_speed: float  # m/s at the last logged step


def _route(agent: _Agent, graph: LaneGraph, mode: Route, rng: np.random.Generator) -> tuple:
    """(path [n, 2], stop arc m or inf) of one agent."""
    length = ROUTE_POINTS * ROUTE_SPACING
    moves = len(agent.log) >= 2
    if not agent.vehicle:
        return (agent.log if moves else agent.xy[None]), np.inf
    if agent.lane >= 0 and (mode is Route.LANES or not agent.logged):
        choose = fork_chooser(graph, agent.log[1:] if moves else None, rng)
        path, dead_end = lane_path(graph, agent.lane, agent.arc, length, choose)
        return path, _path_length(path) if dead_end else np.inf
    if not moves:  # standing all along the log: stays; on no lane, no log: straight on
        return agent.xy[None], 0.0 if agent.logged else np.inf
    path = agent.log
    end_yaw = np.arctan2(*(path[-1] - path[-2])[::-1])
    lane, arc = match_lanes(graph, path[-1:], np.array([end_yaw]))
    if lane[0] < 0:
        return path, _path_length(path)
    more, dead_end = lane_path(
        graph, int(lane[0]), float(arc[0]), length, fork_chooser(graph, None, rng)
    )
    blend = max(JOIN_BLEND_MIN, JOIN_BLEND_TIME * agent.end_speed)
    full = _joined([path, blend_onto_lane(more, path[-1], blend)])
    return full, _path_length(full) if dead_end else np.inf


def blend_onto_lane(lane: np.ndarray, start: np.ndarray, length: float) -> np.ndarray:
    """``lane`` [n, 2] (a path along the lane graph) shifted to begin at ``start`` [2] (where
    the logged path ends, off the lane's centre line), the shift fading out by a smoothstep
    over the first ``length`` m: the joined route has no kink, whose curvature would cap
    the speed (``speed_caps``) of an agent that drives straight on."""
    arc = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(lane, axis=0), axis=1))])
    w = np.clip(1.0 - arc / length, 0.0, 1.0)
    return lane + (w * w * (3.0 - 2.0 * w))[:, None] * (start - lane[0])


def _path_length(path: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(path, axis=0), axis=1).sum()) if len(path) > 1 else 0.0


def build_routes(
    scenario: Scenario,
    graph: LaneGraph,
    start: int,
    mode: Route,
    rng: np.random.Generator,
    only: np.ndarray | None = None,
) -> RoutePlan:
    """The routes of every track of ``scenario`` from step ``start`` on.

    An agent not valid at ``start`` gets its route from the first step it is valid (when it
    appears). Scenes without a logged future use ``Route.LANES``.

    Args:
        scenario: the scenario (on the simulation's time grid).
        graph: its lane graph (``lane_graph``).
        start: the first simulated step.
        mode: the route mode.
        rng: draws the branches no logged future decides.
        only: optional [A] bool, the tracks to route (the others get no route, ``valid``
            False): a planner driving one agent needs its route alone.
    """
    t = scenario.tracks
    a = t.num_tracks
    mode = mode if scenario.has_future else Route.LANES
    valid_from = t.valid[:, start:]
    present = valid_from.any(1) if only is None else valid_from.any(1) & only
    first = np.where(present, np.argmax(valid_from, axis=1) + start, start)
    rows = np.arange(a)
    xy = t.xyz[rows, first, :2].astype(np.float64)
    yaw = t.heading[rows, first].astype(np.float64)
    lanes_for = (t.object_type != int(ObjectType.PEDESTRIAN)) & present
    lane = np.full(a, -1, np.int64)
    arc = np.zeros(a)
    if lanes_for.any():
        lane[lanes_for], arc[lanes_for] = match_lanes(graph, xy[lanes_for], yaw[lanes_for])
    points = np.zeros((a, ROUTE_POINTS, 2))
    end = np.full(a, np.inf)
    backward = np.zeros(a, bool)
    for k in np.flatnonzero(present):
        kind = int(t.object_type[k])
        vehicle = kind not in (int(ObjectType.PEDESTRIAN), int(ObjectType.CYCLIST))
        log = _log_points(scenario, k, first[k])
        logged = bool(t.valid[k, first[k] + 1 :].any())
        last = first[k] + int(np.flatnonzero(t.valid[k, first[k] :])[-1])
        agent = _Agent(
            xy[k],
            float(yaw[k]),
            int(lane[k]),
            float(arc[k]),
            log,
            logged,
            vehicle,
            float(np.linalg.norm(t.velocity[k, last])),
        )
        backward[k] = len(log) > 1 and (log[1] - log[0]) @ [np.cos(yaw[k]), np.sin(yaw[k])] < 0
        path, end[k] = _route(agent, graph, mode, rng)
        points[k], _ = resample(path, float(yaw[k]))
    on_lane = lane >= 0
    limits = graph.speed_limit if graph.num_lanes else np.zeros(1)
    speed = np.where(on_lane, limits[np.maximum(lane, 0)], 0.0)
    return RoutePlan(points, end, on_lane, speed, backward, present)


__all__ = [
    "RoutePlan",
    "blend_onto_lane",
    "build_routes",
    "fork_chooser",
    "lane_path",
    "resample",
    "speed_caps",
    "thin",
]
