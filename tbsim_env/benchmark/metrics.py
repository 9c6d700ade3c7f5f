"""The benchmark's per-episode metrics: pure functions of an ``EpisodeRecord`` (and the scene's
lanes), with nuPlan's definitions adapted to WOMD maps (``docs/benchmark.md``).

States are indexed 0..S (the start and after each step); "moving" means faster than
``BenchmarkConfig.stopped_speed``.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass

import numpy as np
import torch
from scipy.signal import savgol_filter

from tbsim_env.benchmark.config import BenchmarkConfig
from tbsim_env.benchmark.episode import EpisodeRecord
from tbsim_env.core.constants import MapFeatureType, ObjectType
from tbsim_env.data.scenario import Scenario
from tbsim_env.sim.collision import pairwise_overlap

MPH = 0.44704
"""m/s per mile per hour (WOMD lane speed limits are in mph)."""
BIKE_LANE = 3
"""WOMD lane type of bike lanes (``LaneCenter.type``): not a lane a car drives on."""


class CollisionKind(enum.Enum):
    """nuPlan's collision types, by the ego's and the other's state at first contact."""

    STOPPED_EGO = "stopped_ego"  # the ego stands: not its fault
    STOPPED_TRACK = "stopped_track"  # the ego hits a standing agent: its fault
    ACTIVE_FRONT = "active_front"  # the ego's front hits a moving agent: its fault
    ACTIVE_REAR = "active_rear"  # a moving agent hits the ego's rear: not its fault
    ACTIVE_LATERAL = "active_lateral"  # side contact: the ego's fault when it straddles lanes


@dataclass(frozen=True)
class CollisionEvent:
    """The first step of a contact between the ego and another agent.

    Attributes:
        step: state index (1..S); other_id: the other's track id; other_type: its
            ``ObjectType``; kind: the collision type; at_fault: the ego's fault.
    """

    step: int
    other_id: int
    other_type: int
    kind: CollisionKind
    at_fault: bool


@dataclass(frozen=True)
class LaneIndex:
    """Lane centre-line segments of a scene (bike lanes left out), for nearest-lane queries.

    Attributes:
        start: [K, 2] m; direction: [K, 2] unit vectors; length: [K] m.
        speed_limit: [K] m/s of the segment's lane (0: unknown).
    """

    start: np.ndarray
    direction: np.ndarray
    length: np.ndarray
    speed_limit: np.ndarray

    @staticmethod
    def of(scenario: Scenario) -> LaneIndex:
        m = scenario.road_map
        starts, dirs, lens, limits = [], [], [], []
        for k in m.indices_of(MapFeatureType.LANE):
            if int(m.subtype[k]) == BIKE_LANE or len(m.polylines[k]) < 2:
                continue
            p = m.polylines[k][:, :2].astype(np.float64)
            d = np.diff(p, axis=0)
            n = np.linalg.norm(d, axis=-1)
            keep = n > 1e-6
            starts.append(p[:-1][keep])
            dirs.append(d[keep] / n[keep, None])
            lens.append(n[keep])
            limits.append(np.full(int(keep.sum()), float(m.speed_limit_mph[k]) * MPH))
        if not starts:
            z = np.zeros((0, 2))
            return LaneIndex(z, z, np.zeros(0), np.zeros(0))
        return LaneIndex(*(np.concatenate(a) for a in (starts, dirs, lens, limits)))


@dataclass(frozen=True)
class LaneContext:
    """The lane the ego is on at each state: among the centre lines within
    ``lane_radius``, the one whose direction best matches the ego's heading.

    Attributes:
        direction: [S + 1, 2] unit direction of that lane (zero where no lane is near).
        offset: [S + 1] m from the ego's centre to its centre line (inf where none is near).
        speed_limit: [S + 1] m/s (0: unknown or no lane).
    """

    direction: np.ndarray
    offset: np.ndarray
    speed_limit: np.ndarray


def _near_track(lanes: LaneIndex, xy: np.ndarray, radius: float) -> LaneIndex:
    """The segments that may lie within ``radius`` of a point of ``xy`` [S, 2] (a bounding-box
    test of their start, widened by the longest segment)."""
    if len(lanes.length) == 0:
        return lanes
    reach = radius + float(lanes.length.max())
    lo, hi = xy.min(0) - reach, xy.max(0) + reach
    keep = ((lanes.start >= lo) & (lanes.start <= hi)).all(-1)
    return LaneIndex(
        lanes.start[keep], lanes.direction[keep], lanes.length[keep], lanes.speed_limit[keep]
    )


