"""Map pieces, map filtering and traffic-light tokens on synthetic maps.

docs/model.md §1.2, §1.3, §1.6.
"""

from __future__ import annotations

import numpy as np
import pytest

from tbsim_env.core.config import TokenConfig
from tbsim_env.core.constants import NUM_STEPS, MapClass, MapFeatureType, SignalState, TLState
from tbsim_env.data.preprocess import (
    attach_traffic_lights,
    build_map_pieces,
    feature_classes,
    filter_map_pieces,
    map_signal_states,
)
from tbsim_env.data.preprocess.map_filter import min_distance, prune_by_distance
from tbsim_env.data.preprocess.map_pieces import (
    piece_starts,
    polygon_to_polylines,
    split_polylines,
)
from tbsim_env.data.scenario import TrafficSignals
from tests.test_preprocess_support import Feature, line, make_road_map

LANE, LINE, EDGE = MapFeatureType.LANE, MapFeatureType.ROAD_LINE, MapFeatureType.ROAD_EDGE
CFG = TokenConfig()


def test_feature_classes_cover_all_types_and_stop_sign_overwrite():
    pts = line((0, 0), (10, 0))
    feats = [
        Feature(1, LANE, pts, subtype=0),
        Feature(2, LANE, pts, subtype=1),
        Feature(3, LANE, pts, subtype=2),
        Feature(4, LANE, pts, subtype=3),
        Feature(5, LANE, pts, subtype=2),
        *[Feature(10 + k, LINE, pts, subtype=k) for k in range(9)],
        *[Feature(20 + k, EDGE, pts, subtype=k) for k in range(3)],
        Feature(30, MapFeatureType.STOP_SIGN, pts[:1], controlled=(2, 4, 5)),
        Feature(31, MapFeatureType.CROSSWALK, pts[:4]),
        Feature(32, MapFeatureType.SPEED_BUMP, pts[:4]),
        Feature(33, MapFeatureType.DRIVEWAY, pts[:4]),
    ]
    got = feature_classes(make_road_map(feats))
    c = MapClass
    expected = [
        c.SURFACE_STREET, c.STOP_SIGN, c.SURFACE_STREET, c.BIKE_LANE, c.STOP_SIGN,  # lanes
        -1, c.BROKEN, c.SOLID_SINGLE, c.DOUBLE, c.BROKEN, c.BROKEN, c.SOLID_SINGLE,  # lines
        c.DOUBLE, c.DOUBLE,
        -1, c.ROAD_EDGE_BOUNDARY, c.ROAD_EDGE_MEDIAN,  # edges (type 0 skipped)
        -1, c.CROSSWALK, c.SPEED_BUMP, c.SPEED_BUMP,
    ]  # fmt: skip
    np.testing.assert_array_equal(got, [int(x) for x in expected])
    # Unknown road-line/edge types are skipped without error; stop signs yield no piece.
    pieces = build_map_pieces(make_road_map(feats), np.zeros(2), CFG)
    assert not np.isin(pieces.feature_id, [10, 20, 30]).any()
    assert set(pieces.feature_id.tolist()) == {f.id for f in feats} - {10, 20, 30}


def test_polygon_long_sides_both_ways():
    # 10 m x 3 m rectangle with 8 vertices (corners at indices 0, 2, 4, 6).
    corners = np.array([[0, 0], [5, 0], [10, 0], [10, 1.5], [10, 3], [5, 3], [0, 3], [0, 1.5]])
    poly = np.c_[corners, np.zeros(8)].astype(float)
    parts = polygon_to_polylines(poly)
    assert len(parts) == 4
    np.testing.assert_allclose(parts[0][0], [0, 0, 0])
    np.testing.assert_allclose(parts[0][-1], [10, 0, 0])
    np.testing.assert_allclose(parts[2][0], [10, 3, 0])
    np.testing.assert_allclose(parts[2][-1], [0, 3, 0])
    np.testing.assert_allclose(parts[1], parts[0][::-1])
    np.testing.assert_allclose(parts[3], parts[2][::-1])
    # 1 m steps plus the end point: 0, 1, ..., 10 (the end point is not repeated).
    assert parts[0].shape == (11, 3)
    np.testing.assert_allclose(np.diff(parts[0][:-1, 0]), 1.0)


