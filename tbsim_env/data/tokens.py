"""``SceneTokens``: a scenario preprocessed into fixed-size token arrays (docs/model.md §1).

This is the contract between preprocessing (``tbsim_env.data.preprocess``) and its users:
the TrafficBots policy, the observation builder and the training cache. Arrays are numpy,
padded to the limits of a ``TokenConfig`` with ``valid`` masks beside them.

Frame: positions are in the scenario frame shifted by ``origin`` (the SDC xy at the current
step), *not rotated*, so float32 keeps centimetre precision. Add ``origin`` back to get the
file's coordinates. Everything the model computes is pairwise-relative, so the absence of a
rotation does not matter, except for the spec's axis-aligned map box: ``map_boundary`` is
axis-aligned in the spec's scene frame, the token frame rotated by ``frame_yaw`` (the SDC's
heading at the current step), so that it turns with the scene.

Shapes: M = max_map_pieces, P = piece_segments (20), L = max_traffic_lights,
N = max_agents, T = number of steps (91 for WOMD).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SceneTokens:
    """Token arrays of one scenario.

    Attributes:
        scenario_id: the scenario's id.
        origin: [2] float64, xy subtracted from every position (metres, file frame).
        frame_yaw: [] float64, yaw (rad) of the spec's scene frame (x along the SDC's heading
            at the current step) in the token frame; ``map_boundary`` is axis-aligned in it.
        map_pos: [M, P, 3] float32, start point of each segment (node) of each piece.
        map_dir: [M, P, 3] float32, segment vector p_{k+1} - p_k (not normalised, ~1 m).
        map_valid: [M, P] bool, node validity.
        map_class: [M] int64, ``MapClass`` value, -1 for padding.
        map_feature_id: [M] int64, source ``MapFeature.id``, -1 for padding.
        map_boundary: [4] float32, (x_min, x_max, y_min, y_max) over valid nodes, in the
            token frame rotated by ``frame_yaw`` (metres).
        tl_piece: [L] int64, row in the map arrays of the controlled lane piece, -1 padding.
        tl_state: [L, T] int64, ``TLState`` per step (UNKNOWN where not valid).
        tl_valid: [L, T] bool.
        agent_track_index: [N] int64, row in ``Scenario.tracks``, -1 for padding.
            The SDC is row 0.
        agent_valid: [N, T] bool (after gap filling: one contiguous interval per agent).
        agent_pos: [N, T, 3] float32, metres.
        agent_vel: [N, T, 2] float32, m/s.
        agent_speed: [N, T] float32, signed speed (negative when moving backwards), m/s.
        agent_accel: [N, T] float32, m/s^2, from the filled signed speed.
        agent_yaw: [N, T] float32, radians, **unwrapped** (continuous over time).
        agent_yaw_rate: [N, T] float32, rad/s, from the unwrapped yaw.
        agent_type: [N] int64, ``ObjectType`` value (0 for padding).
        agent_size: [N, 3] float32, mean (length, width, height) over valid steps.
        agent_role: [N, 3] bool, (is SDC, object of interest, track to predict).
        agent_dest: [N] int64, destination map-piece row (docs/model.md §1.7), -1 when none.
    """

    scenario_id: str
    origin: np.ndarray
    frame_yaw: np.ndarray
    map_pos: np.ndarray
    map_dir: np.ndarray
    map_valid: np.ndarray
    map_class: np.ndarray
    map_feature_id: np.ndarray
    map_boundary: np.ndarray
    tl_piece: np.ndarray
    tl_state: np.ndarray
    tl_valid: np.ndarray
    agent_track_index: np.ndarray
    agent_valid: np.ndarray
    agent_pos: np.ndarray
    agent_vel: np.ndarray
    agent_speed: np.ndarray
    agent_accel: np.ndarray
    agent_yaw: np.ndarray
    agent_yaw_rate: np.ndarray
    agent_type: np.ndarray
    agent_size: np.ndarray
    agent_role: np.ndarray
    agent_dest: np.ndarray
