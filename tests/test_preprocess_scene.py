"""Agent selection, destinations and the full ``preprocess_scenario`` on synthetic scenes."""

from __future__ import annotations

import numpy as np
import pytest

from tbsim_env.core.config import TokenConfig
from tbsim_env.core.constants import NUM_STEPS, MapClass, MapFeatureType, ObjectType, SignalState
from tbsim_env.data.preprocess import (
    Goals,
    build_map_pieces,
    destination_labels,
    filter_map_pieces,
    preprocess_scenario,
    select_agents,
)
from tbsim_env.data.preprocess.destination import walk_lane_graph
from tbsim_env.data.scenario import TrafficSignals
from tests.test_preprocess_support import (
    Agent,
    Feature,
    assert_tokens_equivariant,
    line,
    make_road_map,
    make_scenario,
)

LANE, EDGE = MapFeatureType.LANE, MapFeatureType.ROAD_EDGE
VEH, PED, CYC = ObjectType.VEHICLE, ObjectType.PEDESTRIAN, ObjectType.CYCLIST


def _valid_from(step: int) -> np.ndarray:
    v = np.zeros(NUM_STEPS, bool)
    v[step:] = True
    return v


def _street_map():
    return make_road_map(
        [
            Feature(1, LANE, line((-100, 0), (100, 0)), subtype=2),
            Feature(2, EDGE, line((-100, 10), (100, 10)), subtype=1),
        ]
    )


def _crowd_scenario(objects_of_interest=()):
    agents = [
        Agent((0, 0), 0.0, 5.0),  # 0 SDC
        Agent((10, 0), 0.0, 5.0),  # 1 track to predict
        Agent((5, 3), 0.0, 3.0, ObjectType.OTHER),  # 2 TYPE_OTHER, not relevant
        Agent((20, 0), 0.0, 5.0, valid=_valid_from(20)),  # 3 never valid in history (a)
        Agent((0, 300), 0.0, 0.0, PED),  # 4 still, far from map and agents (c)
        Agent((30, 15), 0.0, 0.0),  # 5 parked: near the edge, no lane within 3 m (d)
        Agent((50, 0.5), 0.0, 0.0),  # 6 still on an aligned lane: kept
        Agent((60, 0.5), np.pi, 0.0),  # 7 still, facing against the lane: parked (d)
        Agent((-20, 0), 0.0, 5.0),  # 8 moving
        Agent((-60, 0), 0.0, 5.0),  # 9 moving
        Agent((-150, 0), 0.0, 5.0),  # 10 moving, far: pruned first (f, index order)
        Agent((-300, 0), 0.0, 5.0),  # 11 moving, farther
        Agent((0, 500), 0.0, 0.0, PED),  # 12 still and far, object of interest if asked
    ]
    return make_scenario(
        agents,
        _street_map(),
        sdc=0,
        tracks_to_predict=(1,),
        objects_of_interest=objects_of_interest,
    )


def _kept_pieces(scenario, cfg):
    pieces = build_map_pieces(scenario.road_map, np.zeros(2), cfg)
    ref = scenario.tracks.xyz[scenario.role_mask().any(1)][:, :11].reshape(-1, 3)
    return pieces.take(filter_map_pieces(pieces, ref, cfg))


def test_select_agents_filters_a_to_f():
    sc = _crowd_scenario()
    cfg = TokenConfig(max_agents=6)
    got = select_agents(sc, cfg, _kept_pieces(sc, cfg))
    # a drops 3; OTHER drops 2; c drops 4 and 12; d drops 5 and 7; f drops 10 (index order).
    np.testing.assert_array_equal(got, [0, 1, 6, 8, 9, 11])


def test_select_agents_without_limit_pressure_keeps_all_valid():
    sc = _crowd_scenario()
    cfg = TokenConfig(max_agents=64)
    got = select_agents(sc, cfg, _kept_pieces(sc, cfg))
    np.testing.assert_array_equal(got, [0, 1, 4, 5, 6, 7, 8, 9, 10, 11, 12])


def test_select_agents_never_drops_relevant_and_puts_sdc_first():
    sc = _crowd_scenario(objects_of_interest=(112,))  # track 12
    sc = sc.replace(sdc_index=9, tracks_to_predict=np.array([1, 4]))
    cfg = TokenConfig(max_agents=5)
    got = select_agents(sc, cfg, _kept_pieces(sc, cfg))
    assert got[0] == 9 and len(got) == 5
    assert {1, 4, 12} <= set(got.tolist())
    assert (np.diff(got[1:]) > 0).all()


def test_select_agents_raises_when_relevant_exceed_limit():
    sc = _crowd_scenario(objects_of_interest=(112,))
    with pytest.raises(ValueError, match=r"'synthetic'.*3 relevant agents.*max_agents=2"):
        select_agents(sc, TokenConfig(max_agents=2))