def test_polygon_short_first_side_uses_other_pair():
    corners = np.array([[0, 0], [0, 3], [10, 3], [10, 0]], float)  # v0->v1 is the short side
    parts = polygon_to_polylines(np.c_[corners, np.zeros(4)])
    np.testing.assert_allclose(parts[0][[0, -1], :2], [[0, 0], [10, 0]])  # v0 -> v3
    np.testing.assert_allclose(parts[2][[0, -1], :2], [[10, 3], [0, 3]])  # v2 -> v1
    assert parts[0].shape[0] == 11
    side = polygon_to_polylines(np.c_[corners * [1.0, 1.0], np.zeros(4)] * [1.05, 1.0, 1.0])[0]
    np.testing.assert_allclose(side[:, 0], [*range(11), 10.5])  # 10.5 m: 0..10, then the end


def test_polygon_points_do_not_depend_on_the_rounding_of_the_frame():
    # A 14 m x 14 m square crosswalk: integer and equal side lengths, which a rotated and
    # shifted frame measures a rounding error above or below. Same sides, same point counts.
    corners = np.array([[0, 0], [14, 0], [14, 14], [0, 14]], float)
    ref = polygon_to_polylines(np.c_[corners, np.zeros(4)])
    for yaw, shift in [(1.1, (3000.0, -1500.0)), (-2.3, (-4000.0, 700.0)), (0.3, (1e4, 1e4))]:
        c, s = np.cos(yaw), np.sin(yaw)
        moved = corners @ np.array([[c, -s], [s, c]]).T + shift
        parts = polygon_to_polylines(np.c_[moved, np.zeros(4)])
        for a, b in zip(ref, parts, strict=True):
            assert a.shape == b.shape == (15, 3)
            back = (b[:, :2] - shift) @ np.array([[c, -s], [s, c]])
            np.testing.assert_allclose(back, a[:, :2], atol=1e-9)
    # A side a hair longer than an integer still ends on the end point, no extra point.
    near = polygon_to_polylines(np.array([[0, 0, 0], [10 + 1e-9, 0, 0], [10, 3, 0], [0, 3, 0]]))
    assert near[0].shape == (11, 3)


@pytest.mark.parametrize(
    ("segments", "starts"),
    [(1, [0]), (19, [0]), (20, [0, 10]), (45, [0, 15, 30]), (60, [0, 15, 30, 45])],
)
def test_piece_starts(segments, starts):
    np.testing.assert_array_equal(piece_starts(segments, 20), starts)


def test_split_polylines_reconstructs_points():
    rng = np.random.default_rng(0)
    polys = [np.cumsum(rng.normal(size=(n, 3)), axis=0) for n in (2, 21, 22, 46, 100)]
    pos, direction, valid, source = split_polylines(polys, 20)
    assert valid.sum(axis=1).max() <= 20
    for q, poly in enumerate(polys):
        rows = np.flatnonzero(source == q)
        nodes = np.concatenate([pos[r][valid[r]] for r in rows])
        np.testing.assert_allclose(nodes, poly[:-1])
        dirs = np.concatenate([direction[r][valid[r]] for r in rows])
        np.testing.assert_allclose(dirs, np.diff(poly, axis=0))
    assert (direction[~valid] == 0).all() and (pos[~valid] == 0).all()


