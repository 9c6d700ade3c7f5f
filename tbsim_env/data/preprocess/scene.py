"""``preprocess_scenario``: a ``Scenario`` -> padded ``SceneTokens`` (spec section 1).

Order of the steps: frame origin, map pieces, map filtering, traffic-light tokens, agent
selection, gap filling, destinations, padding to the ``TokenConfig`` limits.
"""

from __future__ import annotations

import hashlib

import numpy as np

from tbsim_env.config import TokenConfig
from tbsim_env.data.preprocess.agents import AgentAttributes, agent_attributes
from tbsim_env.data.preprocess.destination import destination_labels, last_valid_goals
from tbsim_env.data.preprocess.map_filter import filter_map_pieces
from tbsim_env.data.preprocess.map_pieces import MapPieces, build_map_pieces
from tbsim_env.data.preprocess.selection import relevant_positions, select_agents
from tbsim_env.data.preprocess.traffic_lights import TrafficLightTokens, attach_traffic_lights
from tbsim_env.data.scenario import Scenario
from tbsim_env.data.tokens import SceneTokens


def scenario_rng(scenario_id: str) -> np.random.Generator:
    """A generator seeded from a stable hash (SHA-256) of the scenario id."""
    digest = hashlib.sha256(scenario_id.encode("utf-8")).digest()
    return np.random.default_rng(int.from_bytes(digest[:8], "little"))


def scene_origin(scenario: Scenario) -> np.ndarray:
    """[2] float64 SDC xy at the current step.

    If the SDC is not valid then, its last valid history position is used, else its first
    valid position, else (0, 0) (not in the spec, which assumes a valid SDC).
    """
    valid = scenario.tracks.valid[scenario.sdc_index]
    xy = scenario.tracks.xyz[scenario.sdc_index, :, :2].astype(np.float64)
    if valid[scenario.current_index]:
        return xy[scenario.current_index].copy()
    history = np.flatnonzero(valid[: scenario.current_index + 1])
    if history.shape[0]:
        return xy[history[-1]].copy()
    anywhere = np.flatnonzero(valid)
    return xy[anywhere[0]].copy() if anywhere.shape[0] else np.zeros(2)


def _pad(array: np.ndarray, size: int, fill: float | int | bool, dtype: type) -> np.ndarray:
    """Pad the first axis of ``array`` to ``size`` with ``fill``, cast to ``dtype``."""
    out = np.full((size, *array.shape[1:]), fill, dtype=dtype)
    out[: array.shape[0]] = array
    return out


def map_boundary(pieces: MapPieces, agents: AgentAttributes, current_index: int) -> np.ndarray:
    """[4] (x_min, x_max, y_min, y_max) over valid map nodes; without map, over the agents'
    valid history positions (spec 1.6); zeros if neither exists."""
    if pieces.valid.any():
        xy = pieces.pos[pieces.valid][:, :2]
    else:
        hist = agents.states.valid[:, : current_index + 1]
        xy = agents.states.pos[:, : current_index + 1][hist][:, :2]
    if xy.shape[0] == 0:
        return np.zeros(4)
    return np.array([xy[:, 0].min(), xy[:, 0].max(), xy[:, 1].min(), xy[:, 1].max()])


def preprocess_scenario(
    scenario: Scenario, cfg: TokenConfig | None = None, *, rng: np.random.Generator | None = None
) -> SceneTokens:
    """Preprocess one scenario into fixed-size token arrays.

    Deliberate deviations from the reference (spec 1.5): positions are shifted by the SDC xy
    at the current step but not rotated, and no random frame augmentation is applied.

    Args:
        scenario: the scenario, file coordinates.
        cfg: limits and split behaviour; default ``TokenConfig()``.
        rng: draws the random exits of the destination walk; default
            ``scenario_rng(scenario.scenario_id)`` (deterministic per scenario).

    Returns:
        The tokens, padded to ``cfg``'s limits.

    Raises:
        ValueError: when the relevant agents alone exceed ``cfg.max_agents``.
    """
    cfg = cfg if cfg is not None else TokenConfig()
    rng = rng if rng is not None else scenario_rng(scenario.scenario_id)
    origin = scene_origin(scenario)
    history = np.zeros_like(scenario.tracks.valid)
    # Spec 1.6 step 1: map reference points are history positions in every split.
    history[:, : scenario.current_index + 1] = scenario.tracks.valid[
        :, : scenario.current_index + 1
    ]
    reference = relevant_positions(scenario, origin, history)

    all_pieces = build_map_pieces(scenario.road_map, origin, cfg)
    pieces = all_pieces.take(filter_map_pieces(all_pieces, reference, cfg))
    lights = attach_traffic_lights(scenario.signals, pieces, reference, cfg)
    agents = agent_attributes(scenario.tracks, select_agents(scenario, cfg, pieces), origin)
    states = agents.states
    goals = last_valid_goals(states.valid, states.pos, states.yaw, states.speed)
    dest = destination_labels(agents.object_type, goals, pieces, scenario.road_map, rng)
    return _assemble(scenario, cfg, origin, pieces, lights, agents, dest)


def _assemble(
    scenario: Scenario,
    cfg: TokenConfig,
    origin: np.ndarray,
    pieces: MapPieces,
    lights: TrafficLightTokens,
    agents: AgentAttributes,
    dest: np.ndarray,
) -> SceneTokens:
    """Pad every array to the limits and cast to the ``SceneTokens`` dtypes."""
    m, n, tl = cfg.max_map_pieces, cfg.max_agents, cfg.max_traffic_lights
    s = agents.states
    role = scenario.role_mask()[agents.track_index]
    f32 = np.float32
    return SceneTokens(
        scenario_id=scenario.scenario_id,
        origin=np.asarray(origin, np.float64),
        map_pos=_pad(pieces.pos, m, 0.0, f32),
        map_dir=_pad(pieces.dir, m, 0.0, f32),
        map_valid=_pad(pieces.valid, m, False, bool),
        map_class=_pad(pieces.map_class, m, -1, np.int64),
        map_feature_id=_pad(pieces.feature_id, m, -1, np.int64),
        map_boundary=map_boundary(pieces, agents, scenario.current_index).astype(f32),
        tl_piece=_pad(lights.piece, tl, -1, np.int64),
        tl_state=_pad(lights.state, tl, 0, np.int64),
        tl_valid=_pad(lights.valid, tl, False, bool),
        agent_track_index=_pad(agents.track_index, n, -1, np.int64),
        agent_valid=_pad(s.valid, n, False, bool),
        agent_pos=_pad(s.pos, n, 0.0, f32),
        agent_vel=_pad(s.vel, n, 0.0, f32),
        agent_speed=_pad(s.speed, n, 0.0, f32),
        agent_accel=_pad(s.accel, n, 0.0, f32),
        agent_yaw=_pad(s.yaw, n, 0.0, f32),
        agent_yaw_rate=_pad(s.yaw_rate, n, 0.0, f32),
        agent_type=_pad(agents.object_type, n, 0, np.int64),
        agent_size=_pad(agents.size, n, 0.0, f32),
        agent_role=_pad(role, n, False, bool),
        agent_dest=_pad(dest, n, -1, np.int64),
    )
