"""Everything the ``idm`` policy derives from one scenario before a rollout (numpy, cached per
scenario, start step and branch variant): routes, bend speed caps, stop lines, crosswalks,
per-agent IDM parameters and desired speeds before the per-rollout draw.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from policies.idm.lanes import LaneGraph
from policies.idm.params import STILL_HISTORY_SPEED, IDMConfig, TypeParams
from policies.idm.routes import RoutePlan, build_routes, speed_caps
from policies.idm.stops import RouteEvents, crosswalk_polygons, route_events
from tbsim_env.core.constants import ObjectType
from tbsim_env.data.scenario import Scenario

PARAM_FIELDS = (
    "max_accel",
    "comfort_decel",
    "time_headway",
    "standstill_gap",
    "exponent",
    "max_decel",
    "min_lookahead",
    "lookahead_time",
)
"""The per-agent columns of ``ScenePlan.params`` (``TypeParams`` fields)."""


@dataclass(frozen=True)
class ScenePlan:
    """The rollout-independent plan of every track of a scenario (A tracks, scenario frame).

    Attributes:
        routes: the routes (``RoutePlan``).
        speed_cap: [A, P] float64 m/s the route's bends allow at each point.
        events: stop lines and crosswalks along the routes.
        crosswalks: [W, V, 2] float64 crosswalk outlines of the scene.
        params: [A, len(PARAM_FIELDS)] float64 IDM parameters of each track's type.
        desired_speed: [A] float64 m/s before the per-rollout factor.
        obeys: [A] bool, the agent stops for signals, stop signs and crosswalks (not
            pedestrians).
    """

    routes: RoutePlan
    speed_cap: np.ndarray
    events: RouteEvents
    crosswalks: np.ndarray
    params: np.ndarray
    desired_speed: np.ndarray
    obeys: np.ndarray


def type_params(cfg: IDMConfig, object_type: np.ndarray) -> list[TypeParams]:
    """The ``TypeParams`` of each object type [A] (vehicle values for UNSET and OTHER)."""
    table = {int(ObjectType.PEDESTRIAN): cfg.pedestrian, int(ObjectType.CYCLIST): cfg.cyclist}
    return [table.get(int(t), cfg.vehicle) for t in object_type]


def history_speed(scenario: Scenario, start: int) -> tuple[np.ndarray, np.ndarray]:
    """Each track's (highest speed over its valid steps up to ``start``, speed at ``start``)
    [A] m/s each (for a track that appears later: up to and at its first valid step)."""
    t = scenario.tracks
    speed = np.linalg.norm(t.velocity.astype(np.float64), axis=-1)  # [A, T]
    later = t.valid[:, start:]
    first = np.where(later.any(1), np.argmax(later, axis=1) + start, start)
    upto = np.arange(t.num_steps)[None] <= first[:, None]
    rows = np.arange(t.num_tracks)
    now = np.where(t.valid[rows, first], speed[rows, first], 0.0)
    return np.where(t.valid & upto, speed, 0.0).max(1), now


def desired_speeds(
    routes: RoutePlan,
    hist: tuple[np.ndarray, np.ndarray],
    defaults: np.ndarray,
    pedestrian: np.ndarray,
    cruise: float,
) -> np.ndarray:
    """[A] m/s before the per-rollout factor.

    An agent on a lane slower than ``cruise`` now (standing in a queue, starting off) wants
    the lane's speed limit (the type's default where the map has none) or its highest history
    speed if that is higher; every other agent its highest history speed (0 for one that
    stood still); an agent whose logged path starts behind it (reversing) 0.

    Args:
        routes: the routes (``on_lane``, ``lane_speed``).
        hist: ([A] highest history speeds, [A] speeds now); defaults: [A] the types' default
            speeds.
        pedestrian: [A] bool.
        cruise: m/s (``IDMConfig.cruise_speed``).
    """
    top, now = hist
    lane = np.where(routes.lane_speed > 0, routes.lane_speed, defaults)
    moving = np.where(top >= STILL_HISTORY_SPEED, top, 0.0)
    starting = routes.on_lane & ~pedestrian & (now < cruise)
    speed = np.where(starting, np.maximum(top, lane), moving)
    return np.where(routes.backward, 0.0, speed)


def scene_plan(
    scenario: Scenario,
    graph: LaneGraph,
    start: int,
    cfg: IDMConfig,
    rng: np.random.Generator,
    only: np.ndarray | None = None,
) -> ScenePlan:
    """The plan of every track of ``scenario`` (of the tracks ``only`` [A] bool flags) from
    step ``start`` (branches drawn by ``rng`` where no logged future decides them)."""
    kinds = scenario.tracks.object_type
    per_type = type_params(cfg, kinds)
    params = np.array([[getattr(p, f) for f in PARAM_FIELDS] for p in per_type], np.float64)
    params = params.reshape(len(per_type), len(PARAM_FIELDS))
    routes = build_routes(scenario, graph, start, cfg.route, rng, only)
    routed = np.flatnonzero(routes.valid)  # events along the routes there are
    events = route_events(routes.points[routed], scenario, graph)
    decel = params[:, PARAM_FIELDS.index("comfort_decel")]
    pedestrian = kinds == int(ObjectType.PEDESTRIAN)
    defaults = np.array([p.default_speed for p in per_type], np.float64)
    return ScenePlan(
        routes=routes,
        speed_cap=speed_caps(routes.points, cfg.lateral_accel, decel),
        events=events.scattered(routed, len(routes.valid)),
        crosswalks=crosswalk_polygons(scenario),
        params=params,
        desired_speed=desired_speeds(
            routes, history_speed(scenario, start), defaults, pedestrian, cfg.cruise_speed
        ),
        obeys=~pedestrian,
    )


__all__ = ["PARAM_FIELDS", "ScenePlan", "desired_speeds", "history_speed", "scene_plan"]
