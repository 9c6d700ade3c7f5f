"""Tests of the generator's scene variety: every layout, stop signs, T-junction priority,
driver personalities and vehicle sizes, cyclists, crossing pedestrians, the training mix
(tbsim_env.data.generator)."""

from __future__ import annotations

import dataclasses
import functools
import time

import numpy as np
import pytest

from tbsim_env.core.constants import (
    CURRENT_INDEX,
    DT,
    NUM_STEPS,
    MapFeatureType,
    ObjectType,
    SignalState,
)
from tbsim_env.data.generator import (
    LAYOUTS,
    default_scenarios,
    frame_offset,
    generate_scenario,
    training_mix,
)
from tbsim_env.data.generator.behaviour import CALIBRATED
from tbsim_env.data.generator.crossings import PED_ACCEL, walk_time_left
from tbsim_env.data.generator.driver import (
    DriverConfig,
    add_cyclists,
    draw_fleet,
    kerb_routes,
    straight_routes,
)
from tbsim_env.data.generator.roads import (
    LAYOUT_BUILDERS,
    PRIORITY,
    STOP,
    build_t_junction,
    connector_conflicts,
    signal_states,
)
from tbsim_env.data.generator.routes import build_routes
from tbsim_env.data.generator.scenes import MAP_MARGIN_M, WALK_SPEED_LIMITS
from tbsim_env.data.scenario import Scenario, wrap_angle_np
from tests.test_generator import (
    SIGNALISED,
    box_corners,
    boxes_overlap,
    on_signalled_lane,
    signed_edge_distance,
)

SEEDS10 = tuple(range(10))
ALL_CASES = [(layout, seed) for layout in LAYOUTS for seed in SEEDS10]
JUNCTIONS = ("stop_intersection", "t_junction")


@functools.cache
def scene(layout: str, seed: int) -> Scenario:
    """The generated scene moved back into its layout's frame (junction at the origin)."""
    dx, dy = frame_offset(layout, seed)
    return generate_scenario(layout, seed).transformed(shift=(-dx, -dy))


def test_scenario_transform_round_trips_and_keeps_placeholders() -> None:
    sc = generate_scenario("intersection", 1)
    moved = sc.transformed(0.7, (120.0, -40.0))
    back = moved.transformed(shift=(-120.0, 40.0)).transformed(-0.7)
    t, b, m = sc.tracks, back.tracks, moved.tracks
    ok = t.valid
    np.testing.assert_allclose(b.xyz[ok], t.xyz[ok], atol=1e-9)
    np.testing.assert_allclose(b.velocity[ok], t.velocity[ok], atol=1e-5)
    np.testing.assert_allclose(wrap_angle_np(b.heading - t.heading)[ok], 0.0, atol=1e-5)
    assert (m.xyz[~ok] == t.xyz[~ok]).all() and (m.heading[~ok] == t.heading[~ok]).all()
    speed = np.linalg.norm(m.velocity[ok], axis=-1)
    np.testing.assert_allclose(speed, np.linalg.norm(t.velocity[ok], axis=-1), atol=1e-4)
    for p, q in zip(back.road_map.polylines, sc.road_map.polylines):
        np.testing.assert_allclose(p, q, atol=1e-9)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_roads_run_past_the_observed_area(layout: str) -> None:
    """Tracks are observed inside [-E, E]^2; the lanes go on MAP_MARGIN_M beyond, so a
    simulated agent ahead of its log still has road (no map end to stop at)."""
    sc = scene(layout, 2)
    extent = LAYOUT_BUILDERS[layout]().half_extent
    t = sc.tracks
    assert (np.abs(t.xyz[..., :2][t.valid]) <= extent + 1e-9).all()
    lanes = np.concatenate(
        [sc.road_map.polylines[k][:, :2] for k in sc.road_map.indices_of(MapFeatureType.LANE)]
    )
    assert np.abs(lanes).max() >= extent + 0.9 * MAP_MARGIN_M
    # Vehicles still enter and leave the observed area during the log.
    enter = leave = False
    for seed in range(2, 10):  # all-way-stop traffic is slow: few leave within 9 s
        v = scene(layout, seed).tracks.valid[vehicles(scene(layout, seed))]
        enter |= bool((~v[:, 0] & v[:, -1]).any())
        leave |= bool((v[:, 0] & ~v[:, -1]).any())
    assert enter and leave