def test_select_agents_relevant_other_type_is_kept():
    sc = _crowd_scenario().replace(tracks_to_predict=np.array([1, 2]))
    got = select_agents(sc, TokenConfig(), _kept_pieces(sc, TokenConfig()))
    assert 2 in got.tolist()


def test_select_agents_without_map_keeps_first_valid():
    sc = _crowd_scenario().replace(tracks_to_predict=np.array([11]))
    got = select_agents(sc, TokenConfig(max_agents=4))
    np.testing.assert_array_equal(got, [0, 1, 4, 11])  # 2 (OTHER) and 3 (a) skipped


def test_select_agents_training_filters_b_and_e():
    short = np.zeros(NUM_STEPS, bool)
    short[:15] = True  # 15 valid steps < 20
    agents = [
        Agent((0, 0), 0.0, 5.0),
        Agent((10, 0), 0.0, 5.0, valid=short),  # b
        Agent((20, 0), 0.0, 5.0),  # moving, heading glitch below (e)
        Agent((30, 0), 0.0, 5.0),
        Agent((40, 0), 0.0, 5.0),
    ]
    sc = make_scenario(agents, _street_map())
    heading = sc.tracks.heading.copy()
    heading[2, 40] = 2.0  # a 2 rad jump
    sc = sc.replace(tracks=sc.tracks.__class__(**{**sc.tracks.__dict__, "heading": heading}))
    train = TokenConfig(max_agents=3, training=True)
    got = select_agents(sc, train, _kept_pieces(sc, train))
    np.testing.assert_array_equal(got, [0, 3, 4])
    # Validation keeps the short track (b is training only) and prunes by distance instead.
    val = TokenConfig(max_agents=3)
    got = select_agents(sc, val, _kept_pieces(sc, val))
    np.testing.assert_array_equal(got, [0, 1, 2])


# ----------------------------------------------------------------------------- destinations


def _chain_map(branch_at: int | None = None, dead_end: bool = False):
    """Lanes 1..5 along +x, 20 m each; lane k exits to k+1 (and 10+k when branching)."""
    feats = []
    for k in range(1, 6):
        exits = (k + 1,) if k < 5 else ()
        if branch_at == k:
            exits = (k + 1, 10 + k)
        if dead_end and k == 1:
            exits = (999,)
        feats.append(Feature(k, LANE, line((20 * (k - 1), 0), (20 * k, 0)), 2, exits))
    if branch_at is not None:
        k = branch_at
        feats.append(Feature(10 + k, LANE, line((20 * k, 0), (20 * k + 20, 15)), 2))
    feats.append(Feature(50, EDGE, line((0, 10), (100, 10)), subtype=1))
    feats.append(Feature(60, LANE, line((0, -5), (100, -5)), subtype=3))  # bike lane
    return make_road_map(feats)


def _dest(road_map, kinds, pos, yaw, speed, valid=None, seed=0):
    pieces = build_map_pieces(road_map, np.zeros(2), TokenConfig())
    n = len(kinds)
    goals = Goals(
        pos=np.array(pos, float),
        yaw=np.array(yaw, float),
        speed=np.array(speed, float),
        valid=np.ones(n, bool) if valid is None else np.array(valid),
    )
    kinds = np.array([int(k) for k in kinds])
    return pieces, destination_labels(kinds, goals, pieces, road_map, np.random.default_rng(seed))


def _last_piece(pieces, lane_id):
    return int(np.flatnonzero(pieces.feature_id == lane_id)[-1])


def test_vehicle_destination_walks_four_hops():
    pieces, dest = _dest(_chain_map(), [VEH], [(5, 0.5)], [0.0], [5.0])
    assert dest[0] == _last_piece(pieces, 4)  # start lane 1, then 2, 3, 4


def test_vehicle_destination_stops_at_branch_after_two_hops():
    for seed in range(5):
        pieces, dest = _dest(_chain_map(branch_at=2), [VEH], [(5, 0.5)], [0.0], [5.0], seed=seed)
        assert dest[0] == _last_piece(pieces, 2)


def test_vehicle_destination_dead_end_and_wrong_way():
    pieces, dest = _dest(_chain_map(dead_end=True), [VEH], [(5, 0.5)], [0.0], [5.0])
    assert dest[0] == _last_piece(pieces, 1)
    # Facing against every lane: the boundary node nearest to goal + 5 s * v * heading.
    pieces, dest = _dest(_chain_map(), [VEH], [(50, 0.5)], [np.pi], [2.0])
    assert pieces.map_class[dest[0]] == MapClass.ROAD_EDGE_BOUNDARY
    node_x = pieces.pos[dest[0]][pieces.valid[dest[0]], 0]
    assert node_x.min() <= 40.0 <= node_x.max() + 1.0


