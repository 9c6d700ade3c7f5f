"""Map features -> map pieces of <= 20 segments (TrafficBots V1.5, docs/model.md §1.2).

A *piece* is one row of up to P nodes: node k holds the start point of segment k (``pos``) and
the segment vector to the next point (``dir``, not normalised, ~1 m). Positions are shifted by
``origin`` (float64 arithmetic); there is no rotation (deliberate deviation from the reference,
docs/model.md §1.5; see ``tbsim_env.data.tokens``).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from tbsim_env.core.config import TokenConfig
from tbsim_env.core.constants import (
    GEOMETRY_TIE_TOLERANCE,
    LaneType,
    MapClass,
    MapFeatureType,
    RoadEdgeType,
    RoadLineType,
)
from tbsim_env.data.scenario import RoadMap

_LOG = logging.getLogger(__name__)

NO_CLASS = -1
"""Class of a feature that yields no piece (stop sign, unknown road-line/edge type)."""

_LANE_CLASS = {
    int(LaneType.UNDEFINED): int(MapClass.SURFACE_STREET),
    int(LaneType.FREEWAY): int(MapClass.FREEWAY),
    int(LaneType.SURFACE_STREET): int(MapClass.SURFACE_STREET),
    int(LaneType.BIKE_LANE): int(MapClass.BIKE_LANE),
}
_ROAD_EDGE_CLASS = {
    int(RoadEdgeType.BOUNDARY): int(MapClass.ROAD_EDGE_BOUNDARY),
    int(RoadEdgeType.MEDIAN): int(MapClass.ROAD_EDGE_MEDIAN),
}
_ROAD_LINE_CLASS = {
    int(RoadLineType.BROKEN_SINGLE_WHITE): int(MapClass.BROKEN),
    int(RoadLineType.BROKEN_SINGLE_YELLOW): int(MapClass.BROKEN),
    int(RoadLineType.BROKEN_DOUBLE_YELLOW): int(MapClass.BROKEN),
    int(RoadLineType.SOLID_SINGLE_WHITE): int(MapClass.SOLID_SINGLE),
    int(RoadLineType.SOLID_SINGLE_YELLOW): int(MapClass.SOLID_SINGLE),
    int(RoadLineType.SOLID_DOUBLE_WHITE): int(MapClass.DOUBLE),
    int(RoadLineType.SOLID_DOUBLE_YELLOW): int(MapClass.DOUBLE),
    int(RoadLineType.PASSING_DOUBLE_YELLOW): int(MapClass.DOUBLE),
}
_POLYGON_CLASS = {
    int(MapFeatureType.CROSSWALK): int(MapClass.CROSSWALK),
    int(MapFeatureType.SPEED_BUMP): int(MapClass.SPEED_BUMP),
    int(MapFeatureType.DRIVEWAY): int(MapClass.SPEED_BUMP),
}
VEHICLE_LANE_CLASSES = (
    int(MapClass.FREEWAY),
    int(MapClass.SURFACE_STREET),
    int(MapClass.STOP_SIGN),
)
"""Classes of the lanes a vehicle drives on (docs/model.md §1.6 d, §1.7)."""
LANE_CLASSES = (*VEHICLE_LANE_CLASSES, int(MapClass.BIKE_LANE))
"""Every lane class (pieces that may carry a traffic light)."""


@dataclass(frozen=True)
class MapPieces:
    """Map pieces, K rows of P nodes, unpadded (K is whatever the map yields).

    Attributes:
        pos: [K, P, 3] float64, node (segment start) positions in metres, frame shifted by origin.
        dir: [K, P, 3] float64, segment vectors p_{k+1} - p_k in metres (zeros where invalid).
        valid: [K, P] bool, node validity (a prefix of each row).
        map_class: [K] int64, ``MapClass`` value.
        feature_id: [K] int64, source ``MapFeature.id``.
        feature_index: [K] int64, source row in ``RoadMap``.
        origin: [2] float64, xy subtracted from the file coordinates.
    """

    pos: np.ndarray
    dir: np.ndarray
    valid: np.ndarray
    map_class: np.ndarray
    feature_id: np.ndarray
    feature_index: np.ndarray
    origin: np.ndarray

    @property
    def num_pieces(self) -> int:
        return int(self.map_class.shape[0])

    def take(self, rows: np.ndarray) -> MapPieces:
        """The pieces at ``rows`` ([k] int), in that order."""
        rows = np.asarray(rows, np.int64)
        return MapPieces(
            pos=self.pos[rows],
            dir=self.dir[rows],
            valid=self.valid[rows],
            map_class=self.map_class[rows],
            feature_id=self.feature_id[rows],
            feature_index=self.feature_index[rows],
            origin=self.origin,
        )

    def last_node_pos(self) -> np.ndarray:
        """[K, 3] position of the last valid node of each piece (node 0 if none is valid)."""
        last = np.maximum(self.valid.sum(axis=1) - 1, 0)
        return self.pos[np.arange(self.num_pieces), last]


def feature_classes(road_map: RoadMap) -> np.ndarray:
    """``MapClass`` of every map feature, before splitting.

    Unknown road-line and road-edge types (type 0) get ``NO_CLASS`` and are skipped: the
    reference implementation asserts on them, but real data may contain them (deliberate
    deviation). Stop signs get ``NO_CLASS`` too; instead they overwrite the class of the
    freeway/surface-street lanes they control with ``STOP_SIGN`` (bike lanes keep theirs).

    Args:
        road_map: the scenario's map, F features.

    Returns:
        [F] int64 class per feature, ``NO_CLASS`` for features without pieces.
    """
    classes = np.full(road_map.num_features, NO_CLASS, np.int64)
    tables = {
        int(MapFeatureType.LANE): _LANE_CLASS,
        int(MapFeatureType.ROAD_EDGE): _ROAD_EDGE_CLASS,
        int(MapFeatureType.ROAD_LINE): _ROAD_LINE_CLASS,
    }
    for k, (ftype, sub) in enumerate(zip(road_map.feature_type, road_map.subtype)):
        ftype = int(ftype)
        if ftype in tables:
            classes[k] = tables[ftype].get(int(sub), NO_CLASS)
        elif ftype in _POLYGON_CLASS:
            classes[k] = _POLYGON_CLASS[ftype]
    stop_sign_rows = road_map.indices_of(MapFeatureType.STOP_SIGN)
    if len(stop_sign_rows):
        controlled = np.concatenate([road_map.controlled_lanes[k] for k in stop_sign_rows])
        overwrite = np.isin(road_map.id, controlled) & np.isin(
            classes, (int(MapClass.FREEWAY), int(MapClass.SURFACE_STREET))
        )
        overwrite &= road_map.feature_type == int(MapFeatureType.LANE)
        classes[overwrite] = int(MapClass.STOP_SIGN)
    return classes


def densify_segment(start: np.ndarray, end: np.ndarray) -> np.ndarray:
    """Points from ``start`` to ``end`` at 1 m steps, end point included.

    docs/model.md §1.2 step 3.4.

    Args:
        start: [3] float64 metres.
        end: [3] float64 metres.

    Returns:
        [n, 3] float64: start + k * unit for k = 0..floor(length), then ``end``. When the
        length is an integer the last k-point equals ``end`` and is not repeated (the
        reference would emit a zero-length segment there; deliberate deviation). "An
        integer" allows ``GEOMETRY_TIE_TOLERANCE``: a 14 m side measures 14 + 2e-12 m in one
        world frame and 14 - 2e-12 m in another, and must get the same points in both.
    """
    vec = end - start
    length = float(np.linalg.norm(vec))
    if length == 0.0:
        return np.stack([start, end])
    # == floor(length) + 1 unless the length is (within the tolerance of) an integer
    count = max(1, int(np.ceil(length - GEOMETRY_TIE_TOLERANCE)))
    k = np.arange(count, dtype=np.float64)
    return np.concatenate([start + k[:, None] * (vec / length), end[None]])


def polygon_to_polylines(polygon: np.ndarray) -> tuple[np.ndarray, ...]:
    """A crosswalk/speed-bump/driveway polygon -> its two long sides, each both ways.

    Takes vertices 0, n/4, n/2, 3n/4 (floored); the long sides are v0->v1 and v2->v3 when
    |v1 - v0| > |v2 - v1|, else v0->v3 and v2->v1 (docs/model.md §1.2 step 3). Sides equal within
    ``GEOMETRY_TIE_TOLERANCE`` (a square) count as equal, so the choice does not depend on the
    float rounding of the world frame.

    Args:
        polygon: [n, 3] float64 vertices (n >= 1), metres.

    Returns:
        4 arrays [m_i, 3]: side A, side A reversed, side B, side B reversed.
    """
    n = polygon.shape[0]
    idx = np.floor(np.linspace(0, n, 4, endpoint=False)).astype(np.int64)
    v0, v1, v2, v3 = polygon[idx]
    if np.linalg.norm(v1 - v0) > np.linalg.norm(v2 - v1) + GEOMETRY_TIE_TOLERANCE:
        side_a, side_b = densify_segment(v0, v1), densify_segment(v2, v3)
    else:
        side_a, side_b = densify_segment(v0, v3), densify_segment(v2, v1)
    return side_a, side_a[::-1], side_b, side_b[::-1]


def piece_starts(num_segments: int, piece_segments: int) -> np.ndarray:
    """Start segment of every piece of a polyline with S segments (docs/model.md §1.2 step 4).

    Args:
        num_segments: S = N - 1 >= 1.
        piece_segments: maximum segments per piece (20).

    Returns:
        [P] int64, P = S // piece_segments + 1, int(linspace(0, S, P, endpoint=False)).
    """
    count = num_segments // piece_segments + 1
    return np.linspace(0, num_segments, count, endpoint=False).astype(np.int64)


def split_polylines(
    polylines: list[np.ndarray], piece_segments: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Cut polylines into pieces of <= ``piece_segments`` segments (batched gather).

    Args:
        polylines: Q arrays [n_q, 3] float64 with n_q >= 2.
        piece_segments: P, maximum segments per piece.

    Returns:
        pos: [K, P, 3] segment start points; dir: [K, P, 3] segment vectors (0 where invalid);
        valid: [K, P] bool; source: [K] int64 index of the polyline of each piece.
    """
    if not polylines:
        empty = np.zeros((0, piece_segments, 3), np.float64)
        return empty, empty.copy(), np.zeros((0, piece_segments), bool), np.zeros(0, np.int64)
    lengths = np.array([p.shape[0] for p in polylines], np.int64)
    offsets = np.concatenate([[0], np.cumsum(lengths)[:-1]])
    points = np.concatenate(polylines)
    starts, ends, source = [], [], []
    for q, n in enumerate(lengths):
        s = piece_starts(int(n) - 1, piece_segments)
        starts.append(s + offsets[q])
        ends.append(np.append(s[1:], n - 1) + offsets[q])
        source.append(np.full(s.shape[0], q, np.int64))
    start = np.concatenate(starts)
    end = np.concatenate(ends)
    node = start[:, None] + np.arange(piece_segments)[None, :]
    valid = node < end[:, None]
    node = np.where(valid, node, start[:, None])
    pos = np.where(valid[..., None], points[node], 0.0)
    nxt = np.minimum(node + 1, points.shape[0] - 1)
    direction = np.where(valid[..., None], points[nxt] - points[node], 0.0)
    return pos, direction, valid, np.concatenate(source)