@pytest.mark.parametrize("layout", LAYOUTS)
def test_scene_lies_far_from_the_placeholder_origin(layout: str) -> None:
    """Invalid track steps hold (0, 0) as in WOMD; no road may be near there."""
    sc = generate_scenario(layout, 3)
    pts = np.concatenate([p[:, :2] for p in sc.road_map.polylines])
    assert np.linalg.norm(pts, axis=-1).min() > 500.0
    t = sc.tracks
    assert (t.xyz[~t.valid] == 0.0).all()
    dx, dy = frame_offset(layout, 3)
    back = sc.transformed(shift=(-dx, -dy))
    local = scene(layout, 3)
    np.testing.assert_allclose(back.tracks.xyz, local.tracks.xyz, atol=1e-9)


def vehicles(sc: Scenario) -> np.ndarray:
    return np.flatnonzero(sc.tracks.object_type == int(ObjectType.VEHICLE))


# ----------------------------------------------------------------------------- API


def test_layouts_are_registered() -> None:
    # New layouts go last: the held-out and validation sets cycle through the first four.
    assert LAYOUTS == (
        "intersection",
        "merge",
        "stop_intersection",
        "t_junction",
        "permissive_intersection",
    )


@pytest.mark.parametrize("layout", LAYOUTS)
def test_every_layout_validates_and_is_deterministic(layout: str) -> None:
    a, b = generate_scenario(layout, 3), generate_scenario(layout, 3)
    a.validate()
    for name in ("id", "object_type", "xyz", "heading", "velocity", "size", "valid"):
        np.testing.assert_array_equal(getattr(a.tracks, name), getattr(b.tracks, name))
    np.testing.assert_array_equal(a.tracks_to_predict, b.tracks_to_predict)
    assert not np.array_equal(a.tracks.xyz[-1], scene(layout, 4).tracks.xyz[-1])
    t = a.tracks
    assert a.sdc_index == t.num_tracks - 1
    assert t.object_type[-1] == int(ObjectType.VEHICLE)
    assert t.valid[-1, CURRENT_INDEX]
    assert 1 <= a.tracks_to_predict.size <= 4 and a.sdc_index not in a.tracks_to_predict
    assert (t.object_type[a.tracks_to_predict] == int(ObjectType.VEHICLE)).all()
    assert a.num_steps == NUM_STEPS


def test_sdc_is_valid_over_the_whole_log_in_most_scenes() -> None:
    full = [scene(layout, s).tracks.valid[-1].all() for layout in LAYOUTS for s in SEEDS10]
    assert np.mean(full) >= 0.9


def test_training_mix_round_robin() -> None:
    for seed in range(len(LAYOUTS)):
        sc = training_mix(seed)
        assert sc.scenario_id == f"gen-{LAYOUTS[seed % len(LAYOUTS)]}-{seed:04d}"
    sc = training_mix(5, ("t_junction", "merge"))
    assert sc.scenario_id == "gen-merge-0005"
    np.testing.assert_array_equal(sc.tracks.xyz, generate_scenario("merge", 5).tracks.xyz)
    with pytest.raises(ValueError):
        training_mix(0, ())


def test_default_scenarios_cover_the_first_four_layouts_and_are_fast() -> None:
    start = time.perf_counter()
    scenes = default_scenarios(8)
    elapsed = time.perf_counter() - start
    # The embedded default was fixed before the permissive intersection was added.
    assert {s.scenario_id.split("-")[1] for s in scenes} == set(LAYOUTS[:4])
    assert elapsed < 4.0  # < 3 s on an idle core; slack for shared CI machines


@pytest.mark.parametrize("layout", LAYOUTS)
def test_generation_under_a_second(layout: str) -> None:
    generate_scenario(layout, 11)  # warm caches (imports)
    start = time.perf_counter()
    generate_scenario(layout, 12)
    assert time.perf_counter() - start < 1.5


# ----------------------------------------------------------------------------- map


@pytest.mark.parametrize("layout", JUNCTIONS)
def test_junction_map_follows_womd_conventions(layout: str) -> None:
    m = scene(layout, 0).road_map
    index = m.index_of_id()
    lanes = m.indices_of(MapFeatureType.LANE)
    for k in lanes:
        pl = m.polylines[k]
        spacing = np.linalg.norm(np.diff(pl[:, :2], axis=0), axis=1)
        assert spacing.max() <= 0.5 + 1e-9 and spacing.min() > 0.35
        for e in m.exit_lanes[k]:
            j = index[int(e)]
            assert np.linalg.norm(m.polylines[j][0] - pl[-1]) < 0.1
            assert m.id[k] in m.entry_lanes[j]
        for e in m.entry_lanes[k]:
            assert m.id[k] in m.exit_lanes[index[int(e)]]
        for nb in m.left_neighbors[k]:
            assert m.id[k] in m.right_neighbors[index[int(nb)]]
    edges = m.indices_of(MapFeatureType.ROAD_EDGE)
    lane_pts = np.concatenate([m.polylines[k][:, :2] for k in lanes])
    dist = signed_edge_distance(lane_pts, [m.polylines[k][:, :2] for k in edges])
    assert (dist < -1.0).all(), dist.max()
    cw = m.indices_of(MapFeatureType.CROSSWALK)
    assert cw.size == (4 if layout == "stop_intersection" else 3)
    assert all(m.polylines[k].shape == (4, 3) for k in cw)
    assert m.indices_of(MapFeatureType.ROAD_LINE).size > 0
    assert len(scene(layout, 0).signals.lane_id) == 0


