"""Choose at most ``max_agents`` simulated agents.

docs/model.md §1.6 (the reference's ``filter_episode_agents``).
"""

from __future__ import annotations

import numpy as np

from tbsim_env.core.config import TokenConfig
from tbsim_env.core.constants import DT, ObjectType
from tbsim_env.data.preprocess import spec
from tbsim_env.data.preprocess.agents import signed_speed
from tbsim_env.data.preprocess.map_filter import min_distance, prune_by_distance
from tbsim_env.data.preprocess.map_pieces import VEHICLE_LANE_CLASSES, MapPieces
from tbsim_env.data.scenario import Scenario, wrap_angle_np

_SIMULATED_TYPES = (int(ObjectType.VEHICLE), int(ObjectType.PEDESTRIAN), int(ObjectType.CYCLIST))
"""Types a non-relevant agent must have to be selected."""


def relevant_mask(scenario: Scenario) -> np.ndarray:
    """[A] bool: SDC, objects of interest or tracks to predict."""
    return scenario.role_mask().any(axis=1)


def selection_window(scenario: Scenario, training: bool) -> np.ndarray:
    """[A, T] bool valid mask restricted to the steps agent selection may look at.

    Training looks at the whole episode; validation/test only at history (steps 0..current).
    """
    valid = scenario.tracks.valid.copy()
    if not training:
        valid[:, scenario.current_index + 1 :] = False
    return valid


