"""Tests of the embedded procedural scenario generator (tbsim_env.data.generator)."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from tbsim_env.core.constants import (
    CURRENT_INDEX,
    DT,
    NUM_STEPS,
    LaneType,
    MapFeatureType,
    ObjectType,
    RoadEdgeType,
    RoadLineType,
    SignalState,
)
from tbsim_env.data.generator import LAYOUTS, default_scenarios, generate_scenario
from tbsim_env.data.generator.roads import build_intersection, signal_states
from tbsim_env.data.generator.scenes import SDC_MIN_TRAVEL_M
from tbsim_env.data.scenario import Scenario, wrap_angle_np

SEEDS = (0, 1, 2)
CASES = [(layout, seed) for layout in ("intersection", "merge") for seed in SEEDS]


@functools.cache
def scene(layout: str, seed: int) -> Scenario:
    return generate_scenario(layout, seed)


def vehicles(sc: Scenario) -> np.ndarray:
    return np.flatnonzero(sc.tracks.object_type == int(ObjectType.VEHICLE))


def box_corners(xy: np.ndarray, heading: np.ndarray, size: np.ndarray) -> np.ndarray:
    """[..., 4, 2] corners of boxes with centre xy [..., 2], heading [...], size [..., >=2]."""
    c, s = np.cos(heading), np.sin(heading)
    fwd = np.stack([c, s], -1) * size[..., 0:1] / 2
    side = np.stack([-s, c], -1) * size[..., 1:2] / 2
    signs = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]], float)
    return xy[..., None, :] + signs[:, 0:1] * fwd[..., None, :] + signs[:, 1:2] * side[..., None, :]


def boxes_overlap(ca: np.ndarray, cb: np.ndarray) -> np.ndarray:
    """Separating-axis test of convex quads ca, cb [..., 4, 2] -> [...] bool (touching = no)."""
    hit = np.ones(ca.shape[:-2], bool)
    for corners in (ca, cb):
        for k in range(2):
            edge = corners[..., k + 1, :] - corners[..., k, :]
            axis = np.stack([-edge[..., 1], edge[..., 0]], -1)[..., None, :]
            pa, pb = (ca * axis).sum(-1), (cb * axis).sum(-1)
            hit &= (pa.max(-1) > pb.min(-1)) & (pb.max(-1) > pa.min(-1))
    return hit


def signed_edge_distance(points: np.ndarray, edges: list[np.ndarray]) -> np.ndarray:
    """Signed distance of points [n, 2] to road edges, > 0 on the right (off-road side).

    Follows the WOSAC rule: nearest segment over all edges; at an end point clipped to a
    segment end, the sign is combined with the neighbour segment by the junction convexity.
    """
    segs = [(e[:-1], e[1:]) for e in edges if len(e) >= 2]
    a = np.concatenate([s[0] for s in segs])
    b = np.concatenate([s[1] for s in segs])
    first = np.concatenate([np.arange(len(s[0])) == 0 for s in segs])
    last = np.concatenate([np.arange(len(s[0])) == len(s[0]) - 1 for s in segs])
    ab = b - a
    q = points[:, None, :]
    t = ((q - a) * ab).sum(-1) / np.maximum((ab**2).sum(-1), 1e-12)
    closest = a + np.clip(t, 0, 1)[..., None] * ab
    d = np.linalg.norm(q - closest, axis=-1)
    k = np.argmin(d, axis=1)
    rows = np.arange(len(points))

    def cross_sign(j: np.ndarray) -> np.ndarray:
        v = points - a[j]
        return np.sign(v[:, 0] * ab[j, 1] - v[:, 1] * ab[j, 0])

    n = cross_sign(k)
    tk = t[rows, k]
    prev = np.where(first[k], k, k - 1)
    nxt = np.where(last[k], k, np.minimum(k + 1, len(a) - 1))

    def convex(j0: np.ndarray, j1: np.ndarray) -> np.ndarray:
        return ab[j0, 0] * ab[j1, 1] - ab[j0, 1] * ab[j1, 0] > 0

    n_prev, n_next = cross_sign(prev), cross_sign(nxt)
    sign = np.where(
        tk < 0,
        np.where(convex(prev, k), np.maximum(n, n_prev), np.minimum(n, n_prev)),
        np.where(tk > 1, np.where(convex(k, nxt), np.maximum(n, n_next), np.minimum(n, n_next)), n),
    )
    return sign * d[rows, k]


# ----------------------------------------------------------------------------- API


def test_layouts_and_unknown_layout() -> None:
    assert set(LAYOUTS) >= {"intersection", "merge"}
    with pytest.raises(ValueError, match="intersection"):
        generate_scenario("roundabout", 0)


@pytest.mark.parametrize("layout", ["intersection", "merge"])
def test_deterministic_and_seed_dependent(layout: str) -> None:
    a, b, c = scene(layout, 0), generate_scenario(layout, 0), scene(layout, 1)
    for name in ("id", "object_type", "xyz", "heading", "velocity", "size", "valid"):
        np.testing.assert_array_equal(getattr(a.tracks, name), getattr(b.tracks, name))
    np.testing.assert_array_equal(a.signals.state, b.signals.state)
    np.testing.assert_array_equal(a.tracks_to_predict, b.tracks_to_predict)
    assert a.tracks.xyz.shape != c.tracks.xyz.shape or not np.array_equal(
        a.tracks.xyz, c.tracks.xyz
    )
    assert a.scenario_id == f"gen-{layout}-0000"
    assert a.source == f"<generated {layout} seed 0>"


def test_default_scenarios_mix_layouts() -> None:
    scenes = default_scenarios(2)
    assert [s.scenario_id for s in scenes] == ["gen-intersection-0000", "gen-merge-0000"]
    with pytest.raises(ValueError):
        default_scenarios(0)


def test_counts_are_respected() -> None:
    def peds(sc: Scenario) -> int:
        return int((sc.tracks.object_type == int(ObjectType.PEDESTRIAN)).sum())

    sc = generate_scenario("intersection", 5, num_vehicles=6, num_pedestrians=0, num_crossing=0)
    assert peds(sc) == 0
    sc2 = generate_scenario("intersection", 5, num_vehicles=24, num_pedestrians=3, num_crossing=0)
    assert peds(sc2) == 3
    assert vehicles(sc2).size > vehicles(sc).size
    # Crossing pedestrians come on top, at most one per crosswalk (4 here, none on a freeway).
    assert peds(generate_scenario("intersection", 5, num_pedestrians=3, num_crossing=2)) == 5
    assert peds(generate_scenario("intersection", 5, num_pedestrians=0, num_crossing=9)) == 4
    assert peds(generate_scenario("merge", 5, num_pedestrians=0, num_crossing=2)) == 0
    with pytest.raises(ValueError):
        generate_scenario("intersection", 5, num_crossing=-1)


# ----------------------------------------------------------------------------- structure


@pytest.mark.parametrize(("layout", "seed"), CASES)
def test_womd_shape_and_roles(layout: str, seed: int) -> None:
    sc = scene(layout, seed)
    sc.validate()
    t = sc.tracks
    assert sc.num_steps == NUM_STEPS and sc.current_index == CURRENT_INDEX
    np.testing.assert_allclose(sc.timestamps, DT * np.arange(NUM_STEPS))
    assert sc.sdc_index == t.num_tracks - 1
    assert t.object_type[sc.sdc_index] == int(ObjectType.VEHICLE)
    assert t.valid[sc.sdc_index, CURRENT_INDEX]
    # The SDC drives (these scenes all have a vehicle that does), rather than waiting out
    # the log at a red light.
    k = sc.sdc_index
    path = np.linalg.norm(np.diff(t.xyz[k, t.valid[k], :2], axis=0), axis=-1).sum()
    assert path >= SDC_MIN_TRAVEL_M
    veh = vehicles(sc)
    assert t.valid[veh, CURRENT_INDEX].sum() >= 8
    ttp = sc.tracks_to_predict
    assert 1 <= ttp.size <= 4 and sc.sdc_index not in ttp
    assert t.valid[ttp, CURRENT_INDEX].all()
    assert len(np.unique(t.id)) == t.num_tracks
    assert len(np.unique(sc.road_map.id)) == sc.road_map.num_features
    h = t.heading[t.valid]
    assert (h >= -np.pi - 1e-6).all() and (h <= np.pi + 1e-6).all()
    size = t.size[veh][t.valid[veh]]
    # Cars and vans, plus occasional trucks/buses of 8-12 m (deliberately added).
    assert ((size[:, 0] > 3.5) & (size[:, 0] <= 12.0)).all()
    assert ((size[:, 1] > 1.6) & (size[:, 1] < 2.6)).all()
    assert np.mean(size[:, 0] < 7.0) > 0.8
    assert abs(float(np.median(size[:, 0])) - 4.6) < 0.5
    # Invalid entries hold zeros.
    assert not t.xyz[~t.valid].any() and not t.velocity[~t.valid].any()


@pytest.mark.parametrize("layout", ["intersection", "merge"])
def test_lane_graph_and_spacing(layout: str) -> None:
    m = scene(layout, 0).road_map
    index = m.index_of_id()
    lanes = m.indices_of(MapFeatureType.LANE)
    expect_type = LaneType.SURFACE_STREET if layout == "intersection" else LaneType.FREEWAY
    assert (m.subtype[lanes] == int(expect_type)).all()
    assert (m.speed_limit_mph[lanes] > 0).all()
    for k in lanes:
        pl = m.polylines[k]
        assert (pl[:, 2] == 0).all()
        spacing = np.linalg.norm(np.diff(pl[:, :2], axis=0), axis=1)
        assert spacing.max() <= 0.5 + 1e-9 and spacing.min() > 0.35
        for e in m.exit_lanes[k]:
            j = index[int(e)]
            assert m.feature_type[j] == int(MapFeatureType.LANE)
            assert np.linalg.norm(m.polylines[j][0] - pl[-1]) < 0.1
            assert m.id[k] in m.entry_lanes[j]
        for e in m.entry_lanes[k]:
            assert m.id[k] in m.exit_lanes[index[int(e)]]
        for nb in m.left_neighbors[k]:
            assert m.id[k] in m.right_neighbors[index[int(nb)]]


def test_intersection_movements_are_smooth_separate_lanes() -> None:
    net = build_intersection()
    inbound = [ln for ln in net.lanes if not ln.entry]
    assert len(inbound) == 8
    turns = []
    for ln in inbound:
        assert len(ln.exit) == 2  # through + one turn
        for c in ln.exit:
            pts = net.lane(c).points
            d = np.diff(pts, axis=0)
            h = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
            # Smooth arc: radius >= 6 m at 0.5 m spacing, curvature nearly constant, no kinks.
            assert np.abs(np.diff(h)).max() < 0.5 / 6.0
            assert np.abs(np.diff(h, n=2)).max() < 0.01
            turns.append(round(float(h[-1] - h[0]) / (np.pi / 2)))
    assert sorted(set(turns)) == [-1, 0, 1]
    assert turns.count(0) == 8 and turns.count(1) == 4 and turns.count(-1) == 4


@pytest.mark.parametrize("layout", ["intersection", "merge"])
def test_map_features_follow_womd_conventions(layout: str) -> None:
    m = scene(layout, 0).road_map
    edges = m.indices_of(MapFeatureType.ROAD_EDGE)
    assert edges.size >= 3
    assert (m.subtype[edges] == int(RoadEdgeType.BOUNDARY)).all()
    line_types = set(m.subtype[m.indices_of(MapFeatureType.ROAD_LINE)].tolist())
    assert int(RoadLineType.BROKEN_SINGLE_WHITE) in line_types
    if layout == "intersection":
        assert int(RoadLineType.SOLID_DOUBLE_YELLOW) in line_types
        cw = m.indices_of(MapFeatureType.CROSSWALK)
        assert cw.size == 4 and all(m.polylines[k].shape == (4, 3) for k in cw)
    # Road on the left of every edge: lane centres are on the left (negative side).
    lane_pts = np.concatenate([m.polylines[k][:, :2] for k in m.indices_of(MapFeatureType.LANE)])
    dist = signed_edge_distance(lane_pts, [m.polylines[k][:, :2] for k in edges])
    assert (dist < -1.0).all(), dist.max()


def test_signed_edge_distance_helper_detects_a_flipped_edge() -> None:
    edge = np.array([[10.0, 0.0], [-10.0, 0.0]])  # westward: road (y < 0) on the left
    pts = np.array([[0.0, -2.0], [0.0, 2.0]])
    d = signed_edge_distance(pts, [edge])
    np.testing.assert_allclose(d, [-2.0, 2.0])
    np.testing.assert_allclose(signed_edge_distance(pts, [edge[::-1]]), [2.0, -2.0])


# ----------------------------------------------------------------------------- signals


def test_signal_cycle_has_yellow_and_all_red() -> None:
    plan = build_intersection().signals
    assert plan is not None
    t = np.arange(0.0, plan.cycle_s, 0.1)
    st = signal_states(plan, t, 0.0)
    go = st == int(SignalState.GO)
    # Never two approaches green or yellow at once, and some time all are red.
    active = (st != int(SignalState.STOP)).reshape(4, 2, -1)[:, 0]
    assert active.sum(axis=0).max() == 1
    assert (active.sum(axis=0) == 0).any()
    for row in st:
        # Green is always followed by yellow, never directly by red.
        change = np.flatnonzero(row[1:] != row[:-1])
        for c in change:
            if row[c] == int(SignalState.GO):
                assert row[c + 1] == int(SignalState.CAUTION)
    assert go.mean() == pytest.approx(plan.green_s / plan.cycle_s, abs=0.01)


def test_signal_offset_depends_on_seed() -> None:
    states = {tuple(scene("intersection", s).signals.state.flatten().tolist()) for s in SEEDS}
    assert len(states) > 1
    sc = scene("intersection", 0)
    lanes = sc.road_map.index_of_id()
    for lid, sp in zip(sc.signals.lane_id, sc.signals.stop_point):
        np.testing.assert_allclose(sc.road_map.polylines[lanes[int(lid)]][-1], sp)


def on_signalled_lane(sc: Scenario, veh: np.ndarray, lane_id: int, stop: np.ndarray):
    """Where vehicles ``veh`` are relative to a signalled lane's stop point ``stop`` [>= 2]:
    (front-bumper distance past the stop point [V, T] m, on the lane [V, T] bool).

    A vehicle is on the lane when it is valid, its centre is within 1.75 m of the lane's line
    through the stop point and it heads along the lane.
    """
    t = sc.tracks
    pl = sc.road_map.polylines[sc.road_map.index_of_id()[int(lane_id)]][:, :2]
    d = (pl[-1] - pl[-2]) / np.linalg.norm(pl[-1] - pl[-2])
    rel = t.xyz[veh, :, :2] - stop[:2]
    lon = rel @ d + 0.5 * t.size[veh, :, 0]
    lat = np.abs(rel @ np.array([-d[1], d[0]]))
    head = np.cos(t.heading[veh]) * d[0] + np.sin(t.heading[veh]) * d[1]
    return lon, t.valid[veh] & (lat < 1.75) & (head > 0.9)


def stop_line_crossings(sc: Scenario, states: np.ndarray) -> tuple[int, int]:
    """(front-bumper crossings of signalled stop lines, crossings into a STOP state).

    A vehicle on a controlled lane (``on_signalled_lane``) crosses between t and t+1 when its
    front bumper goes from before the stop point to past it.
    """
    veh = vehicles(sc)
    crossings = violations = 0
    for lid, st, sp in zip(sc.signals.lane_id, states, sc.signals.stop_point):
        lon, on = on_signalled_lane(sc, veh, lid, sp)
        cross = on[:, :-1] & on[:, 1:] & (lon[:, :-1] <= 0) & (lon[:, 1:] > 0)
        crossings += int(cross.sum())
        violations += int((cross & (st[1:] == int(SignalState.STOP))[None, :]).sum())
    return crossings, violations


SIGNALISED = ("intersection", "permissive_intersection")


@pytest.mark.parametrize("seed", range(5))
@pytest.mark.parametrize("layout", SIGNALISED)
def test_vehicles_stop_for_red(layout: str, seed: int) -> None:
    sc = scene(layout, seed)
    assert stop_line_crossings(sc, sc.signals.state)[1] == 0


@pytest.mark.parametrize("layout", SIGNALISED)
def test_red_light_check_is_not_vacuous(layout: str) -> None:
    total = flipped = 0
    for seed in SEEDS:
        sc = scene(layout, seed)
        total += stop_line_crossings(sc, sc.signals.state)[0]
        # With GO and STOP swapped, vehicles that crossed on green now cross "on red".
        swap = np.where(
            sc.signals.state == int(SignalState.GO), int(SignalState.STOP), int(SignalState.GO)
        )
        flipped += stop_line_crossings(sc, swap)[1]
    assert total > 0 and flipped > 0


# ----------------------------------------------------------------------------- kinematics


@pytest.mark.parametrize(("layout", "seed"), CASES)
def test_no_vehicle_overlap(layout: str, seed: int) -> None:
    sc = scene(layout, seed)
    t = sc.tracks
    veh = vehicles(sc)
    corners = box_corners(t.xyz[veh, :, :2], t.heading[veh], t.size[veh])
    i, j = np.triu_indices(veh.size, 1)
    both = t.valid[veh][i] & t.valid[veh][j]
    hit = boxes_overlap(corners[i], corners[j]) & both
    assert not hit.any(), f"overlap of tracks {veh[i[hit.any(1)]]} and {veh[j[hit.any(1)]]}"


def test_overlap_helper_detects_overlap() -> None:
    xy = np.array([[0.0, 0.0], [4.0, 0.5], [0.0, 3.0]])
    c = box_corners(xy, np.array([0.0, 0.3, 0.0]), np.array([[4.5, 2.0], [4.5, 2.0], [4.5, 2.0]]))
    assert boxes_overlap(c[0], c[1]) and not boxes_overlap(c[0], c[2])


@pytest.mark.parametrize(("layout", "seed"), CASES)
def test_kinematics_are_unicycle_consistent(layout: str, seed: int) -> None:
    sc = scene(layout, seed)
    t = sc.tracks
    veh = vehicles(sc)
    xy = t.xyz[veh, :, :2]
    valid = t.valid[veh]
    pair = valid[:, 1:] & valid[:, :-1]
    speed = np.linalg.norm(t.velocity[veh], axis=-1)
    if layout == "intersection":
        assert speed[valid].max() <= 25.0
    assert speed[valid].max() > 5.0  # traffic moves
    # Velocity direction equals heading (where moving).
    moving = valid & (speed > 0.5)
    vdir = np.arctan2(t.velocity[veh, :, 1], t.velocity[veh, :, 0])
    assert np.abs(wrap_angle_np(vdir - t.heading[veh]))[moving].max() < 1e-3
    # Positions agree with the mean of consecutive velocities.
    fd = np.diff(xy, axis=1) / DT
    mean_v = 0.5 * (t.velocity[veh, 1:] + t.velocity[veh, :-1])
    assert np.linalg.norm(fd - mean_v, axis=-1)[pair].max() < 0.3
    # Acceleration and yaw rate from finite differences.
    acc = np.diff(speed, axis=1) / DT
    assert np.abs(acc[pair]).max() <= 8.0
    assert np.mean(np.abs(acc[pair]) <= 5.0 + 1e-3) > 0.99
    yaw = wrap_angle_np(np.diff(t.heading[veh].astype(np.float64), axis=1)) / DT
    assert np.abs(yaw[pair]).max() <= 1.5
    # Heading is smooth: yaw acceleration bounded.
    pair3 = pair[:, 1:] & pair[:, :-1]
    assert np.abs(np.diff(yaw, axis=1)[pair3]).max() / DT < 10.0


@pytest.mark.parametrize(("layout", "seed"), CASES)
def test_vehicles_stay_on_lanes_and_leave_at_border(layout: str, seed: int) -> None:
    sc = scene(layout, seed)
    t = sc.tracks
    veh = vehicles(sc)
    m = sc.road_map
    lane_pts = np.concatenate([m.polylines[k][:, :2] for k in m.indices_of(MapFeatureType.LANE)])
    xy = t.xyz[veh, :, :2][t.valid[veh]]
    d = np.min(np.linalg.norm(xy[:, None, :] - lane_pts[None, ::2], axis=-1), axis=1)
    assert d.max() < 0.6
    extent = np.abs(np.concatenate([p[:, :2] for p in m.polylines])).max()
    assert np.abs(xy).max() <= extent + 1e-6
    # Once invalid after being valid, a vehicle stays invalid (it left the map).
    v = t.valid[veh].astype(int)
    assert (np.diff(v, axis=1) >= 0).sum() + (np.diff(v, axis=1) < 0).sum() == v.size - veh.size
    ends = (np.diff(v, axis=1) < 0).sum(axis=1)
    starts = (np.diff(v, axis=1) > 0).sum(axis=1)
    assert (ends <= 1).all() and (starts <= 1).all()


def test_pedestrians_walk_off_road() -> None:
    """Sidewalk walkers (crossing pedestrians are tested in test_generator_layouts)."""
    sc = generate_scenario("intersection", 0, num_crossing=0)
    t = sc.tracks
    ped = np.flatnonzero(t.object_type == int(ObjectType.PEDESTRIAN))
    assert ped.size == 4
    speed = np.linalg.norm(t.velocity[ped], axis=-1)[t.valid[ped]]
    assert ((speed > 0.5) & (speed < 2.5)).all()
    m = sc.road_map
    edges = [m.polylines[k][:, :2] for k in m.indices_of(MapFeatureType.ROAD_EDGE)]
    dist = signed_edge_distance(t.xyz[ped, :, :2][t.valid[ped]], edges)
    assert (dist > 0).all()


def test_generation_is_fast() -> None:
    import time

    start = time.perf_counter()
    generate_scenario("intersection", 7)
    assert time.perf_counter() - start < 1.5