@pytest.mark.parametrize("layout", JUNCTIONS)
def test_stop_signs_control_the_lanes_ending_at_the_junction(layout: str) -> None:
    m = scene(layout, 0).road_map
    index = m.index_of_id()
    signs = m.indices_of(MapFeatureType.STOP_SIGN)
    assert signs.size == (4 if layout == "stop_intersection" else 1)
    for k in signs:
        assert m.polylines[k].shape == (1, 3)
        ctrl = m.controlled_lanes[k]
        assert ctrl.size == 2
        for lid in ctrl:
            j = index[int(lid)]
            assert m.feature_type[j] == int(MapFeatureType.LANE)
            assert len(m.entry_lanes[j]) == 0 and len(m.exit_lanes[j]) >= 1
            # The sign stands by the end of the lane it controls.
            assert np.linalg.norm(m.polylines[j][-1, :2] - m.polylines[k][0, :2]) < 8.0
    others = np.setdiff1d(np.arange(m.num_features), signs)
    assert all(m.controlled_lanes[k].size == 0 for k in others)


def test_t_junction_priority_rules() -> None:
    net = build_t_junction()
    assert net.junction is not None and net.signals is None
    kinds = dict(zip(net.junction.lane_ids, net.junction.kind))
    minor = [lid for lid, k in kinds.items() if k == STOP]
    assert len(minor) == 2 and sum(k == PRIORITY for k in kinds.values()) == 4
    turns = []
    for lid in minor:
        for c in net.lane(lid).exit:
            assert net.junction.rank[c] == 2
            p = net.lane(c).points
            h = np.unwrap(np.arctan2(*np.diff(p, axis=0)[:, ::-1].T))
            turns.append(round(float(h[-1] - h[0]) / (np.pi / 2)))
    assert sorted(turns) == [-1, 1]  # the minor road turns left or right, no through
    conflict = connector_conflicts(net)
    assert not np.diagonal(conflict).any() and (conflict == conflict.T).all()
    ranks = net.junction.rank
    # Both major through directions never conflict with each other.
    for a in ranks:
        for b in ranks:
            if ranks[a] == 0 and ranks[b] == 0:
                assert not conflict[a, b]
    # Major left turns (rank 1) conflict with oncoming through traffic.
    lefts = [c for c, r in ranks.items() if r == 1]
    assert lefts and all(conflict[c, [a for a in ranks if ranks[a] == 0]].any() for c in lefts)


# ----------------------------------------------------------------------------- safety


@pytest.mark.parametrize(("layout", "seed"), ALL_CASES)
def test_no_overlap_between_any_agents(layout: str, seed: int) -> None:
    sc = scene(layout, seed)
    t = sc.tracks
    corners = box_corners(t.xyz[..., :2], t.heading, t.size)
    i, j = np.triu_indices(t.num_tracks, 1)
    hit = boxes_overlap(corners[i], corners[j]) & t.valid[i] & t.valid[j]
    assert not hit.any(), f"overlap of tracks {i[hit.any(1)]} and {j[hit.any(1)]}"


@pytest.mark.parametrize(("layout", "seed"), ALL_CASES)
def test_vehicle_kinematics_every_layout(layout: str, seed: int) -> None:
    sc = scene(layout, seed)
    t = sc.tracks
    veh = vehicles(sc)
    valid = t.valid[veh]
    pair = valid[:, 1:] & valid[:, :-1]
    speed = np.linalg.norm(t.velocity[veh], axis=-1)
    moving = valid & (speed > 0.5)
    vdir = np.arctan2(t.velocity[veh, :, 1], t.velocity[veh, :, 0])
    assert np.abs(wrap_angle_np(vdir - t.heading[veh]))[moving].max() < 1e-3
    fd = np.diff(t.xyz[veh, :, :2], axis=1) / DT
    mean_v = 0.5 * (t.velocity[veh, 1:] + t.velocity[veh, :-1])
    assert np.linalg.norm(fd - mean_v, axis=-1)[pair].max() < 0.3
    acc = np.diff(speed, axis=1) / DT
    assert np.mean(np.abs(acc[pair]) <= 5.0 + 1e-3) > 0.99
    yaw = wrap_angle_np(np.diff(t.heading[veh].astype(np.float64), axis=1)) / DT
    assert np.abs(yaw[pair]).max() <= 1.5