def relevant_positions(scenario: Scenario, origin: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """[R, 3] float64 positions (shifted by origin) of the relevant agents at ``valid`` steps."""
    mask = valid & relevant_mask(scenario)[:, None]
    shift = np.array([origin[0], origin[1], 0.0])
    return scenario.tracks.xyz[mask].astype(np.float64) - shift


def _first_last(valid: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Values at the first and last valid step ([A, T, ...] -> two [A, ...]; step 0 if none)."""
    rows = np.arange(valid.shape[0])
    first = np.argmax(valid, axis=1)
    last = valid.shape[1] - 1 - np.argmax(valid[:, ::-1], axis=1)
    return values[rows, first], values[rows, last]


def _aligned_lane_nearby(
    pos_xy: np.ndarray, heading: np.ndarray, pieces: MapPieces, classes: tuple[int, ...]
) -> np.ndarray:
    """[A] bool: some node of the given classes within 3 m (xy) with dir . heading > 0."""
    rows = np.isin(pieces.map_class, classes)
    node_ok = pieces.valid[rows]
    nodes = pieces.pos[rows][node_ok][:, :2]
    dirs = pieces.dir[rows][node_ok][:, :2]
    if nodes.shape[0] == 0 or pos_xy.shape[0] == 0:
        return np.zeros(pos_xy.shape[0], bool)
    near = ((pos_xy[:, None, :] - nodes[None]) ** 2).sum(-1) < spec.PARKED_LANE_DISTANCE**2
    unit = np.stack([np.cos(heading), np.sin(heading)], axis=-1)
    aligned = unit @ dirs.T > 0.0
    return (near & aligned).any(axis=1)


def select_agents(
    scenario: Scenario, cfg: TokenConfig, pieces: MapPieces | None = None
) -> np.ndarray:
    """Track rows of the simulated agents: SDC first, then the others in track order.

    Relevant agents (SDC, objects_of_interest, tracks_to_predict) are never dropped. Filters,
    in order (docs/model.md §1.6): drop non-relevant TYPE_UNSET/TYPE_OTHER tracks (they have no slot
    in the policy; deliberate deviation); (a) never valid in history; (b, training) < 20 valid
    steps; then, while more than ``cfg.max_agents`` remain: (c) still and far from relevant
    agents and from the map; (d) parked vehicles; (e, training) heading glitches; (f) distance
    pruning from 120 m, halving. Filter d uses the vehicle's own first/last positions for its
    "far from relevant agents" test (fixes the stale-variable bug of the reference).

    Distances to agents and map nodes are 3-D; the "aligned lane node within 3 m" test is xy.
    Training looks at all steps, validation/test only at history (``cfg.training``).

    Args:
        scenario: the scenario.
        cfg: ``max_agents`` and ``training``.
        pieces: the kept map pieces (for filters c and d); None or empty means no map, in
            which case the first valid agents after the relevant ones are kept (docs/model.md §1.6).

    Returns:
        [n] int64 track indices, n <= cfg.max_agents.

    Raises:
        ValueError: when the relevant agents alone exceed ``cfg.max_agents``.
    """
    tracks = scenario.tracks
    relevant = relevant_mask(scenario)
    if relevant.sum() > cfg.max_agents:
        raise ValueError(
            f"scenario {scenario.scenario_id!r}: {int(relevant.sum())} relevant agents (SDC, "
            f"objects_of_interest, tracks_to_predict) exceed max_agents={cfg.max_agents}"
        )
    has_map = pieces is not None and pieces.num_pieces > 0
    origin = pieces.origin if pieces is not None else np.zeros(2)
    valid = selection_window(scenario, cfg.training)
    history = tracks.valid[:, : scenario.current_index + 1]
    known_type = np.isin(tracks.object_type, _SIMULATED_TYPES)
    keep = relevant | (known_type & history.any(axis=1))
    if cfg.training:
        keep &= relevant | (tracks.valid.sum(axis=1) >= spec.MIN_VALID_STEPS_TRAINING)

    if not has_map:
        # docs/model.md §1.6, scenarios without map: the relevant agents, then the first valid ones.
        others = np.flatnonzero(keep & ~relevant)[: cfg.max_agents - int(relevant.sum())]
        keep = relevant.copy()
        keep[others] = True
    if keep.sum() > cfg.max_agents:
        keep = _filter_still_and_parked(scenario, cfg, pieces, valid, relevant, keep, origin)
    if keep.sum() > cfg.max_agents and cfg.training:
        keep &= relevant | ~_heading_glitch(scenario, valid)
    if keep.sum() > cfg.max_agents:
        shift = np.array([origin[0], origin[1], 0.0])
        first, last = _first_last(valid, tracks.xyz.astype(np.float64) - shift)
        targets = relevant_positions(scenario, origin, valid)
        distance = np.minimum(min_distance(first, targets), min_distance(last, targets))
        keep = prune_by_distance(
            distance, keep, relevant, cfg.max_agents, spec.AGENT_PRUNE_START_RADIUS
        )
    rows = np.flatnonzero(keep)
    return np.concatenate([[scenario.sdc_index], rows[rows != scenario.sdc_index]]).astype(np.int64)


def _displacement(scenario: Scenario, valid: np.ndarray) -> np.ndarray:
    """[A] displacement proxy: sum of the *signed* speed * DT over valid steps (as the spec)."""
    spd = signed_speed(scenario.tracks.velocity, scenario.tracks.heading)
    return np.where(valid, spd, 0.0).sum(axis=1) * DT


def _filter_still_and_parked(
    scenario: Scenario,
    cfg: TokenConfig,
    pieces: MapPieces,
    valid: np.ndarray,
    relevant: np.ndarray,
    keep: np.ndarray,
    origin: np.ndarray,
) -> np.ndarray:
    """Filters c and d of docs/model.md §1.6; returns the new keep mask."""
    tracks = scenario.tracks
    shift = np.array([origin[0], origin[1], 0.0])
    first, last = _first_last(valid, tracks.xyz.astype(np.float64) - shift)
    targets = relevant_positions(scenario, origin, valid)
    to_agents = np.minimum(min_distance(first, targets), min_distance(last, targets))
    threshold = spec.STILL_DISPLACEMENT_TRAINING if cfg.training else spec.STILL_DISPLACEMENT_EVAL
    still = keep & ~relevant & (_displacement(scenario, valid) < threshold)
    nodes = pieces.pos[pieces.valid]
    rows = np.flatnonzero(still)
    to_map = np.full(tracks.num_tracks, np.inf)
    to_map[rows] = np.minimum(min_distance(first[rows], nodes), min_distance(last[rows], nodes))
    far = (to_agents > spec.STILL_FAR_DISTANCE) & (to_map > spec.STILL_FAR_DISTANCE)
    keep = keep & ~(still & far)
    if keep.sum() <= cfg.max_agents:
        return keep
    vehicle = tracks.object_type == ObjectType.VEHICLE
    candidates = np.flatnonzero(keep & still & vehicle)
    _, last_heading = _first_last(valid, tracks.heading.astype(np.float64))
    on_lane = np.zeros(tracks.num_tracks, bool)
    on_lane[candidates] = _aligned_lane_nearby(
        last[candidates, :2], last_heading[candidates], pieces, VEHICLE_LANE_CLASSES
    )
    parked = keep & still & vehicle & ~on_lane & (to_agents > spec.PARKED_FAR_DISTANCE)
    return keep & ~parked


def _heading_glitch(scenario: Scenario, valid: np.ndarray) -> np.ndarray:
    """[A] bool, filter e: a per-step |delta yaw| > 1.5 rad, or > 0.5 rad for slow agents."""
    tracks = scenario.tracks
    both = valid[:, 1:] & valid[:, :-1]
    heading = tracks.heading.astype(np.float64)
    jump = np.where(both, np.abs(wrap_angle_np(heading[:, 1:] - heading[:, :-1])), 0.0).max(
        axis=1, initial=0.0
    )
    slow_limit = np.where(
        tracks.object_type == ObjectType.VEHICLE,
        spec.YAW_JUMP_SLOW_DISPLACEMENT_VEHICLE,
        spec.YAW_JUMP_SLOW_DISPLACEMENT_OTHER,
    )
    slow = _displacement(scenario, valid) < slow_limit
    return (jump > spec.YAW_JUMP_MAX) | ((jump > spec.YAW_JUMP_SLOW) & slow)