def test_pedestrian_cyclist_and_invalid_destinations():
    pieces, dest = _dest(
        _chain_map(),
        [PED, CYC, CYC, VEH],
        [(70, 5), (30, -4), (30, 4), (10, 0)],
        [np.pi / 2, 0.0, np.pi / 2, 0.0],
        [1.0, 0.1, 1.0, 1.0],
        valid=[True, True, True, False],
    )
    assert pieces.map_class[dest[0]] == MapClass.ROAD_EDGE_BOUNDARY
    assert pieces.pos[dest[0]][pieces.valid[dest[0]], 0].min() <= 70.0
    assert pieces.map_class[dest[1]] == MapClass.BIKE_LANE  # bike lane within 3 m, aligned
    assert pieces.map_class[dest[2]] == MapClass.ROAD_EDGE_BOUNDARY  # extended goal (30, 9)
    assert dest[3] == -1


def test_destinations_without_bike_lanes_or_boundaries():
    rm = make_road_map([Feature(1, LANE, line((0, 0), (20, 0)), subtype=2)])
    pieces, dest = _dest(rm, [CYC, PED, VEH], [(5, 0)] * 3, [0.0] * 3, [1.0] * 3)
    assert dest[0] == -1 and dest[1] == -1  # no bike lane and no boundary: no destination
    assert dest[2] == _last_piece(pieces, 1)
    rm = make_road_map([Feature(2, EDGE, line((0, 5), (20, 5)), subtype=1)])
    pieces, dest = _dest(rm, [CYC], [(5, 0)], [0.0], [1.0])
    assert pieces.map_class[dest[0]] == MapClass.ROAD_EDGE_BOUNDARY


def test_walk_lane_graph_is_driven_by_rng():
    exits = {1: np.array([2, 3]), 2: np.array([4]), 3: np.array([5])}
    last_piece = {1: 0, 2: 1, 3: 2, 4: 3, 5: 4}
    seen = {walk_lane_graph(1, exits, last_piece, np.random.default_rng(s)) for s in range(20)}
    assert seen == {4, 5}  # 1 -> 2|3 -> 4|5 (dead ends after), never stops at 1


# ----------------------------------------------------------------------------- full scene


def _full_scene():
    sc = _crowd_scenario(objects_of_interest=(108,))
    valid = np.ones((2, NUM_STEPS), bool)
    valid[1, 60:] = False
    signals = TrafficSignals(
        lane_id=np.array([1, 77], np.int64),
        state=np.where(valid, int(SignalState.STOP), 0).astype(np.int8),
        valid=valid,
        stop_point=np.zeros((2, 3)),
    )
    rm = sc.road_map
    crosswalk = np.array([[5, -3, 0], [15.3, -3, 0], [15.3, 3, 0], [5, 3, 0]], float)
    extra = make_road_map([Feature(90, MapFeatureType.CROSSWALK, crosswalk)])
    rm = rm.__class__(
        **{
            name: (
                np.concatenate([getattr(rm, name), getattr(extra, name)])
                if isinstance(getattr(rm, name), np.ndarray)
                else getattr(rm, name) + getattr(extra, name)
            )
            for name in rm.__dataclass_fields__
        }
    )
    return sc.replace(road_map=rm, signals=signals).validate()