def stop_sign_crossings(sc: Scenario) -> tuple[int, int]:
    """(stop-line crossings of stop-controlled lanes, crossings without a full stop before).

    A vehicle is on a controlled lane when its centre is within 1.75 m of the lane's line
    through the lane end and it heads along the lane. A crossing (front bumper from before
    the line to past it) needs an earlier step of the same approach with speed < 0.05 m/s
    and the front within 4 m of the line. Crossings of vehicles that were already moving
    within 8 m of the line when first seen are skipped (their stop may predate the log).
    """
    t, m = sc.tracks, sc.road_map
    veh = vehicles(sc)
    index = m.index_of_id()
    speed = np.linalg.norm(t.velocity[veh], axis=-1)
    crossings = missing = 0
    for k in m.indices_of(MapFeatureType.STOP_SIGN):
        for lid in m.controlled_lanes[k]:
            pl = m.polylines[index[int(lid)]][:, :2]
            d = (pl[-1] - pl[-2]) / np.linalg.norm(pl[-1] - pl[-2])
            rel = t.xyz[veh, :, :2] - pl[-1]
            lon = rel @ d + 0.5 * t.size[veh, :, 0]
            lat = np.abs(rel @ np.array([-d[1], d[0]]))
            head = np.cos(t.heading[veh]) * d[0] + np.sin(t.heading[veh]) * d[1]
            on = t.valid[veh] & (lat < 1.75) & (head > 0.9) & (lon > -90.0)
            cross = on[:, :-1] & on[:, 1:] & (lon[:, :-1] <= 0) & (lon[:, 1:] > 0)
            for a, step in zip(*np.nonzero(cross)):
                first = int(np.argmax(on[a]))
                if lon[a, first] > -8.0 and speed[a, first] >= 0.05:
                    continue
                crossings += 1
                seg = slice(first, step + 1)
                stopped = on[a, seg] & (speed[a, seg] < 0.05) & (lon[a, seg] > -4.0)
                missing += int(not stopped.any())
    return crossings, missing


@pytest.mark.parametrize("layout", JUNCTIONS)
def test_full_stop_at_stop_signs(layout: str) -> None:
    total = 0
    # 20 seeds: crossing pedestrians and cyclists hold the minor road of the T-junction
    # long enough that 10 seeds of 9 s see only a few stop-line crossings.
    for seed in range(20):
        crossings, missing = stop_sign_crossings(scene(layout, seed))
        assert missing == 0, (seed, crossings, missing)
        total += crossings
    assert total >= 5  # the check is not vacuous


def test_stop_check_detects_rolling_stops() -> None:
    sc = scene("stop_intersection", 0)
    t = sc.tracks
    # Replace every vehicle speed by a constant 5 m/s: no one ever stops.
    vel = t.velocity.copy()
    norm = np.maximum(np.linalg.norm(vel, axis=-1, keepdims=True), 1e-9)
    unit = np.where(norm > 1e-6, vel / norm, 1.0)
    fake = sc.replace(tracks=type(t)(**{**t.__dict__, "velocity": (unit * 5.0).astype(np.float32)}))
    total = sum(stop_sign_crossings(scene("stop_intersection", s))[0] for s in SEEDS10)
    assert total > 0
    crossings, missing = stop_sign_crossings(fake)
    assert missing == crossings


def test_stop_intersection_vehicles_cross_from_several_approaches() -> None:
    arms = set()
    for seed in SEEDS10:
        sc = scene("stop_intersection", seed)
        t = sc.tracks
        veh = vehicles(sc)
        inside = t.valid[veh] & (np.abs(t.xyz[veh, :, :2]).max(axis=-1) < 8.0)
        for a in np.flatnonzero(inside.any(axis=1)):
            step = int(np.argmax(inside[a]))
            h = float(t.heading[veh[a], step])
            arms.add(round(h / (np.pi / 2)) % 4)
    assert len(arms) == 4


def test_t_junction_minor_road_turns_left_and_right() -> None:
    turns = set()
    for seed in SEEDS10:
        sc = scene("t_junction", seed)
        t = sc.tracks
        for a in vehicles(sc):
            v = np.flatnonzero(t.valid[a])
            p0, p1 = t.xyz[a, v[0], :2], t.xyz[a, v[-1], :2]
            if p0[1] < -10.0 and abs(p1[1]) < 8.0:  # came from the south arm, left on major
                turns.add("left" if p1[0] < -8.0 else "right" if p1[0] > 8.0 else "?")
    assert {"left", "right"} <= turns


