"""Run a planner over one scene's episode in ``TrafficEnv`` and record what the metrics read.

The controlled agents (the SDC, or the tracks to predict) are driven by the planner for the
whole episode (no termination on collision or goal, as nuPlan's simulation goes on after a
collision); every other agent is an NPC of the traffic policy. A planner that raises or
returns a malformed action (wrong shape, NaN, infinite) fails the episode with a message; the
caller goes on with the next one.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from tbsim_env.benchmark.planner import PlannerInput, reset_planner
from tbsim_env.core.config import EnvConfig, TerminationConfig
from tbsim_env.data.scenario import Scenario
from tbsim_env.env import TrafficEnv
from tbsim_env.env.vector_env import route_features
from tbsim_env.sim.geometry import to_local

ROUTE_POINTS, ROUTE_SPACING = 20, 2.0
"""Route points a planner gets and their spacing (m): 40 m of its logged route."""


@dataclass(frozen=True)
class EpisodeRecord:
    """One controlled agent's episode in the scenario's frame (S steps, S + 1 states: the
    start and after each step; N agent slots, the ego's included and masked out).

    Attributes:
        scenario_id: the scene; traffic: the NPC policy; agent: the env's agent name.
        slot: the ego's agent slot (its column of the ``others_*`` arrays).
        ego_pose: [S + 1, 3] (x m, y m, yaw rad); ego_speed: [S + 1] m/s.
        ego_size: [2] (length, width) m; ego_type: ``ObjectType``.
        others_pose: [S + 1, N, 3]; others_speed: [S + 1, N]; others_valid: [S + 1, N] bool
            (the ego's own slot False).
        others_size: [N, 2]; others_type: [N]; others_id: [N] track ids; track_index: [N]
            each slot's row in ``Scenario.tracks`` (-1: padding).
        offroad_distance: [S + 1] m, the env's signed road-edge distance of the ego's box
            (positive: off the road).
        progress: [S + 1] m, the env's progress along the ego's logged route.
        expert_progress: m the log advances along its route from the start to its last
            logged state of the episode; route_length: m of the logged route from the start
            to its end.
        dt: s per step.
        error: why the planner failed this episode, or None.
    """

    scenario_id: str
    traffic: str
    agent: str
    slot: int
    ego_pose: np.ndarray
    ego_speed: np.ndarray
    ego_size: np.ndarray
    ego_type: int
    others_pose: np.ndarray
    others_speed: np.ndarray
    others_valid: np.ndarray
    others_size: np.ndarray
    others_type: np.ndarray
    others_id: np.ndarray
    track_index: np.ndarray
    offroad_distance: np.ndarray
    progress: np.ndarray
    expert_progress: float
    route_length: float
    dt: float
    error: str | None = None


class PlannerError(RuntimeError):
    """A planner raised or returned a malformed action; the message names the scene, agent
    and step."""


def logged_arc(scenario: Scenario, track: int) -> np.ndarray:
    """[T] m, cumulative arc length of a track's logged positions (an invalid step repeats
    the previous valid position, as the env's routes do)."""
    t = scenario.tracks
    xy = t.xyz[track, :, :2].astype(np.float64)
    valid = t.valid[track]
    idx = np.maximum.accumulate(np.where(valid, np.arange(len(valid)), 0))
    filled = xy[idx]
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(filled, axis=0), axis=-1))])


def _expert_span(scenario: Scenario, track: int, start: int, end: int) -> tuple[float, float]:
    """(m the log advances from ``start`` to its last valid step <= ``end``, m from ``start``
    to the route's end)."""
    arc = logged_arc(scenario, track)
    valid = scenario.tracks.valid[track, : end + 1]
    last = int(np.flatnonzero(valid)[-1]) if valid.any() else start
    return float(arc[max(last, start)] - arc[start]), float(arc[-1] - arc[start])


def _planner_inputs(env: TrafficEnv) -> dict[str, dict[str, Any]]:
    """Per live agent: route points, goal (own frame), speed, slot and the simulator state."""
    ep = env.episode
    setup, sim = ep.setup, ep.sim
    pose = sim.pose.gather(1, setup.query[..., None].expand(-1, -1, 3))  # [1, Q, 3]
    speed = sim.speed.gather(1, setup.query)
    route = route_features(setup.route, ep.progress, pose, ROUTE_POINTS, ROUTE_SPACING)
    goal = to_local(setup.route.goal[..., None, :], pose[..., None, :])[..., 0, :]
    route, goal, speed = route[0].numpy(), goal[0].float().numpy(), speed[0].tolist()
    return {
        name: {
            "route": route[j],
            "goal": goal[j],
            "speed": speed[j],
            "slot": int(setup.query[0, j]),
            "sim": sim,
        }
        for name, j in env.agent_columns.items()
        if name in env.agents
    }


