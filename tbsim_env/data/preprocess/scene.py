"""``preprocess_scenario``: a ``Scenario`` -> padded ``SceneTokens`` (docs/model.md §1).

Order of the steps: frame origin and yaw, map pieces, map filtering, traffic-light tokens, agent
selection, gap filling, destinations, padding to the ``TokenConfig`` limits.
"""

from __future__ import annotations

import hashlib

import numpy as np

from tbsim_env.core.config import TokenConfig
from tbsim_env.data.preprocess.agents import AgentAttributes, agent_attributes
from tbsim_env.data.preprocess.destination import destination_labels, last_valid_goals
from tbsim_env.data.preprocess.map_filter import filter_map_pieces, rotate_xy
from tbsim_env.data.preprocess.map_pieces import MapPieces, build_map_pieces
from tbsim_env.data.preprocess.selection import relevant_positions, select_agents
from tbsim_env.data.preprocess.traffic_lights import TrafficLightTokens, attach_traffic_lights
from tbsim_env.data.scenario import Scenario
from tbsim_env.data.tokens import SceneTokens


def scenario_rng(scenario_id: str) -> np.random.Generator:
    """A generator seeded from a stable hash (SHA-256) of the scenario id."""
    digest = hashlib.sha256(scenario_id.encode("utf-8")).digest()
    return np.random.default_rng(int.from_bytes(digest[:8], "little"))


def _frame_step(scenario: Scenario) -> int | None:
    """Step of the SDC state that places the scene frame: the current step; if the SDC is not
    valid then, its last valid history step, else its first valid step (not in the spec, which
    assumes a valid SDC); None if the SDC is never valid."""
    valid = scenario.tracks.valid[scenario.sdc_index]
    if valid[scenario.current_index]:
        return scenario.current_index
    history = np.flatnonzero(valid[: scenario.current_index + 1])
    if history.shape[0]:
        return int(history[-1])
    anywhere = np.flatnonzero(valid)
    return int(anywhere[0]) if anywhere.shape[0] else None


def scene_origin(scenario: Scenario) -> np.ndarray:
    """[2] float64 SDC xy at the current step (see ``_frame_step``), (0, 0) without any."""
    step = _frame_step(scenario)
    if step is None:
        return np.zeros(2)
    return scenario.tracks.xyz[scenario.sdc_index, step, :2].astype(np.float64)


def scene_yaw(scenario: Scenario) -> float:
    """SDC heading (rad) at the step of ``scene_origin``, the x-axis of the spec's scene frame
    (1.5); 0 without any valid SDC state."""
    step = _frame_step(scenario)
    if step is None:
        return 0.0
    return float(scenario.tracks.heading[scenario.sdc_index, step])


def _pad(array: np.ndarray, size: int, fill: float | int | bool, dtype: type) -> np.ndarray:
    """Pad the first axis of ``array`` to ``size`` with ``fill``, cast to ``dtype``."""
    out = np.full((size, *array.shape[1:]), fill, dtype=dtype)
    out[: array.shape[0]] = array
    return out


def map_boundary(
    pieces: MapPieces, agents: AgentAttributes, current_index: int, frame_yaw: float = 0.0
) -> np.ndarray:
    """[4] (x_min, x_max, y_min, y_max) over valid map nodes; without map, over the agents'
    valid history positions (docs/model.md §1.6); zeros if neither exists.

    The box is axis-aligned in the spec's scene frame: the token frame rotated by
    ``frame_yaw`` (rad). Tokens are not rotated into that frame (a deviation, see
    ``preprocess_scenario``), but the box is, so that which agents leave the map does not
    depend on the orientation of the file's world frame.
    """
    if pieces.valid.any():
        xy = pieces.pos[pieces.valid][:, :2]
    else:
        hist = agents.states.valid[:, : current_index + 1]
        xy = agents.states.pos[:, : current_index + 1][hist][:, :2]
    if xy.shape[0] == 0:
        return np.zeros(4)
    xy = rotate_xy(xy, -frame_yaw)
    return np.array([xy[:, 0].min(), xy[:, 0].max(), xy[:, 1].min(), xy[:, 1].max()])


def preprocess_scenario(
    scenario: Scenario, cfg: TokenConfig | None = None, *, rng: np.random.Generator | None = None
) -> SceneTokens:
    """Preprocess one scenario into fixed-size token arrays.

    Deliberate deviations from the reference (docs/model.md §1.5): positions are shifted by the SDC
    xy at the current step but not rotated, and no random frame augmentation is applied. The
    steps of the spec that depend on the frame's orientation (the map box filter and
    ``map_boundary``) still use the spec's scene frame, x along the SDC's heading
    (``frame_yaw``), so the tokens of a rotated scene are the rotated tokens.

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
    origin, frame_yaw = scene_origin(scenario), scene_yaw(scenario)
    history = np.zeros_like(scenario.tracks.valid)
    # docs/model.md §1.6 step 1: map reference points are history positions in every split.
    history[:, : scenario.current_index + 1] = scenario.tracks.valid[
        :, : scenario.current_index + 1
    ]
    reference = relevant_positions(scenario, origin, history)

    all_pieces = build_map_pieces(scenario.road_map, origin, cfg)
    pieces = all_pieces.take(filter_map_pieces(all_pieces, reference, cfg, frame_yaw))
    lights = attach_traffic_lights(scenario.signals, pieces, reference, cfg)
    agents = agent_attributes(scenario.tracks, select_agents(scenario, cfg, pieces), origin)
    states = agents.states
    goals = last_valid_goals(states.valid, states.pos, states.yaw, states.speed)
    dest = destination_labels(agents.object_type, goals, pieces, scenario.road_map, rng)
    return _assemble(scenario, cfg, origin, frame_yaw, pieces, lights, agents, dest)


def _assemble(
    scenario: Scenario,
    cfg: TokenConfig,
    origin: np.ndarray,
    frame_yaw: float,
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
        frame_yaw=np.asarray(frame_yaw, np.float64),
        map_pos=_pad(pieces.pos, m, 0.0, f32),
        map_dir=_pad(pieces.dir, m, 0.0, f32),
        map_valid=_pad(pieces.valid, m, False, bool),
        map_class=_pad(pieces.map_class, m, -1, np.int64),
        map_feature_id=_pad(pieces.feature_id, m, -1, np.int64),
        map_boundary=map_boundary(pieces, agents, scenario.current_index, frame_yaw).astype(f32),
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