def test_build_map_pieces_resamples_shifts_and_tags():
    lane = line((100, 50), (140, 50))  # 81 points, 0.5 m apart -> 41 points -> 40 segments
    rm = make_road_map(
        [Feature(7, LANE, lane, subtype=2), Feature(8, MapFeatureType.STOP_SIGN, lane[:1])]
    )
    pieces = build_map_pieces(rm, np.array([100.0, 50.0]), CFG)
    assert pieces.num_pieces == 3  # S = 40 -> 3 pieces of 13, 13, 14 segments
    np.testing.assert_array_equal(pieces.valid.sum(axis=1), [13, 13, 14])
    np.testing.assert_array_equal(pieces.feature_id, [7, 7, 7])
    np.testing.assert_allclose(pieces.pos[0, 0], [0, 0, 0])
    d = np.linalg.norm(pieces.dir[pieces.valid], axis=1)
    np.testing.assert_allclose(d, 1.0)
    assert pieces.map_class.tolist() == [int(MapClass.SURFACE_STREET)] * 3


def test_empty_map_gives_no_pieces():
    pieces = build_map_pieces(make_road_map([]), np.zeros(2), CFG)
    assert pieces.pos.shape == (0, 20, 3) and pieces.num_pieces == 0
    assert filter_map_pieces(pieces, np.zeros((3, 3)), CFG).shape == (0,)


def _grid_map(n: int, spacing: float, length: float = 10.0):
    feats = [
        Feature(k, LANE, line((k * spacing, 0), (k * spacing, length)), subtype=2) for k in range(n)
    ]
    return make_road_map(feats)


def test_box_filter_and_guard():
    # 12 lanes near the agents, 3 lanes 2 km away: the far ones are cut by the box filter.
    near = [Feature(k, LANE, line((k * 5, 0), (k * 5, 10)), subtype=2) for k in range(12)]
    far = [Feature(50 + k, LANE, line((2000 + k, 0), (2000 + k, 10)), subtype=2) for k in range(3)]
    pieces = build_map_pieces(make_road_map(near + far), np.zeros(2), CFG)
    ref = np.array([[0.0, 0.0, 0.0], [10.0, 5.0, 0.0]])
    kept = filter_map_pieces(pieces, ref, CFG)
    assert set(pieces.feature_id[kept]) == set(range(12))
    # Guard: with only 3 near lanes (< 10 survivors) the box filter is undone.
    pieces = build_map_pieces(make_road_map(near[:3] + far), np.zeros(2), CFG)
    kept = filter_map_pieces(pieces, ref, CFG)
    assert set(pieces.feature_id[kept]) == {0, 1, 2, 50, 51, 52}


def test_short_pieces_are_dropped():
    rm = make_road_map(
        [
            Feature(1, LANE, line((0, 0), (0, 1.5)), subtype=2),  # 4 pts -> 2 -> 1 segment
            Feature(2, LANE, line((5, 0), (5, 3.0)), subtype=2),  # 7 pts -> 4 -> 3 segments
            Feature(3, LANE, line((9, 0), (9, 4.0)), subtype=2),  # 9 pts -> 5 -> 4 segments
        ]
    )
    pieces = build_map_pieces(rm, np.zeros(2), CFG)
    kept = filter_map_pieces(pieces, np.zeros((1, 3)), CFG)
    assert pieces.feature_id[kept].tolist() == [3]


def test_distance_pruning_keeps_nearest_in_order():
    rm = _grid_map(40, spacing=20.0)  # lanes at x = 0, 20, ..., 780
    pieces = build_map_pieces(rm, np.zeros(2), CFG)
    cfg = TokenConfig(max_map_pieces=7)
    ref = np.array([[400.0, 5.0, 0.0]])
    kept = filter_map_pieces(pieces, ref, cfg)
    assert kept.shape == (7,) and (np.diff(kept) > 0).all()
    # Kept are exactly the 7 lanes with the smallest distance (x = 340..460).
    np.testing.assert_array_equal(pieces.feature_id[kept], np.arange(17, 24))


