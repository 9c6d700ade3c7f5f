"""Destination label of each agent: one map-piece row (TrafficBots V1.5, docs/model.md §1.7)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tbsim_env.core.constants import MapClass, ObjectType
from tbsim_env.data.preprocess import spec
from tbsim_env.data.preprocess.map_pieces import VEHICLE_LANE_CLASSES, MapPieces
from tbsim_env.data.scenario import RoadMap

NO_DESTINATION = -1


@dataclass(frozen=True)
class Goals:
    """Last valid state of each agent (docs/model.md §1.4 ``goal``).

    Attributes:
        pos: [N, 2] float64 xy, metres (map frame).
        yaw: [N] float64 radians.
        speed: [N] float64 signed speed, m/s.
        valid: [N] bool, the agent has a valid step at all.
    """

    pos: np.ndarray
    yaw: np.ndarray
    speed: np.ndarray
    valid: np.ndarray


def last_valid_goals(
    valid: np.ndarray, pos: np.ndarray, yaw: np.ndarray, speed: np.ndarray
) -> Goals:
    """Goals from per-step states.

    Args:
        valid: [N, T] bool.
        pos: [N, T, >=2] metres.
        yaw: [N, T] radians.
        speed: [N, T] m/s.
    """
    rows = np.arange(valid.shape[0])
    last = valid.shape[1] - 1 - np.argmax(valid[:, ::-1], axis=1)
    return Goals(
        pos=np.asarray(pos, np.float64)[rows, last, :2],
        yaw=np.asarray(yaw, np.float64)[rows, last],
        speed=np.asarray(speed, np.float64)[rows, last],
        valid=valid.any(axis=1),
    )


@dataclass(frozen=True)
class _Nodes:
    """Flattened valid nodes of some classes: xy [Q, 2], dir xy [Q, 2], piece row [Q]."""

    xy: np.ndarray
    dir: np.ndarray
    piece: np.ndarray


def _nodes(pieces: MapPieces, classes: tuple[int, ...]) -> _Nodes:
    """The valid nodes of the pieces whose class is in ``classes``."""
    mask = pieces.valid & np.isin(pieces.map_class, classes)[:, None]
    row = np.broadcast_to(np.arange(pieces.num_pieces)[:, None], mask.shape)
    return _Nodes(xy=pieces.pos[mask][:, :2], dir=pieces.dir[mask][:, :2], piece=row[mask])


def _nearest_aligned(points: np.ndarray, yaw: np.ndarray, nodes: _Nodes) -> np.ndarray:
    """[N] node index of the nearest node within 3 m (xy) with dir . heading > 0, or -1."""
    if nodes.piece.shape[0] == 0 or points.shape[0] == 0:
        return np.full(points.shape[0], -1, np.int64)
    d2 = ((points[:, None, :] - nodes.xy[None]) ** 2).sum(-1)
    unit = np.stack([np.cos(yaw), np.sin(yaw)], axis=-1)
    ok = (d2 < spec.DEST_LANE_DISTANCE**2) & (unit @ nodes.dir.T > 0.0)
    best = np.argmin(np.where(ok, d2, np.inf), axis=1)
    return np.where(ok.any(axis=1), best, -1)


def _nearest(points: np.ndarray, nodes: _Nodes) -> np.ndarray:
    """[N] piece row of the nearest node (xy), or -1 when there is no node."""
    if nodes.piece.shape[0] == 0:
        return np.full(points.shape[0], NO_DESTINATION, np.int64)
    d2 = ((points[:, None, :] - nodes.xy[None]) ** 2).sum(-1)
    return nodes.piece[np.argmin(d2, axis=1)]


def walk_lane_graph(
    start_lane: int,
    exit_lanes: dict[int, np.ndarray],
    last_piece: dict[int, int],
    rng: np.random.Generator,
) -> int:
    """Follow random exits from ``start_lane``; return the final candidate lane id.

    At each hop a random exit edge (lane, next) is drawn (lane, -1 when there is no exit);
    ``lane`` becomes the candidate. The walk stops when ``next`` is not a kept vehicle lane, when
    the lane just left had several exits and >= 2 hops are done, or after 4 hops
    (docs/model.md §1.7).

    Args:
        start_lane: feature id of the lane matched at the goal (a kept vehicle lane).
        exit_lanes: lane id -> [e] successor lane ids.
        last_piece: kept vehicle-lane id -> row of its last kept piece.
        rng: the generator the exits are drawn from.

    Returns:
        Feature id of the destination lane (a key of ``last_piece``).
    """
    lane, hops = start_lane, 0
    while True:
        exits = exit_lanes.get(lane, np.zeros(0, np.int64))
        options = exits if exits.shape[0] > 0 else np.array([-1])
        nxt = int(options[rng.integers(options.shape[0])])
        candidate, hops = lane, hops + 1
        if nxt not in last_piece:
            break
        if options.shape[0] > 1 and hops >= spec.DEST_BRANCH_MIN_HOPS:
            break
        if hops >= spec.DEST_MAX_HOPS:
            break
        lane = nxt
    return candidate


def destination_labels(
    object_type: np.ndarray,
    goals: Goals,
    pieces: MapPieces,
    road_map: RoadMap,
    rng: np.random.Generator,
) -> np.ndarray:
    """Destination piece row of each agent (docs/model.md §1.7).

    Vehicles: the lane under the goal (node within 3 m, aligned with the goal heading), then a
    random walk of up to 4 hops over exits; the destination is the last kept piece of the final
    lane. Without a matching lane, and for pedestrians, the ROAD_EDGE_BOUNDARY node nearest the
    extended goal (goal + 5 s * speed * heading). Cyclists: the nearest aligned BIKE_LANE node
    within 3 m of the extended goal, else the boundary rule. TYPE_UNSET/TYPE_OTHER agents use
    the vehicle rule (deliberate: the reference has no slot for them).

    Args:
        object_type: [N] int ``ObjectType`` values.
        goals: last valid states, map frame.
        pieces: the kept map pieces (row = token map row).
        road_map: the scenario map (for the exit lanes).
        rng: draws the random exits, one per hop, agents in order.

    Returns:
        [N] int64 piece rows, -1 when there is no usable node or the agent is never valid.
    """
    n = object_type.shape[0]
    extended = goals.pos + spec.DEST_EXTEND_SECONDS * goals.speed[:, None] * np.stack(
        [np.cos(goals.yaw), np.sin(goals.yaw)], axis=-1
    )
    boundary = _nearest(extended, _nodes(pieces, (int(MapClass.ROAD_EDGE_BOUNDARY),)))
    dest = boundary.copy()

    cyclist = object_type == ObjectType.CYCLIST
    bike = _nodes(pieces, (int(MapClass.BIKE_LANE),))
    bike_hit = _nearest_aligned(extended[cyclist], goals.yaw[cyclist], bike)
    if bike.piece.shape[0] > 0:
        hit_piece = bike.piece[np.maximum(bike_hit, 0)]
        dest[cyclist] = np.where(bike_hit >= 0, hit_piece, boundary[cyclist])

    vehicle_like = ~np.isin(object_type, (int(ObjectType.PEDESTRIAN), int(ObjectType.CYCLIST)))
    lanes = _nodes(pieces, VEHICLE_LANE_CLASSES)
    lane_hit = np.full(n, -1, np.int64)
    lane_hit[vehicle_like] = _nearest_aligned(
        goals.pos[vehicle_like], goals.yaw[vehicle_like], lanes
    )
    if (lane_hit >= 0).any():
        is_lane = np.isin(pieces.map_class, VEHICLE_LANE_CLASSES)
        # Later rows overwrite earlier ones: the last kept piece of each lane.
        last_piece = {
            int(f): int(r) for r, f in zip(np.flatnonzero(is_lane), pieces.feature_id[is_lane])
        }
        exits = {int(i): road_map.exit_lanes[k] for k, i in enumerate(road_map.id)}
        for a in np.flatnonzero(lane_hit >= 0):
            start = int(pieces.feature_id[lanes.piece[lane_hit[a]]])
            dest[a] = last_piece[walk_lane_graph(start, exits, last_piece, rng)]
    return np.where(goals.valid, dest, NO_DESTINATION).astype(np.int64)