# ----------------------------------------------------------------------------- variety


def test_driver_personalities_shape_parameters() -> None:
    net = LAYOUT_BUILDERS["intersection"]()
    routes = build_routes(net)
    cfg = DriverConfig(desired_speed=(9.0, 14.0))
    w = np.ones(routes.num_routes)
    fleet = draw_fleet(routes, w, 2000, cfg, np.random.default_rng(0))
    p = fleet.personality
    assert p.min() < -0.7 and p.max() > 0.7  # timid and aggressive drivers
    car = ~fleet.is_long
    for name, sign in (
        ("desired_speed", 1),
        ("time_headway", -1),
        ("min_gap", -1),
        ("max_accel", 1),
        ("comfort_decel", 1),
        ("reaction", -1),
        ("gap_time", -1),
    ):
        x = getattr(fleet, name)[car]
        assert sign * np.corrcoef(p[car], x)[0, 1] > 0.6, name
    assert fleet.time_headway.min() < 1.1 and fleet.time_headway.max() > 2.0
    # Per-seed culture: the mean personality differs between seeds.
    means = [
        draw_fleet(routes, w, 400, cfg, np.random.default_rng(s)).personality.mean()
        for s in range(8)
    ]
    assert np.ptp(means) > 0.2


def test_vehicle_sizes_include_vans_and_trucks_on_straight_routes() -> None:
    net = LAYOUT_BUILDERS["intersection"]()
    routes = build_routes(net)
    cfg = DriverConfig(desired_speed=(9.0, 14.0), truck_share=(0.05, 0.1))
    fleet = draw_fleet(routes, np.ones(routes.num_routes), 3000, cfg, np.random.default_rng(1))
    length = fleet.size[:, 0]
    truck = fleet.is_long
    assert 0.04 < truck.mean() < 0.11
    assert ((length[truck] >= 8.0) & (length[truck] <= 12.0)).all()
    assert ((length > 5.0) & (length < 6.5)).mean() > 0.03
    assert straight_routes(routes, cfg)[fleet.route[truck]].all()
    assert not straight_routes(routes, cfg).all()
    # Trucks are slower off the line than cars.
    assert fleet.max_accel[truck].mean() < 0.8 * fleet.max_accel[~truck].mean()


def test_generated_scenes_contain_long_vehicles() -> None:
    lengths = np.concatenate(
        [
            scene(layout, s).tracks.size[vehicles(scene(layout, s))].max(axis=1)[:, 0]
            for layout in LAYOUTS
            for s in SEEDS10
        ]
    )
    assert (lengths > 8.0).sum() >= 3
    assert lengths.max() <= 12.0 + 1e-4


# ----------------------------------------------------------------------------- cyclists

URBAN = ("intersection", "stop_intersection", "t_junction", "permissive_intersection")


def cyclists(sc: Scenario) -> np.ndarray:
    return np.flatnonzero(sc.tracks.object_type == int(ObjectType.CYCLIST))


@pytest.mark.parametrize("layout", LAYOUTS)
def test_cyclists_ride_in_urban_layouts_only(layout: str) -> None:
    total = 0
    for seed in range(8):
        sc = scene(layout, seed)
        t = sc.tracks
        cyc = cyclists(sc)
        total += cyc.size
        assert sc.sdc_index not in cyc and not np.isin(sc.tracks_to_predict, cyc).any()
        if cyc.size == 0:
            continue
        size = t.size[cyc][t.valid[cyc]]
        assert ((size[:, 0] >= 1.6 - 1e-6) & (size[:, 0] <= 1.9 + 1e-6)).all()
        assert ((size[:, 1] >= 0.6 - 1e-6) & (size[:, 1] <= 0.8 + 1e-6)).all()
        assert ((size[:, 2] >= 1.6 - 1e-6) & (size[:, 2] <= 1.8 + 1e-6)).all()
        valid = t.valid[cyc]
        speed = np.linalg.norm(t.velocity[cyc], axis=-1)
        assert speed[valid].max() <= 7.0 + 1e-3
        pair = valid[:, 1:] & valid[:, :-1]
        acc = np.diff(speed, axis=1) / DT
        assert np.mean(acc[pair] <= 1.5 + 1e-3) > 0.99  # gentler than cars
        fd = np.diff(t.xyz[cyc, :, :2], axis=1) / DT
        mean_v = 0.5 * (t.velocity[cyc, 1:] + t.velocity[cyc, :-1])
        assert np.linalg.norm(fd - mean_v, axis=-1)[pair].max() < 0.3
    if layout == "merge":
        assert total == 0
    else:
        assert total >= 4, total