def test_prune_by_distance_walks_in_index_order():
    dist = np.array([300.0, 600.0, 700.0, 100.0, 550.0, 10.0])
    keep = np.ones(6, bool)
    out = prune_by_distance(dist, keep, np.zeros(6, bool), 4, 500.0)
    # The first pass (r = 500) may drop rows 1, 2, 4; it stops after 2 drops (rows 1 and 2).
    np.testing.assert_array_equal(out, [True, False, False, True, True, True])
    out = prune_by_distance(dist, keep, np.array([0, 1, 1, 0, 0, 0], bool), 3, 500.0)
    # Rows 1, 2 protected; r = 500 drops 4; r = 250 drops 0; r = 125 -> nothing; r = 62.5 -> 3.
    np.testing.assert_array_equal(out, [False, True, True, False, False, True])


def test_prune_terminates_on_exact_ties():
    out = prune_by_distance(np.zeros(5), np.ones(5, bool), np.zeros(5, bool), 2, 500.0)
    assert out.sum() == 2


def test_min_distance_matches_brute_force():
    rng = np.random.default_rng(1)
    pts, tgt = rng.normal(size=(7, 5, 3)) * 100, rng.normal(size=(9, 3)) * 100
    brute = np.linalg.norm(pts[..., None, :] - tgt, axis=-1).min(-1)
    np.testing.assert_allclose(min_distance(pts, tgt, chunk=20), brute, rtol=1e-9)
    assert np.isinf(min_distance(pts, np.zeros((0, 3)))).all()


def test_map_signal_states_all_raw_values():
    raw = np.arange(9)
    got = map_signal_states(raw, np.ones(9, bool))
    expect = [0, 1, 2, 3, 1, 2, 3, 4, 4]
    np.testing.assert_array_equal(got, expect)
    assert got[SignalState.FLASHING_CAUTION] == TLState.FLASHING
    np.testing.assert_array_equal(map_signal_states(raw, np.zeros(9, bool)), 0)
    np.testing.assert_array_equal(map_signal_states(np.array([9, -1]), np.ones(2, bool)), 0)


def _signals(lane_ids, raw_state: int) -> TrafficSignals:
    s = len(lane_ids)
    valid = np.zeros((s, NUM_STEPS), bool)
    valid[:, :50] = True
    return TrafficSignals(
        lane_id=np.array(lane_ids, np.int64),
        state=np.where(valid, raw_state, 0).astype(np.int8),
        valid=valid,
        stop_point=np.zeros((s, 3)),
    )


def test_traffic_lights_one_token_per_kept_piece():
    rm = make_road_map(
        [
            Feature(1, LANE, line((0, 0), (0, 60)), subtype=2),  # 60 segments -> 4 pieces
            Feature(2, LANE, line((5, 0), (5, 10)), subtype=2),
            Feature(3, LINE, line((9, 0), (9, 10)), subtype=1),
        ]
    )
    pieces = build_map_pieces(rm, np.zeros(2), CFG)
    kept = pieces.take(filter_map_pieces(pieces, np.zeros((1, 3)), CFG))
    signals = _signals([1, 2, 99], int(SignalState.ARROW_GO))
    tl = attach_traffic_lights(signals, kept, np.zeros((1, 3)), CFG)
    assert tl.num_tokens == 5
    np.testing.assert_array_equal(kept.feature_id[tl.piece], [1, 1, 1, 1, 2])
    np.testing.assert_array_equal(tl.signal, [0, 0, 0, 0, 1])
    assert (tl.state[:, :50] == TLState.GO).all() and (tl.state[:, 50:] == 0).all()
    np.testing.assert_array_equal(tl.valid, signals.valid[tl.signal])
    # Over the limit: the tokens nearest the reference are kept, in order.
    ref = np.array([[0.0, 60.0, 0.0]])
    tl = attach_traffic_lights(signals, kept, ref, TokenConfig(max_traffic_lights=2))
    np.testing.assert_array_equal(tl.piece, [2, 3])
