"""Parked vehicles and tracker jitter in generated logs (tbsim_env.data.generator.recording)."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest

from tbsim_env.core.constants import MapFeatureType, ObjectType
from tbsim_env.data.generator import LAYOUTS, frame_offset, generate_scenario
from tbsim_env.data.generator.recording import (
    JITTER_FULL_SPEED,
    RECORDED,
    ROAD_CLEARANCE_M,
    Recording,
)
from tbsim_env.data.scenario import Scenario, wrap_angle_np
from tests.test_generator import box_corners, boxes_overlap, signed_edge_distance

NOTHING = Recording(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
SIDEWALK_LAYOUTS = tuple(lay for lay in LAYOUTS if lay != "merge")


@functools.cache
def pair(layout: str, seed: int, rec: Recording = RECORDED) -> tuple[Scenario, Scenario]:
    """(exact scene, recorded scene), both moved back into the layout's frame."""
    dx, dy = frame_offset(layout, seed)
    exact = generate_scenario(layout, seed).transformed(shift=(-dx, -dy))
    recorded = generate_scenario(layout, seed, recording=rec).transformed(shift=(-dx, -dy))
    return exact, recorded


def parked_rows(exact: Scenario, recorded: Scenario) -> slice:
    """Rows of the parked vehicles: inserted before the SDC."""
    return slice(exact.tracks.num_tracks - 1, recorded.tracks.num_tracks - 1)


@pytest.mark.parametrize("layout", LAYOUTS)
def test_recording_keeps_the_driven_traffic_and_the_sdc_last(layout: str) -> None:
    exact, rec = pair(layout, 5)
    a, b = exact.tracks, rec.tracks
    n = a.num_tracks
    keep = np.r_[0 : n - 1, b.num_tracks - 1]
    assert rec.sdc_index == b.num_tracks - 1
    np.testing.assert_array_equal(rec.tracks_to_predict, exact.tracks_to_predict)
    np.testing.assert_array_equal(b.id[keep], a.id)
    np.testing.assert_array_equal(b.valid[keep], a.valid)
    assert np.abs(b.velocity[keep] - a.velocity).max() < 3.0
    assert len(set(b.id.tolist())) == b.num_tracks
    # Jitter only: centimetres, and exact where a vehicle stands.
    moved = np.abs(b.xyz[keep] - a.xyz)
    assert moved.max() < 0.5
    vehicle = (a.object_type != int(ObjectType.PEDESTRIAN))[:, None]
    standing = vehicle & a.valid & (np.linalg.norm(a.velocity, axis=-1) == 0.0)
    assert (moved[standing] == 0.0).all()
    assert (b.velocity[keep][standing] == 0.0).all()
    rec.validate()


def test_no_recording_is_the_exact_log_and_same_seed_same_scene() -> None:
    exact, none = pair("intersection", 2, NOTHING)
    for f in ("xyz", "heading", "velocity", "size", "valid", "id"):
        np.testing.assert_array_equal(getattr(none.tracks, f), getattr(exact.tracks, f))
    again = generate_scenario("intersection", 2, recording=RECORDED)
    first = generate_scenario("intersection", 2, recording=RECORDED)
    for f in ("xyz", "heading", "size", "valid", "id"):
        np.testing.assert_array_equal(getattr(again.tracks, f), getattr(first.tracks, f))


@pytest.mark.parametrize("layout", SIDEWALK_LAYOUTS)
def test_parked_vehicles_stand_still_off_the_road_and_overlap_nothing(layout: str) -> None:
    exact, rec = pair(layout, 7, dataclasses.replace(RECORDED, parked_occupancy=1.0))
    t = rec.tracks
    rows = parked_rows(exact, rec)
    k = rows.stop - rows.start
    assert k >= 10, f"{layout}: only {k} parked vehicles with every slot taken"
    assert (t.object_type[rows] == int(ObjectType.VEHICLE)).all()
    assert t.valid[rows].all()
    assert (t.xyz[rows] == t.xyz[rows, :1]).all() and (t.heading[rows] == t.heading[rows, :1]).all()
    assert (t.velocity[rows] == 0.0).all()
    # Off the road, clear of every road edge.
    rm = rec.road_map
    edges = [rm.polylines[i][:, :2] for i in rm.indices_of(MapFeatureType.ROAD_EDGE)]
    corners = box_corners(t.xyz[rows, 0, :2], t.heading[rows, 0], t.size[rows, 0])
    d = signed_edge_distance(corners.reshape(-1, 2), edges)
    assert (d > ROAD_CLEARANCE_M - 1e-6).all(), d.min()
    # No overlap with any other object at any step.
    every = box_corners(t.xyz[..., :2], t.heading, t.size)
    for r in range(rows.start, rows.stop):
        hit = boxes_overlap(np.broadcast_to(every[r], every.shape), every) & t.valid & t.valid[r]
        hit[r] = False
        assert not hit.any(), (layout, r, np.flatnonzero(hit.any(1)))


def test_freeway_has_no_parked_vehicles() -> None:
    exact, rec = pair("merge", 3, dataclasses.replace(RECORDED, parked_occupancy=1.0))
    assert rec.tracks.num_tracks == exact.tracks.num_tracks


def test_occupancy_sets_the_share_of_slots_taken() -> None:
    counts = {}
    for occ in (0.0, 0.3, 1.0):
        exact, rec = pair("intersection", 4, dataclasses.replace(NOTHING, parked_occupancy=occ))
        counts[occ] = rec.tracks.num_tracks - exact.tracks.num_tracks
    assert counts[0.0] == 0
    assert 0.15 * counts[1.0] < counts[0.3] < 0.45 * counts[1.0], counts