def test_cyclists_take_kerb_lanes_and_keep_other_draws() -> None:
    net = LAYOUT_BUILDERS["intersection"]()
    routes = build_routes(net)
    w = np.ones(routes.num_routes)
    cfg = DriverConfig(desired_speed=(9.0, 14.0), cyclist_share=(0.2, 0.3))
    fleet = draw_fleet(routes, w, 2000, cfg, np.random.default_rng(0))
    kerb = kerb_routes(net, routes)
    assert 0 < kerb.sum() < routes.num_routes
    with_cyc = add_cyclists(fleet, w, kerb, cfg, np.random.default_rng(1))
    cyc = with_cyc.cyclist
    assert 0.15 < cyc.mean() < 0.35
    assert kerb[with_cyc.route[cyc]].all()
    assert ((with_cyc.desired_speed[cyc] >= 4.0) & (with_cyc.desired_speed[cyc] <= 7.0)).all()
    assert with_cyc.max_accel[cyc].max() <= 1.5 and not with_cyc.is_long[cyc].any()
    # Motor vehicle slots are untouched.
    for name in ("route", "size", "desired_speed", "max_accel", "personality"):
        np.testing.assert_array_equal(getattr(with_cyc, name)[~cyc], getattr(fleet, name)[~cyc])
    # No share, no cyclists and no draws: the fleet object comes back as it was.
    none = dataclasses.replace(cfg, cyclist_share=(0.0, 0.0))
    assert add_cyclists(fleet, w, kerb, none, np.random.default_rng(1)) is fleet


def test_vehicles_queue_behind_cyclists() -> None:
    """Somewhere a motor vehicle drives right behind a cyclist (same heading, within 12 m)
    at about the cyclist's speed: cyclists are part of the traffic, not ghosts."""
    found = 0
    for layout in URBAN:
        for seed in range(8):
            t = scene(layout, seed).tracks
            veh, cyc = vehicles(scene(layout, seed)), cyclists(scene(layout, seed))
            for c in cyc:
                h = np.stack([np.cos(t.heading[c]), np.sin(t.heading[c])], -1)  # [T, 2]
                rel = t.xyz[veh, :, :2] - t.xyz[c, :, :2]  # [V, T, 2]
                lon = (rel * h).sum(-1)
                lat = np.abs(rel[..., 0] * h[:, 1] - rel[..., 1] * h[:, 0])
                v_c = np.linalg.norm(t.velocity[c], axis=-1)
                v_v = np.linalg.norm(t.velocity[veh], axis=-1)
                behind = t.valid[veh] & t.valid[c] & (lon < -2.0) & (lon > -12.0) & (lat < 1.0)
                found += int((behind & (v_c > 2.0) & (np.abs(v_v - v_c) < 1.0)).any())
    assert found >= 4


# ----------------------------------------------------------------------------- crossings


def crosswalk_polygons(sc: Scenario) -> list:
    import shapely

    m = sc.road_map
    return [shapely.Polygon(m.polylines[k][:, :2]) for k in m.indices_of(MapFeatureType.CROSSWALK)]


def on_crosswalk(sc: Scenario, a: int, buffer: float = 0.0) -> np.ndarray:
    """[T, C] bool, track a's centre inside each crosswalk polygon (grown by buffer) and valid."""
    import shapely

    xy = sc.tracks.xyz[a, :, :2]
    polys = crosswalk_polygons(sc)
    inside = [shapely.contains_xy(p.buffer(buffer), xy[:, 0], xy[:, 1]) for p in polys]
    return np.stack(inside, axis=1) & sc.tracks.valid[a][:, None]


def pedestrians(sc: Scenario) -> np.ndarray:
    return np.flatnonzero(sc.tracks.object_type == int(ObjectType.PEDESTRIAN))


@pytest.mark.parametrize("layout", URBAN)
def test_pedestrians_cross_on_crosswalks_and_stay_off_the_road_elsewhere(layout: str) -> None:
    import shapely

    crossing = 0
    for seed in range(8):
        sc = scene(layout, seed)
        t, m = sc.tracks, sc.road_map
        edges = [m.polylines[k][:, :2] for k in m.indices_of(MapFeatureType.ROAD_EDGE)]
        for a in pedestrians(sc):
            xy = t.xyz[a, t.valid[a], :2]
            path = shapely.LineString(xy) if len(xy) > 1 else shapely.Point(xy[0])
            crosses = any(path.intersects(p) for p in crosswalk_polygons(sc))
            crossing += crosses
            # On the road only on (or right beside, at the rounded kerb) a crosswalk.
            off_road = signed_edge_distance(xy, edges) > 0.0
            near_cw = on_crosswalk(sc, a, buffer=1.2).any(axis=1)[t.valid[a]]
            assert (off_road | near_cw).all(), (seed, a)
            speed = np.linalg.norm(t.velocity[a], axis=-1)
            if not crosses:  # sidewalk walkers: calibrated speed fluctuation (scenes.py)
                assert speed[t.valid[a]].max() <= WALK_SPEED_LIMITS[1] + 0.1
                continue
            assert speed[t.valid[a]].max() <= CALIBRATED.crossing_speed[1] + 1e-3
            pair = t.valid[a, 1:] & t.valid[a, :-1]
            assert (np.abs(np.diff(speed) / DT)[pair] <= PED_ACCEL + 1e-3).all()  # no jumps
    assert crossing >= 6, crossing