def _checked(action: Any, where: str) -> np.ndarray:
    """The planner's action as float32 [2], or ``PlannerError``."""
    try:
        a = np.asarray(action, np.float32).reshape(-1)
    except (TypeError, ValueError) as err:
        raise PlannerError(f"{where}: action is not numeric ({err})") from err
    if a.shape != (2,):
        raise PlannerError(f"{where}: action has {a.size} values, expected 2 (accel, yaw rate)")
    if not np.isfinite(a).all():
        raise PlannerError(f"{where}: action {a.tolist()} is not finite")
    return a


def _actions(env: TrafficEnv, planners: dict[str, Any], step: int, obs: dict) -> dict:
    """One action per live agent from its planner (``PlannerError`` on a bad one)."""
    expert = functools.cache(env.expert_actions)  # computed once, if a planner reads it
    extra = _planner_inputs(env)
    t0 = env.config.start_step
    out = {}
    for name in env.agents:
        where = f"scene {env.scenario.scenario_id}, agent {name}, step {step}"
        x = PlannerInput(
            scenario_id=env.scenario.scenario_id,
            agent=name,
            step=step,
            time_s=round((step - t0) * 0.1, 6),
            observations=obs,
            experts=expert,
            **extra[name],
        )
        try:
            action = planners[name].act(x)
        except Exception as err:  # a planner's own failure, reported, not raised
            raise PlannerError(f"{where}: planner raised {type(err).__name__}: {err}") from err
        out[name] = _checked(action, where)
    return out