def lane_context(record: EpisodeRecord, lanes: LaneIndex, cfg: BenchmarkConfig) -> LaneContext:
    """The ``LaneContext`` of the ego's states."""
    n = len(record.ego_pose)
    lanes = _near_track(lanes, record.ego_pose[:, :2], cfg.lane_radius)
    if len(lanes.length) == 0:
        return LaneContext(np.zeros((n, 2)), np.full(n, np.inf), np.zeros(n))
    xy = record.ego_pose[:, None, :2] - lanes.start[None]  # [S+1, K, 2]
    along = np.clip((xy * lanes.direction).sum(-1), 0.0, lanes.length)
    foot = lanes.start + along[..., None] * lanes.direction
    dist = np.linalg.norm(record.ego_pose[:, None, :2] - foot, axis=-1)
    heading = np.stack([np.cos(record.ego_pose[:, 2]), np.sin(record.ego_pose[:, 2])], -1)
    align = (lanes.direction[None] * heading[:, None]).sum(-1)  # cos of the angle
    near = dist <= cfg.lane_radius
    best = np.argmax(np.where(near, align, -np.inf), axis=-1)
    has = near.any(-1)
    rows = np.arange(n)
    return LaneContext(
        direction=np.where(has[:, None], lanes.direction[best], 0.0),
        offset=np.where(has, dist[rows, best], np.inf),
        speed_limit=np.where(has, lanes.speed_limit[best], 0.0),
    )


def _overlaps(record: EpisodeRecord, pose: np.ndarray) -> np.ndarray:
    """[S + 1, N] bool: the ego box at ``pose`` [S + 1, 3] overlaps each valid other's box."""
    ego = torch.as_tensor(pose)[:, None]  # [S+1, 1, 3]
    size = torch.as_tensor(np.broadcast_to(record.ego_size, (len(pose), 1, 2)).copy())
    others = torch.as_tensor(record.others_pose)
    osize = torch.as_tensor(
        np.broadcast_to(record.others_size, record.others_pose.shape[:2] + (2,)).copy()
    )
    hit = pairwise_overlap(ego, size, others, osize)[:, 0].numpy()
    return hit & record.others_valid


def _ego_part(pose: np.ndarray, size: np.ndarray, sign: float) -> np.ndarray:
    """[S + 1, 3] pose of the front (sign +1) or rear (-1) quarter of the ego's box."""
    shift = sign * 0.375 * size[0]
    out = pose.copy()
    out[:, 0] += shift * np.cos(pose[:, 2])
    out[:, 1] += shift * np.sin(pose[:, 2])
    return out


def collision_events(
    record: EpisodeRecord, lanes: LaneContext, cfg: BenchmarkConfig
) -> list[CollisionEvent]:
    """Every contact the ego starts with another agent, classified as nuPlan does.

    A contact starts at a state where the boxes overlap and did not at the previous one.
    The ego standing: not at fault; the other standing: at fault; else by where the other's
    box touches the ego's: its front quarter (at fault), only its rear quarter (not at fault),
    else the side (at fault when the ego straddles lanes or is off the road).
    """
    hit = _overlaps(record, record.ego_pose)
    start = hit & ~np.vstack([np.zeros((1, hit.shape[1]), bool), hit[:-1]])
    start[0] = False  # contacts at the start are the log's
    steps, others = np.nonzero(start)
    if len(steps) == 0:
        return []
    quarter = np.array([record.ego_size[0] / 4, record.ego_size[1]])
    size = torch.as_tensor(np.broadcast_to(quarter, (len(steps), 1, 2)).copy())
    other = torch.as_tensor(record.others_pose[steps, others][:, None])
    osize = torch.as_tensor(record.others_size[others][:, None])
    touches = {}
    for sign in (1.0, -1.0):
        part = torch.as_tensor(_ego_part(record.ego_pose[steps], record.ego_size, sign)[:, None])
        touches[sign] = pairwise_overlap(part, size, other, osize)[:, 0, 0].numpy()
    off_lane = (lanes.offset[steps] > cfg.lane_straddle) | (record.offroad_distance[steps] > 0.0)
    events = []
    for k, (s, o) in enumerate(zip(steps.tolist(), others.tolist())):
        if record.ego_speed[s] < cfg.stopped_speed:
            kind = CollisionKind.STOPPED_EGO
        elif abs(record.others_speed[s, o]) < cfg.stopped_speed:
            kind = CollisionKind.STOPPED_TRACK
        elif touches[1.0][k]:
            kind = CollisionKind.ACTIVE_FRONT
        elif touches[-1.0][k]:
            kind = CollisionKind.ACTIVE_REAR
        else:
            kind = CollisionKind.ACTIVE_LATERAL
        fault = kind in (CollisionKind.STOPPED_TRACK, CollisionKind.ACTIVE_FRONT) or (
            kind is CollisionKind.ACTIVE_LATERAL and bool(off_lane[k])
        )
        events.append(
            CollisionEvent(s, int(record.others_id[o]), int(record.others_type[o]), kind, fault)
        )
    return events


