"""Builders of small synthetic scenarios for the preprocessing tests (no tests in here)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from tbsim_env.core.constants import NUM_STEPS, MapFeatureType, ObjectType
from tbsim_env.data.scenario import RoadMap, Scenario, Tracks, TrafficSignals, wrap_angle_np

CURRENT = 10


@dataclass
class Feature:
    """One map feature for ``make_road_map``."""

    id: int
    kind: MapFeatureType
    points: np.ndarray
    subtype: int = 0
    exits: tuple[int, ...] = ()
    controlled: tuple[int, ...] = field(default_factory=tuple)


def line(start: tuple[float, float], end: tuple[float, float], spacing: float = 0.5) -> np.ndarray:
    """[n, 3] points from start to end (z = 0) at ``spacing`` metres, end included."""
    a, b = np.array([*start, 0.0]), np.array([*end, 0.0])
    n = int(round(np.linalg.norm(b - a) / spacing)) + 1
    return a + np.linspace(0.0, 1.0, n)[:, None] * (b - a)


def make_road_map(features: list[Feature]) -> RoadMap:
    """A ``RoadMap`` from a list of features (file order)."""
    empty = np.zeros(0, np.int64)
    return RoadMap(
        id=np.array([f.id for f in features], np.int64),
        feature_type=np.array([int(f.kind) for f in features], np.int8),
        subtype=np.array([f.subtype for f in features], np.int8),
        polylines=tuple(np.asarray(f.points, np.float64) for f in features),
        speed_limit_mph=np.zeros(len(features), np.float32),
        entry_lanes=tuple(empty for _ in features),
        exit_lanes=tuple(np.array(f.exits, np.int64) for f in features),
        left_neighbors=tuple(empty for _ in features),
        right_neighbors=tuple(empty for _ in features),
        controlled_lanes=tuple(np.array(f.controlled, np.int64) for f in features),
    )


def straight_track(
    start: tuple[float, float], yaw: float, speed: float, num_steps: int = NUM_STEPS
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """xyz [T, 3], heading [T], velocity [T, 2] of constant-velocity motion."""
    t = np.arange(num_steps) * 0.1
    unit = np.array([np.cos(yaw), np.sin(yaw)])
    xyz = np.zeros((num_steps, 3))
    xyz[:, :2] = np.array(start) + t[:, None] * speed * unit
    xyz[:, 2] = 0.8
    heading = np.full(num_steps, yaw)
    velocity = np.tile(speed * unit, (num_steps, 1))
    return xyz, heading, velocity


@dataclass
class Agent:
    """One track for ``make_scenario``."""

    start: tuple[float, float]
    yaw: float = 0.0
    speed: float = 0.0
    kind: ObjectType = ObjectType.VEHICLE
    valid: np.ndarray | None = None


def make_scenario(
    agents: list[Agent],
    road_map: RoadMap | None = None,
    signals: TrafficSignals | None = None,
    sdc: int = 0,
    tracks_to_predict: tuple[int, ...] = (),
    objects_of_interest: tuple[int, ...] = (),
    scenario_id: str = "synthetic",
) -> Scenario:
    """A validated ``Scenario``; track ids are 100 + row."""
    motion = [straight_track(a.start, a.yaw, a.speed) for a in agents]
    valid = np.stack([a.valid if a.valid is not None else np.ones(NUM_STEPS, bool) for a in agents])
    xyz = np.stack([m[0] for m in motion]) * valid[..., None]
    heading = np.stack([m[1] for m in motion]) * valid
    velocity = np.stack([m[2] for m in motion]) * valid[..., None]
    size = np.where(
        np.array([a.kind == ObjectType.PEDESTRIAN for a in agents])[:, None, None],
        np.array([0.8, 0.8, 1.8]),
        np.array([4.5, 2.0, 1.6]),
    )
    size = np.broadcast_to(size, (len(agents), NUM_STEPS, 3)) * valid[..., None]
    tracks = Tracks(
        id=np.arange(100, 100 + len(agents), dtype=np.int64),
        object_type=np.array([int(a.kind) for a in agents], np.int8),
        xyz=xyz.astype(np.float64),
        heading=wrap_angle_np(heading).astype(np.float32),
        velocity=velocity.astype(np.float32),
        size=size.astype(np.float32),
        valid=valid,
    )
    return Scenario(
        scenario_id=scenario_id,
        timestamps=np.arange(NUM_STEPS) * 0.1,
        current_index=CURRENT,
        tracks=tracks,
        road_map=road_map if road_map is not None else RoadMap.empty(),
        signals=signals if signals is not None else TrafficSignals.empty(NUM_STEPS),
        sdc_index=sdc,
        tracks_to_predict=np.array(tracks_to_predict, np.int64),
        predict_difficulty=np.zeros(len(tracks_to_predict), np.int8),
        objects_of_interest=np.array(objects_of_interest, np.int64),
    ).validate()


def rotation(theta: float) -> np.ndarray:
    """[2, 2] rotation matrix."""
    c, s = np.cos(theta), np.sin(theta)
    return np.array([[c, -s], [s, c]])


def assert_tokens_equivariant(tok_a, tok_b, theta: float, atol: float = 2e-3) -> None:
    """``tok_b`` is ``tok_a`` rotated by ``theta`` (same selection, transformed positions)."""
    rot = rotation(theta)
    for name in (
        "map_valid",
        "map_class",
        "map_feature_id",
        "tl_piece",
        "tl_state",
        "tl_valid",
        "agent_track_index",
        "agent_valid",
        "agent_type",
        "agent_role",
        "agent_dest",
    ):
        np.testing.assert_array_equal(getattr(tok_a, name), getattr(tok_b, name), err_msg=name)
    np.testing.assert_allclose(tok_b.map_pos[..., :2], tok_a.map_pos[..., :2] @ rot.T, atol=atol)
    np.testing.assert_allclose(tok_b.map_pos[..., 2], tok_a.map_pos[..., 2], atol=atol)
    np.testing.assert_allclose(tok_b.map_dir[..., :2], tok_a.map_dir[..., :2] @ rot.T, atol=atol)
    np.testing.assert_allclose(
        tok_b.agent_pos[..., :2], tok_a.agent_pos[..., :2] @ rot.T, atol=atol
    )
    np.testing.assert_allclose(tok_b.agent_vel, tok_a.agent_vel @ rot.T, atol=atol)
    for name in ("agent_speed", "agent_accel", "agent_size"):
        np.testing.assert_allclose(getattr(tok_b, name), getattr(tok_a, name), atol=atol * 10)
    np.testing.assert_allclose(tok_b.agent_yaw_rate, tok_a.agent_yaw_rate, atol=atol * 10)
    dyaw = wrap_angle_np(tok_b.agent_yaw.astype(np.float64) - tok_a.agent_yaw - theta)
    np.testing.assert_allclose(np.where(tok_a.agent_valid, dyaw, 0.0), 0.0, atol=atol)
    # The map box turns with the scene: same bounds in the frame that turned by theta.
    np.testing.assert_allclose(tok_b.map_boundary, tok_a.map_boundary, atol=atol)
    dframe = wrap_angle_np(float(tok_b.frame_yaw) - float(tok_a.frame_yaw) - theta)
    assert abs(dframe) <= atol, ("frame_yaw", float(tok_a.frame_yaw), float(tok_b.frame_yaw))