def through_lanes(sc: Scenario, poly: object) -> tuple[np.ndarray, np.ndarray]:
    """Signal rows of (lanes whose traffic runs straight through the crosswalk, lanes whose
    traffic runs beside it), by the direction of the lane at its stop point."""
    m = sc.road_map
    lanes = m.index_of_id()
    corners = np.asarray(poly.exterior.coords)[:4]
    long_axis = corners[3] - corners[0]
    long_axis = long_axis / np.linalg.norm(long_axis)
    centre = corners.mean(axis=0)
    through, beside = [], []
    for row, lid in enumerate(sc.signals.lane_id):
        pl = m.polylines[lanes[int(lid)]][:, :2]
        d = (pl[-1] - pl[-2]) / np.linalg.norm(pl[-1] - pl[-2])
        if abs(d @ long_axis) < 0.1 and abs((pl[-1] - centre) @ long_axis) < 7.0:
            through.append(row)
        elif abs(d @ long_axis) > 0.9:
            beside.append(row)
    return np.asarray(through), np.asarray(beside)


@pytest.mark.parametrize("layout", SIGNALISED)
def test_signalised_crossings_start_while_traffic_through_them_has_red(layout: str) -> None:
    starts = 0
    for seed in range(10):
        sc = scene(layout, seed)
        polys = crosswalk_polygons(sc)
        state = sc.signals.state
        for a in pedestrians(sc):
            on = on_crosswalk(sc, a)
            for c in np.flatnonzero(on.any(axis=0)):
                k = int(np.argmax(on[:, c]))
                if k == 0 or not sc.tracks.valid[a, k - 1]:
                    continue  # already on it when first seen
                starts += 1
                through, beside = through_lanes(sc, polys[c])
                assert through.size == 4 and beside.size == 4
                assert (state[through, k] == int(SignalState.STOP)).all(), (seed, a, k)
                assert (state[beside, k] != int(SignalState.STOP)).any(), (seed, a, k)
    assert starts >= 3, starts


@pytest.mark.parametrize("layout", SIGNALISED)
def test_walk_windows_follow_the_perpendicular_green(layout: str) -> None:
    net = LAYOUT_BUILDERS[layout]()
    plan = net.signals
    times = np.arange(0.0, plan.cycle_s, 0.1)
    left = walk_time_left(net, times, 0.0)
    states = signal_states(plan, times, 0.0)
    for c, x in enumerate(net.crossings):
        arms = np.asarray([net.lane(int(lid)).approach for lid in plan.lane_ids])
        beside = states[(arms - x.arm) % 2 == 1]
        through = states[(arms - x.arm) % 2 == 0]
        open_ = left[c] > 0
        assert open_.any() and not open_.all()
        assert (beside[:, open_] == int(SignalState.GO)).any(axis=0).all()
        assert (through[:, open_] == int(SignalState.STOP)).all()
    assert np.isinf(walk_time_left(build_t_junction(), times, 0.0)).all()


@pytest.mark.parametrize("layout", URBAN)
def test_no_vehicle_drives_through_a_pedestrian_or_cyclist(layout: str) -> None:
    """Oriented-box overlap (the simulator's own collision code) of every vehicle or cyclist
    with every pedestrian, and of every vehicle with every cyclist, at every valid step; and
    vehicles do meet crossing pedestrians (some stand still within 10 m of one on a
    crosswalk), so the check is not vacuous."""
    import torch

    from tbsim_env.sim.collision import pairwise_overlap

    waits = 0
    for seed in range(8):
        sc = scene(layout, seed)
        t = sc.tracks
        kind = t.object_type
        pose = torch.as_tensor(
            np.concatenate([t.xyz[..., :2], t.heading[..., None]], axis=-1), dtype=torch.float64
        ).transpose(0, 1)  # [T, A, 3]
        size = torch.as_tensor(t.size[..., :2], dtype=torch.float64).transpose(0, 1)
        hit = pairwise_overlap(pose, size, pose, size).numpy()  # [T, A, A]
        both = (t.valid[:, None, :] & t.valid[None, :, :]).transpose(2, 0, 1)
        veh = kind == int(ObjectType.VEHICLE)
        cyc = kind == int(ObjectType.CYCLIST)
        ped = kind == int(ObjectType.PEDESTRIAN)
        pairs = ((veh | cyc)[:, None] & ped[None, :]) | (veh[:, None] & cyc[None, :])
        bad = hit & both & pairs[None]
        assert not bad.any(), (seed, np.argwhere(bad)[:3])
        speed = np.linalg.norm(t.velocity, axis=-1)
        for a in np.flatnonzero(ped):
            on = on_crosswalk(sc, a).any(axis=1)
            d = np.linalg.norm(t.xyz[:, :, :2] - t.xyz[a, None, :, :2], axis=-1)
            near = (veh | cyc)[:, None] & t.valid & (d < 10.0) & (speed < 0.1) & on[None, :]
            waits += int(near.any())
    assert waits >= 4, waits