def test_jitter_is_white_along_the_heading_and_as_large_as_asked() -> None:
    """Only along-heading jitter asked: the lateral offset and the heading stay exact, the
    along offsets of moving vehicles have the asked scale (times the mean log-normal factor)
    and no correlation from one step to the next."""
    sigma = 0.02
    along, lateral, ratio = [], [], []
    for seed in range(4):
        exact, rec = pair("intersection", seed, dataclasses.replace(NOTHING, jitter_along=sigma))
        a, b = exact.tracks, rec.tracks
        n = a.num_tracks
        vehicle = a.object_type != int(ObjectType.PEDESTRIAN)
        fast = (
            vehicle[:, None] & a.valid & (np.linalg.norm(a.velocity, axis=-1) > JITTER_FULL_SPEED)
        )
        d = (b.xyz - a.xyz)[..., :2]
        h = a.heading.astype(np.float64)
        u = d[..., 0] * np.cos(h) + d[..., 1] * np.sin(h)
        v = -d[..., 0] * np.sin(h) + d[..., 1] * np.cos(h)
        np.testing.assert_array_equal(b.heading[:n], a.heading)
        along.append(u[fast])
        lateral.append(v[fast])
        both = fast[:, 1:] & fast[:, :-1]
        ratio.append(np.stack([u[:, 1:][both], u[:, :-1][both]]))
    u, v, pairs = np.concatenate(along), np.concatenate(lateral), np.concatenate(ratio, axis=1)
    assert np.abs(v).max() < 1e-4 * max(1.0, np.abs(u).max())
    # E[exp(N(0, 0.7))^2] = exp(0.98): the pooled std is sigma * exp(0.49) = 1.63 sigma.
    assert 1.2 * sigma < u.std() < 2.2 * sigma, u.std()
    assert abs(np.corrcoef(pairs)[0, 1]) < 0.1


def test_standing_pedestrians_jitter_in_heading_walking_ones_less() -> None:
    exact, rec = pair(
        "intersection", 1, dataclasses.replace(NOTHING, ped_jitter_heading=0.3, ped_jitter=0.01)
    )
    a, b = exact.tracks, rec.tracks
    ped = (a.object_type == int(ObjectType.PEDESTRIAN))[:, None] & a.valid
    speed = np.linalg.norm(a.velocity, axis=-1)
    dh = np.abs(wrap_angle_np(b.heading[: a.num_tracks] - a.heading))
    standing, walking = ped & (speed == 0.0), ped & (speed >= JITTER_FULL_SPEED)
    assert standing.any() and walking.any()
    assert np.median(dh[standing]) > 0.1 and (dh[walking] == 0.0).all()
    assert (dh[~ped & a.valid] == 0.0).all()
    moved = np.linalg.norm(b.xyz[: a.num_tracks, :, :2] - a.xyz[..., :2], axis=-1)
    assert (moved[standing] > 0.0).all()


@pytest.mark.parametrize("field", [f.name for f in dataclasses.fields(Recording)])
def test_recording_rejects_negative_values(field: str) -> None:
    with pytest.raises(ValueError, match=field):
        dataclasses.replace(RECORDED, **{field: -0.1})


def test_recording_rejects_occupancy_above_one() -> None:
    with pytest.raises(ValueError, match="parked_occupancy"):
        dataclasses.replace(RECORDED, parked_occupancy=1.5)


def test_token_cache_builds_recorded_scenes(tmp_path) -> None:
    from tbsim_env.core.config import TokenConfig
    from tbsim_env.data.cache import TokenCache, build_cache, parse_generated
    from tbsim_env.data.preprocess import preprocess_scenario

    assert parse_generated("generated:merge:3-4") == [("merge", 3, False), ("merge", 4, False)]
    assert parse_generated("generated-recorded:t_junction:2-2") == [("t_junction", 2, True)]
    with pytest.raises(ValueError, match="bad generator source"):
        parse_generated("generated-noisy:merge:0-1")
    build_cache(["generated-recorded:t_junction:2-2"], tmp_path, workers=1, progress=False)
    got = TokenCache(tmp_path)[0]
    cfg = TokenConfig(training=True)
    ref = preprocess_scenario(generate_scenario("t_junction", 2, recording=RECORDED), cfg)
    plain = preprocess_scenario(generate_scenario("t_junction", 2), cfg)
    np.testing.assert_array_equal(got.agent_pos, ref.agent_pos)
    assert got.agent_pos.shape != plain.agent_pos.shape or not np.array_equal(
        got.agent_pos, plain.agent_pos
    )


def test_velocity_jitter_is_along_the_heading_of_moving_vehicles() -> None:
    sigma = 0.2
    exact, rec = pair("t_junction", 3, dataclasses.replace(NOTHING, speed_jitter=sigma))
    a, b = exact.tracks, rec.tracks
    np.testing.assert_array_equal(b.xyz, a.xyz)
    vehicle = (a.object_type != int(ObjectType.PEDESTRIAN))[:, None] & a.valid
    fast = vehicle & (np.linalg.norm(a.velocity, axis=-1) > JITTER_FULL_SPEED)
    dv = (b.velocity - a.velocity).astype(np.float64)
    h = a.heading.astype(np.float64)
    along = dv[..., 0] * np.cos(h) + dv[..., 1] * np.sin(h)
    across = -dv[..., 0] * np.sin(h) + dv[..., 1] * np.cos(h)
    assert 1.2 * sigma < along[fast].std() < 2.2 * sigma, along[fast].std()
    assert np.abs(across[vehicle]).max() < 1e-5
    standing = vehicle & (np.linalg.norm(a.velocity, axis=-1) == 0.0)
    assert standing.any() and (dv[standing] == 0.0).all()