def _states(env: TrafficEnv) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(pose [N, 3] in the scenario frame, speed [N], valid [N]) of every agent slot now."""
    sim = env.sim_state
    pose = sim.pose[0].double().clone()
    pose[:, :2] += sim.origin[0].double()
    return pose.numpy(), sim.speed[0].double().numpy(), sim.valid[0].numpy().copy()


@dataclass(frozen=True)
class EpisodeSpec:
    """One episode to run: the scene, the NPC policy, which agents the planner drives.

    Attributes:
        scenario: the scene (its log must reach the episode's end for ``log_replay``).
        traffic: NPC policy name (``log_replay``, ``idm``, ``trafficbots``, ...).
        controlled: ``"sdc"`` or ``"tracks_to_predict"``.
        seed: the env's seed (NPC sampling) and the planners' ``reset`` seed.
        npc_checkpoint: TrafficBots weights for ``trafficbots`` traffic (None: shipped).
    """

    scenario: Scenario
    traffic: str
    controlled: str = "sdc"
    seed: int = 0
    npc_checkpoint: str | None = None


def run_episode(spec: EpisodeSpec, make_planner: Callable[[], Any]) -> list[EpisodeRecord]:
    """Drive ``spec``'s controlled agents with one planner each (from ``make_planner``) for
    the whole episode; one record per agent. A failing planner ends the episode: every
    agent's record then carries the error (and the states up to it)."""
    never = EnvConfig(termination=TerminationConfig(collision=False, goal=False))
    env = TrafficEnv(
        [spec.scenario],
        controlled=spec.controlled,
        npc_policy=spec.traffic,
        npc_checkpoint=spec.npc_checkpoint,
        config=never,
        lazy_observations=True,  # built-in planners read the state, not observations
    )
    obs, infos = env.reset(seed=spec.seed)
    planners = {name: make_planner() for name in env.agents}
    for name, planner in planners.items():
        reset_planner(planner, spec.scenario, name, spec.seed)
    names = list(env.agents)
    states = [_states(env)]
    metrics = [{n: (infos[n]["offroad_distance"], infos[n]["progress"]) for n in names}]
    error, step = None, env.config.start_step
    with torch.inference_mode():
        while env.agents:
            try:
                actions = _actions(env, planners, step, obs)
            except PlannerError as err:
                error = str(err)
                break
            obs, _, _, _, infos = env.step(actions)
            states.append(_states(env))
            metrics.append({n: (infos[n]["offroad_distance"], infos[n]["progress"]) for n in names})
            step += 1
    return [_record(env, spec, name, states, metrics, error) for name in names]


@dataclass(frozen=True)
class Trace:
    """What an episode recorded of one scene's N agent slots (S steps, S + 1 states).

    Attributes:
        pose: [S + 1, N, 3] (x m, y m, yaw rad) in the scenario's frame; speed: [S + 1, N]
            m/s; valid: [S + 1, N] bool.
        size: [N, 2] (length, width) m; object_type, track_id, track_index: [N].
        offroad: [S + 1] m, the ego's signed road-edge distance (the env's info).
        progress: [S + 1] m, the ego's progress along its logged route (the env's info).
    """

    pose: np.ndarray
    speed: np.ndarray
    valid: np.ndarray
    size: np.ndarray
    object_type: np.ndarray
    track_id: np.ndarray
    track_index: np.ndarray
    offroad: np.ndarray
    progress: np.ndarray


def slot_fields(agents: Any, row: int, n: int | None = None) -> dict[str, np.ndarray]:
    """The ``Trace`` fields of batch row ``row``'s first ``n`` agent slots (every slot by
    default) of a ``SimState.agents``: size, object type, track id and track index."""
    cut = slice(None, n)
    return {
        "size": agents.size[row, cut, :2].double().numpy(),
        "object_type": agents.object_type[row, cut].numpy().copy(),
        "track_id": agents.track_id[row, cut].numpy().copy(),
        "track_index": agents.track_index[row, cut].numpy().copy(),
    }


def make_record(
    spec: EpisodeSpec, name: str, slot: int, trace: Trace, config: EnvConfig, error: str | None
) -> EpisodeRecord:
    """The record of the ego ``name`` (agent slot ``slot``) from its scene's trace."""
    others_valid = trace.valid.copy()
    others_valid[:, slot] = False
    track = int(trace.track_index[slot])
    expert, length = _expert_span(spec.scenario, track, config.start_step, config.last_step)
    return EpisodeRecord(
        scenario_id=spec.scenario.scenario_id,
        traffic=spec.traffic,
        agent=name,
        slot=slot,
        ego_pose=trace.pose[:, slot],
        ego_speed=trace.speed[:, slot],
        ego_size=trace.size[slot],
        ego_type=int(trace.object_type[slot]),
        others_pose=trace.pose,
        others_speed=trace.speed,
        others_valid=others_valid,
        others_size=trace.size,
        others_type=trace.object_type,
        others_id=trace.track_id,
        track_index=trace.track_index,
        offroad_distance=trace.offroad,
        progress=trace.progress,
        expert_progress=expert,
        route_length=length,
        dt=0.1,
        error=error,
    )


def _record(
    env: TrafficEnv,
    spec: EpisodeSpec,
    name: str,
    states: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    metrics: list[dict[str, tuple[float, float]]],
    error: str | None,
) -> EpisodeRecord:
    """The record of agent ``name`` from the per-step states and info metrics."""
    slot = int(env.episode.setup.query[0, env.agent_columns[name]])
    trace = Trace(
        pose=np.stack([s[0] for s in states]),
        speed=np.stack([s[1] for s in states]),
        valid=np.stack([s[2] for s in states]),
        offroad=np.array([m[name][0] for m in metrics]),
        progress=np.array([m[name][1] for m in metrics]),
        **slot_fields(env.sim_state.agents, 0),
    )
    return make_record(spec, name, slot, trace, env.config, error)


__all__ = [
    "EpisodeRecord",
    "EpisodeSpec",
    "PlannerError",
    "Trace",
    "make_record",
    "run_episode",
    "slot_fields",
]


def log_record(scenario: Scenario, track: int, traffic: str = "log") -> EpisodeRecord:
    """The log itself as an episode of track row ``track``: what the log earns, scored as a
    planner's episode is (the road-edge distance by the env's own box test).

    Raises:
        MissingFutureError: the log does not reach the episode's end.
    """
    from tbsim_env.core.boxes import box_corner_xy
    from tbsim_env.sim.build import build_sim_state
    from tbsim_env.sim.offroad import box_offroad_distance

    cfg = EnvConfig()
    start, end = cfg.start_step, cfg.last_step
    scenario.require_log_until(end, "scoring the log")
    sim = build_sim_state([scenario], start_step=start)
    log = sim.log
    steps = slice(start, end + 1)
    pose = log.take("pose")[0, :, steps].transpose(0, 1).double()  # [S+1, N, 3] shifted frame
    speed = log.take("speed")[0, :, steps].transpose(0, 1).double()
    valid = log.take("valid")[0, :, steps].transpose(0, 1)
    slot = int(torch.nonzero(sim.agents.track_index[0] == track)[0, 0])
    size = sim.agents.size[0, :, :2]
    corners = box_corner_xy(pose[:, slot].float()[None], size[slot, 0], size[slot, 1])
    offroad = box_offroad_distance(corners, sim.road_edges)[0][0].double()
    world = pose.clone()
    world[..., :2] += sim.origin[0].double()
    trace = Trace(
        pose=world.numpy(),
        speed=speed.numpy(),
        valid=valid.numpy(),
        offroad=offroad.numpy(),
        progress=logged_arc(scenario, track)[start : end + 1],
        **slot_fields(sim.agents, 0),
    )
    name = f"track_{int(scenario.tracks.id[track])}"
    return make_record(EpisodeSpec(scenario, traffic), name, slot, trace, cfg, None)