def build_map_pieces(road_map: RoadMap, origin: np.ndarray, cfg: TokenConfig) -> MapPieces:
    """All map pieces of a scenario, in feature order with the pieces of a feature consecutive.

    Lanes, road lines and road edges are resampled (every ``cfg.resample_stride``-th point);
    polygons become 4 densified polylines. Polylines with fewer than 2 points after resampling
    have no segment and yield no piece (the reference would emit an empty piece that the
    short-piece filter drops anyway).

    Args:
        road_map: F map features, file coordinates.
        origin: [2] float64 xy subtracted from every point (metres).
        cfg: piece size and resampling stride.

    Returns:
        The unfiltered, unpadded pieces.
    """
    origin = np.asarray(origin, np.float64)
    shift = np.array([origin[0], origin[1], 0.0])
    classes = feature_classes(road_map)
    unknown = (classes == NO_CLASS) & (road_map.feature_type != int(MapFeatureType.STOP_SIGN))
    if unknown.any():
        _LOG.debug(
            "skipped %d map features of unknown type: ids %s", unknown.sum(), road_map.id[unknown]
        )
    polylines: list[np.ndarray] = []
    owner: list[int] = []
    for k in np.flatnonzero(classes != NO_CLASS):
        points = np.asarray(road_map.polylines[k], np.float64) - shift
        if int(road_map.feature_type[k]) in _POLYGON_CLASS:
            parts: tuple[np.ndarray, ...] = polygon_to_polylines(points)
        else:
            parts = (points[:: cfg.resample_stride],)
        for part in parts:
            if part.shape[0] >= 2:
                polylines.append(part)
                owner.append(int(k))
    pos, direction, valid, source = split_polylines(polylines, cfg.piece_segments)
    feature_index = np.asarray(owner, np.int64)[source]
    return MapPieces(
        pos=pos,
        dir=direction,
        valid=valid,
        map_class=classes[feature_index],
        feature_id=road_map.id.astype(np.int64)[feature_index],
        feature_index=feature_index,
        origin=origin,
    )