def no_at_fault_collisions(events: list[CollisionEvent]) -> float:
    """1; 0.5 when the ego's faults hit only objects of type OTHER (nuPlan's static objects);
    0 when one hits a vehicle, pedestrian or cyclist."""
    fault = [e for e in events if e.at_fault]
    if not fault:
        return 1.0
    return 0.5 if all(e.other_type == int(ObjectType.OTHER) for e in fault) else 0.0


def drivable_area_compliance(record: EpisodeRecord, cfg: BenchmarkConfig) -> float:
    """0 when a corner of the ego's box gets farther than ``drivable_violation`` beyond a
    road edge, else 1."""
    return float(not (record.offroad_distance[1:] > cfg.drivable_violation).any())


def wrong_way_distance(record: EpisodeRecord, lanes: LaneContext, cfg: BenchmarkConfig) -> float:
    """m: the largest progress against its lane's direction the ego makes in a window of
    ``direction_window_s`` (steps with no lane near count nothing)."""
    step = np.diff(record.ego_pose[:, :2], axis=0)  # [S, 2]
    along = (step * lanes.direction[:-1]).sum(-1)
    against = np.clip(-along, 0.0, None)
    w = max(1, round(cfg.direction_window_s / record.dt))
    if len(against) == 0:
        return 0.0
    sums = np.convolve(against, np.ones(w), mode="valid") if len(against) >= w else [against.sum()]
    return float(np.max(sums))


def driving_direction_compliance(distance: float, cfg: BenchmarkConfig) -> float:
    """1 below ``direction_ok`` m against the lane in a window, 0.5 below ``direction_bad``,
    else 0."""
    return 1.0 if distance < cfg.direction_ok else 0.5 if distance < cfg.direction_bad else 0.0


def ego_progress(record: EpisodeRecord) -> float:
    """m the ego advanced along its logged route over the episode."""
    return float(record.progress[-1] - record.progress[0])


def progress_ratio(record: EpisodeRecord, cfg: BenchmarkConfig) -> float:
    """Ego progress over expert progress in [0, 1] (1 when the expert advanced less than
    ``min_expert_progress``)."""
    if record.expert_progress < cfg.min_expert_progress:
        return 1.0
    return float(np.clip(ego_progress(record) / record.expert_progress, 0.0, 1.0))


def route_completion(record: EpisodeRecord) -> float:
    """Share of the logged route from the start to its end the ego covered, in [0, 1]."""
    if record.route_length <= 1e-6:
        return 1.0
    return float(np.clip(ego_progress(record) / record.route_length, 0.0, 1.0))


def _projected(pose: np.ndarray, speed: np.ndarray, t: np.ndarray) -> np.ndarray:
    """[..., H, 3] poses at times ``t`` [H] s of constant-velocity motion from ``pose``
    [..., 3] at signed ``speed`` [...] m/s."""
    d = speed[..., None] * t  # [..., H]
    out = np.repeat(pose[..., None, :], len(t), axis=-2)
    out[..., 0] += d * np.cos(pose[..., None, 2])
    out[..., 1] += d * np.sin(pose[..., None, 2])
    return out


def min_time_to_collision(record: EpisodeRecord, cfg: BenchmarkConfig) -> float:
    """s: the least time within ``ttc_horizon`` after which the moving ego and an agent ahead
    of it, both projected at constant velocity, would overlap (inf if never). Agents already
    in contact with the ego are left out, as nuPlan does."""
    t = np.arange(1, round(cfg.ttc_horizon / cfg.ttc_step) + 1) * cfg.ttc_step  # [H]
    rows = np.flatnonzero(np.abs(record.ego_speed[1:]) >= cfg.stopped_speed) + 1
    if len(rows) == 0:
        return float("inf")
    ego = record.ego_pose[rows]  # [R, 3]
    rel = record.others_pose[rows, :, :2] - ego[:, None, :2]
    ahead = rel[..., 0] * np.cos(ego[:, None, 2]) + rel[..., 1] * np.sin(ego[:, None, 2]) > 0
    touching = _overlaps(record, record.ego_pose)[rows]
    watch = record.others_valid[rows] & ahead & ~touching  # [R, N]
    if not watch.any():
        return float("inf")
    ego_f = _projected(ego, record.ego_speed[rows], t)  # [R, H, 3]
    oth_f = _projected(record.others_pose[rows], record.others_speed[rows], t)  # [R, N, H, 3]
    n = oth_f.shape[1]
    size = torch.as_tensor(np.broadcast_to(record.ego_size, (*ego_f.shape[:2], 1, 2)).copy())
    osize = torch.as_tensor(
        np.broadcast_to(record.others_size[:, None], (len(rows), n, len(t), 2))
        .transpose(0, 2, 1, 3)
        .copy()
    )
    hit = pairwise_overlap(
        torch.as_tensor(ego_f[:, :, None]),
        size,
        torch.as_tensor(oth_f.transpose(0, 2, 1, 3)),
        osize,
    )[:, :, 0].numpy()  # [R, H, N]
    hit &= watch[:, None, :]
    if not hit.any():
        return float("inf")
    return float(t[np.nonzero(hit.any(-1))[1]].min())