# ----------------------------------------------------------------------------- permissive turns


def test_permissive_intersection_runs_opposite_arms_together() -> None:
    """Two phases: opposite arms share every state, perpendicular arms never go together;
    left turns rank below the oncoming through and right turns."""
    net = LAYOUT_BUILDERS["permissive_intersection"]()
    plan = net.signals
    states = signal_states(plan, np.arange(0.0, plan.cycle_s, 0.1), 0.0)
    arms = np.asarray([net.lane(int(lid)).approach for lid in plan.lane_ids])
    by_arm = {a: states[arms == a] for a in range(4)}
    for a in range(4):
        assert (by_arm[a] == by_arm[a][:1]).all()  # both lanes of an arm together
    np.testing.assert_array_equal(by_arm[0], by_arm[2])
    np.testing.assert_array_equal(by_arm[1], by_arm[3])
    go = {a: by_arm[a][0] != int(SignalState.STOP) for a in range(4)}
    assert not (go[0] & go[1]).any() and go[0].any() and go[1].any()
    conflict = connector_conflicts(net)
    ranks = net.junction.rank
    lefts = [c for c, k in ranks.items() if k == 1]
    assert len(lefts) == 4 and len(ranks) == 16  # 2 through, 1 left, 1 right per arm
    for c in lefts:  # each left turn crosses rank-0 movements of the oncoming arm
        arm = net.lane(c).approach
        crossed = [o for o, k in ranks.items() if conflict[c, o] and k == 0]
        assert any(net.lane(o).approach == (arm + 2) % 4 for o in crossed)


def standing_at_green(sc: Scenario) -> int:
    """Steps at which a vehicle stands (< 0.3 m/s) first in line at a green light, its front
    bumper within 4 m of the stop point, with another vehicle standing behind it in the same
    lane (within 20 m of the line), summed over the signalised lanes."""
    t = sc.tracks
    veh = np.flatnonzero(t.object_type == int(ObjectType.VEHICLE))
    standing = np.linalg.norm(t.velocity[veh, :, :2], axis=-1) < 0.3
    count = 0
    for lid, state, stop in zip(sc.signals.lane_id, sc.signals.state, sc.signals.stop_point):
        lon, on = on_signalled_lane(sc, veh, lid, stop)
        on &= standing
        first = (on & (lon > -4.0) & (lon <= 0.5)).any(axis=0)
        behind = (on & (lon > -20.0) & (lon <= -4.0)).any(axis=0)
        count += int((first & behind & (state == int(SignalState.GO))).sum())
    return count


def test_permissive_left_turns_hold_queues_at_a_green_light() -> None:
    """The layout's purpose: a queue standing behind a vehicle that waits at a green light
    (for a gap in oncoming traffic or for a crossing pedestrian), the situation the shipped
    NPC mishandles (docs/MODEL_CARD.md). With the calibrated drivers (faster, shorter
    headways), over seeds 0-19: 244 such steps in 8 scenes, against 30 in 11 scenes of the
    split-phase intersection, where only pedestrians cause it (before the calibration, over
    seeds 0-9: 278 steps in 7 scenes against 26 in 4)."""
    seeds = range(20)
    split = [standing_at_green(scene("intersection", s)) for s in seeds]
    permissive = [standing_at_green(scene("permissive_intersection", s)) for s in seeds]
    assert sum(permissive) >= 5 * max(sum(split), 1), (permissive, split)
    assert sum(c > 0 for c in permissive) >= 6, permissive
    # Not more: vehicles that their light holds take no part in the priority rules. When the
    # cross street's queue at its red light counted as approaching traffic, left turns
    # waited for it through their green (711 steps on seeds 0-9, before the calibration).
    assert sum(permissive) <= 400, permissive