def test_preprocess_scenario_shapes_and_padding():
    cfg = TokenConfig(max_map_pieces=40, max_traffic_lights=16, max_agents=12)
    sc = _full_scene()
    tok = preprocess_scenario(sc, cfg)
    m, p, n, tl, t = 40, 20, 12, 16, NUM_STEPS
    shapes = {
        "map_pos": ((m, p, 3), np.float32),
        "map_dir": ((m, p, 3), np.float32),
        "map_valid": ((m, p), np.bool_),
        "map_class": ((m,), np.int64),
        "map_feature_id": ((m,), np.int64),
        "map_boundary": ((4,), np.float32),
        "tl_piece": ((tl,), np.int64),
        "tl_state": ((tl, t), np.int64),
        "tl_valid": ((tl, t), np.bool_),
        "agent_track_index": ((n,), np.int64),
        "agent_valid": ((n, t), np.bool_),
        "agent_pos": ((n, t, 3), np.float32),
        "agent_vel": ((n, t, 2), np.float32),
        "agent_speed": ((n, t), np.float32),
        "agent_accel": ((n, t), np.float32),
        "agent_yaw": ((n, t), np.float32),
        "agent_yaw_rate": ((n, t), np.float32),
        "agent_type": ((n,), np.int64),
        "agent_size": ((n, 3), np.float32),
        "agent_role": ((n, 3), np.bool_),
        "agent_dest": ((n,), np.int64),
    }
    for name, (shape, dtype) in shapes.items():
        arr = getattr(tok, name)
        assert arr.shape == shape and arr.dtype == dtype, name
    np.testing.assert_allclose(tok.origin, sc.tracks.xyz[0, 10, :2])
    np.testing.assert_allclose(tok.agent_pos[0, 10, :2], 0.0, atol=1e-6)
    # Padding rows.
    pad_map = tok.map_class < 0
    assert pad_map.any() and not tok.map_valid[pad_map].any()
    assert (tok.map_feature_id[pad_map] == -1).all()
    pad_ag = tok.agent_track_index < 0
    assert not tok.agent_valid[pad_ag].any() and (tok.agent_dest[pad_ag] == -1).all()
    np.testing.assert_array_equal(
        tok.agent_track_index[~pad_ag], [0, 1, 4, 5, 6, 7, 8, 9, 10, 11, 12]
    )
    np.testing.assert_array_equal(tok.agent_role[:3], [[1, 0, 0], [0, 0, 1], [0, 0, 0]])
    # Object of interest: track id 108 is row 8 (the 7th selected agent).
    assert tok.agent_role[list(tok.agent_track_index).index(8), 1]
    # TL tokens: lane 1 only (lane 77 does not exist), state STOP where valid.
    live = tok.tl_piece >= 0
    assert live.sum() == 11  # lane 1: 200 m -> 200 segments -> 200 // 20 + 1 = 11 pieces
    assert (tok.map_feature_id[tok.tl_piece[live]] == 1).all()
    assert (tok.tl_state[live] == 1).all() and tok.tl_valid[live].all()
    # Crosswalk: 4 polylines, 10.3 m long sides (one piece each).
    assert (tok.map_class == MapClass.CROSSWALK).sum() == 4
    # Boundary covers the valid nodes.
    nodes = tok.map_pos[tok.map_valid]
    np.testing.assert_allclose(
        tok.map_boundary,
        [nodes[:, 0].min(), nodes[:, 0].max(), nodes[:, 1].min(), nodes[:, 1].max()],
    )
    # Destinations point at valid pieces.
    live_ag = tok.agent_dest >= 0
    assert live_ag.sum() >= 8 and (tok.map_class[tok.agent_dest[live_ag]] >= 0).all()


def test_preprocess_scenario_is_deterministic():
    sc = _full_scene()
    a, b = preprocess_scenario(sc), preprocess_scenario(sc)
    for name in a.__dataclass_fields__:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)


@pytest.mark.parametrize(("theta", "shift"), [(0.7, (1234.5, -987.25)), (-2.9, (-5e3, 3e3))])
def test_preprocess_scenario_is_equivariant(theta, shift):
    sc = _full_scene()
    cfg = TokenConfig(max_map_pieces=30, max_agents=8)
    a = preprocess_scenario(sc, cfg)
    b = preprocess_scenario(sc.transformed(theta, shift), cfg)
    assert_tokens_equivariant(a, b, theta)


def test_preprocess_scenario_without_map():
    sc = _crowd_scenario().replace(road_map=make_road_map([]))
    tok = preprocess_scenario(sc, TokenConfig(max_agents=5))
    assert not tok.map_valid.any() and (tok.map_class == -1).all()
    assert (tok.tl_piece == -1).all() and (tok.agent_dest == -1).all()
    np.testing.assert_array_equal(tok.agent_track_index, [0, 1, 4, 5, 6])
    hist = tok.agent_pos[:, :11][tok.agent_valid[:, :11]]
    np.testing.assert_allclose(
        tok.map_boundary,
        [hist[:, 0].min(), hist[:, 0].max(), hist[:, 1].min(), hist[:, 1].max()],
    )
    assert tok.map_boundary[3] == pytest.approx(300.0)  # the still pedestrian at y = 300


@pytest.mark.parametrize("layout", ["intersection", "merge"])
def test_generated_scenes_preprocess(layout):
    generator = pytest.importorskip("tbsim_env.data.generator")
    sc = generator.generate_scenario(layout, 0)
    tok = preprocess_scenario(sc)
    live = tok.agent_track_index >= 0
    assert tok.agent_track_index[0] == sc.sdc_index and live.sum() >= 2
    assert (tok.map_class >= 0).sum() > 20 and (tok.agent_dest[live] >= 0).all()
    assert (tok.map_class[tok.agent_dest[live]] >= 0).all()
    assert (tok.map_feature_id[tok.tl_piece[tok.tl_piece >= 0]] >= 0).all()
    np.testing.assert_array_equal(tok.tl_valid[tok.tl_piece < 0], False)