def speed_limit_compliance(
    record: EpisodeRecord, lanes: LaneContext, cfg: BenchmarkConfig
) -> float | None:
    """``max(0, 1 - sum(over-speed * dt) / (max_overspeed * duration))`` over the states with
    a known limit; None when the map gives none (the metric then does not count)."""
    known = lanes.speed_limit[1:] > 0
    if not known.any():
        return None
    over = np.clip(np.abs(record.ego_speed[1:]) - lanes.speed_limit[1:], 0.0, None) * known
    duration = record.dt * len(over)
    return float(max(0.0, 1.0 - over.sum() * record.dt / (cfg.max_overspeed * duration)))


@dataclass(frozen=True)
class Comfort:
    """Extremes of the ego's motion (Savitzky-Golay derivatives) and whether all are within
    ``ComfortBounds``.

    Attributes:
        lon_accel: (min, max) m/s^2; lat_accel, yaw_rate, yaw_accel, lon_jerk, jerk: max |.|
            (m/s^2, rad/s, rad/s^2, m/s^3, m/s^3); ok: all within bounds.
    """

    lon_accel: tuple[float, float]
    lat_accel: float
    yaw_rate: float
    yaw_accel: float
    lon_jerk: float
    jerk: float
    ok: bool


def comfort(record: EpisodeRecord, cfg: BenchmarkConfig) -> Comfort:
    """The ego's ``Comfort``: longitudinal acceleration and jerk from its speed, yaw rate
    and yaw acceleration from its unwrapped heading, lateral acceleration as speed times yaw
    rate (smoothed as the accelerations are), jerk as the magnitude of the body-frame
    acceleration's derivative; Savitzky-Golay windows of ``ComfortBounds``."""
    b = cfg.comfort
    n = len(record.ego_speed)
    if n < 3:
        return Comfort((0.0, 0.0), 0.0, 0.0, 0.0, 0.0, 0.0, True)

    def d(y: np.ndarray, order: int, window: int) -> np.ndarray:
        w = min(window, n if n % 2 else n - 1)
        return savgol_filter(y, w, min(2, w - 1), deriv=order, delta=record.dt, mode="interp")

    speed, yaw = record.ego_speed, np.unwrap(record.ego_pose[:, 2])
    yaw_rate, yaw_acc = d(yaw, 1, b.yaw_window), d(yaw, 2, b.yaw_window)
    lon_acc = d(speed, 1, b.accel_window)
    lat_acc = d(speed * yaw_rate, 0, b.accel_window)
    lon_jerk, lat_jerk = d(lon_acc, 1, b.accel_window), d(lat_acc, 1, b.accel_window)
    out = Comfort(
        lon_accel=(float(lon_acc.min()), float(lon_acc.max())),
        lat_accel=float(np.abs(lat_acc).max()),
        yaw_rate=float(np.abs(yaw_rate).max()),
        yaw_accel=float(np.abs(yaw_acc).max()),
        lon_jerk=float(np.abs(lon_jerk).max()),
        jerk=float(np.hypot(lon_jerk, lat_jerk).max()),
        ok=True,
    )
    ok = (
        b.min_lon_accel <= out.lon_accel[0]
        and out.lon_accel[1] <= b.max_lon_accel
        and out.lat_accel <= b.max_abs_lat_accel
        and out.yaw_rate <= b.max_abs_yaw_rate
        and out.yaw_accel <= b.max_abs_yaw_accel
        and out.lon_jerk <= b.max_abs_lon_jerk
        and out.jerk <= b.max_abs_jerk
    )
    return Comfort(**{**out.__dict__, "ok": bool(ok)})
