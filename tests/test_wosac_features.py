"""WOSAC features on hand-computed cases: kinematics, boxes, TTC, road edges, red lights."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tbsim_env.core.constants import LaneType, MapFeatureType, RoadEdgeType, SignalState
from tbsim_env.data.scenario import RoadMap
from tbsim_env.metrics.wosac.config import HISTOGRAMS
from tbsim_env.metrics.wosac.estimators import histogram_bin_index
from tbsim_env.metrics.wosac.features import compute_metric_features
from tbsim_env.metrics.wosac.features_interactive import (
    distance_to_nearest_object,
    rectangle_signed_distance,
    time_to_collision,
)
from tbsim_env.metrics.wosac.features_kinematic import (
    acceleration_validity,
    kinematic_features,
    speed_validity,
)
from tbsim_env.metrics.wosac.features_map import (
    MapFeatureError,
    distance_to_road_edge,
    road_edge_segments,
    traffic_light_map,
    traffic_light_violation,
)
from tbsim_env.metrics.wosac.segment_search import build_segment_index, nearest_segment
from tbsim_env.metrics.wosac.synthetic import noisy_rollouts, synthetic_scenario
from tbsim_env.metrics.wosac.trajectories import (
    ObjectTrajectories,
    log_trajectories,
    select_objects,
    simulated_trajectories,
)

pytestmark = [pytest.mark.usefixtures("torch_one_thread"), pytest.mark.float_sensitive]


def make_traj(
    x, y, heading=None, length=4.0, width=2.0, valid=None, z=None, height=1.5, num_eval=1
):
    """ObjectTrajectories from [R, N, T] arrays (or [N, T], R = 1); scalar sizes broadcast."""
    x = torch.as_tensor(np.asarray(x, np.float32))
    if x.dim() == 2:
        x = x.unsqueeze(0)
    shape = x.shape

    def full(v, fill=0.0):
        if v is None:
            return torch.full(shape, fill)
        return torch.as_tensor(np.asarray(v, np.float32)).reshape(shape)

    def per_object(v):
        return torch.as_tensor(np.broadcast_to(np.asarray(v, np.float32), (shape[1],)).copy())

    return ObjectTrajectories(
        x=x,
        y=full(y),
        z=full(z),
        heading=full(heading),
        valid=torch.ones(shape, dtype=torch.bool) if valid is None else full(valid).bool(),
        length=per_object(length),
        width=per_object(width),
        height=per_object(height),
        object_type=torch.ones(shape[1], dtype=torch.int64),
        num_eval=num_eval,
    )


# --------------------------------------------------------------------------- kinematics


def test_speed_and_acceleration_central_differences_with_nan_ends():
    t = torch.arange(6, dtype=torch.float32)
    x = 3.0 * t  # 30 m/s constant
    kin = kinematic_features(x, torch.zeros(6), torch.zeros(6), torch.zeros(6))
    assert torch.isnan(kin.linear_speed[[0, 5]]).all()
    assert kin.linear_speed[1:5].tolist() == pytest.approx([30.0] * 4, rel=1e-5)
    assert torch.isnan(kin.linear_acceleration[[0, 1, 4, 5]]).all()
    assert kin.linear_acceleration[2:4].tolist() == pytest.approx([0.0, 0.0], abs=1e-3)
    # Speed is the 3-D norm: a vertical climb counts.
    kin = kinematic_features(torch.zeros(6), torch.zeros(6), t, torch.zeros(6))
    assert kin.linear_speed[2].item() == pytest.approx(10.0, rel=1e-5)


def test_angular_speed_wraps_heading_across_pi():
    raw = 3.0 + 0.1 * torch.arange(6, dtype=torch.float32)  # crosses pi at step 2
    wrapped = torch.remainder(raw + math.pi, 2 * math.pi) - math.pi
    assert wrapped[2] < 0 < wrapped[1]
    for heading in (raw, wrapped, raw + 4 * math.pi):
        kin = kinematic_features(torch.zeros(6), torch.zeros(6), torch.zeros(6), heading)
        assert kin.angular_speed[1:5].tolist() == pytest.approx([1.0] * 4, abs=1e-3)
        assert kin.angular_acceleration[2:4].tolist() == pytest.approx([0.0] * 2, abs=0.1)
        assert torch.isnan(kin.angular_speed[[0, 5]]).all()
        assert torch.isnan(kin.angular_acceleration[[0, 1, 4, 5]]).all()


def test_scoring_masks():
    v = torch.tensor([True, True, True, False, True, True, True, True])
    assert speed_validity(v).tolist() == [False, True, False, True, False, True, True, False]
    # accel_valid_k = V[k-2] & V[k] & V[k+2], never at k in {0, 1, T-2, T-1}.
    want = [False, False, True, False, True, False, False, False]
    assert acceleration_validity(v).tolist() == want


def test_nan_edge_steps_reach_the_last_histogram_bin():
    scenario = synthetic_scenario(num_agents=6, seed=1)
    objects = select_objects(scenario)
    log = log_trajectories(scenario, objects)
    sim = simulated_trajectories(log, objects, noisy_rollouts(scenario, 4), scenario.current_index)
    edges = road_edge_segments(scenario)
    feat = compute_metric_features(sim, edges, traffic_light_map(scenario), 11)
    assert feat.linear_speed.shape == (4, objects.num_eval, 80)
    assert torch.isnan(feat.linear_speed[..., 79]).all()
    assert not torch.isnan(feat.linear_speed[..., :79]).any()
    assert torch.isnan(feat.angular_acceleration[..., 78:]).all()
    assert not torch.isnan(feat.angular_acceleration[..., :78]).any()
    bins = histogram_bin_index(feat.linear_speed[..., 79], HISTOGRAMS.linear_speed)
    assert (bins == HISTOGRAMS.linear_speed.num_bins - 1).all()


# --------------------------------------------------------------------------- boxes


def test_rectangle_signed_distance_hand_cases():
    half = torch.tensor([2.0, 1.0])
    zero = torch.tensor(0.0)

    def sd(dx, dy, hb=0.0):
        return rectangle_signed_distance(
            torch.zeros(2), zero, half, torch.tensor([dx, dy]), torch.tensor(hb), half
        ).item()

    assert sd(3.0, 0.0) == pytest.approx(-1.0, abs=1e-5)  # 1 m overlap along x
    assert sd(0.0, 1.5) == pytest.approx(-0.5, abs=1e-5)
    assert sd(6.0, 0.0) == pytest.approx(2.0, abs=1e-5)
    assert sd(6.0, 4.0) == pytest.approx(math.sqrt(8.0), abs=1e-5)  # corner to corner
    # Rotated by 90 degrees: b spans x in [dx - 1, dx + 1].
    assert sd(5.0, 0.0, math.pi / 2) == pytest.approx(2.0, abs=1e-5)


def test_overlapping_rounded_boxes_collide_and_apart_ones_do_not():
    # L=4, W=2: corner radius 0.7, cores 2.6 x 0.6 (docs/metrics.md, "Object shape").
    x = [[0.0], [3.0], [100.0]]
    traj = make_traj(x, np.zeros((3, 1)), num_eval=2)
    dist = distance_to_nearest_object(traj)
    assert dist.shape == (1, 2, 1)
    assert dist[0, :, 0].tolist() == pytest.approx([-1.0, -1.0], abs=1e-4)
    assert (dist < 0).all()
    # Apart along the sides: like sharp boxes; diagonally: the rounded corners add distance.
    side = distance_to_nearest_object(make_traj([[0.0], [10.0]], [[0.0], [0.0]]))
    assert side.item() == pytest.approx(6.0, abs=1e-4)
    diag = distance_to_nearest_object(make_traj([[0.0], [6.0]], [[0.0], [4.0]]))
    assert diag.item() == pytest.approx(math.sqrt(2) * 3.4 - 1.4, abs=1e-4)


def test_nearest_object_skips_invalid_partners_and_self():
    traj = make_traj([[0.0], [3.0]], [[0.0], [0.0]], valid=[[1], [0]])
    assert distance_to_nearest_object(traj).item() == 1e10
    alone = make_traj([[0.0]], [[0.0]])
    assert distance_to_nearest_object(alone).item() == 1e10


def test_nearest_object_pruning_matches_brute_force():
    gen = torch.Generator().manual_seed(0)
    r, n, t, e = 3, 12, 5, 4
    x = torch.rand(r, n, t, generator=gen) * 30
    y = torch.rand(r, n, t, generator=gen) * 30
    h = (torch.rand(r, n, t, generator=gen) - 0.5) * 8
    length = 2 + torch.rand(n, generator=gen) * 4
    width = 1 + torch.rand(n, generator=gen) * 1.5
    valid = torch.rand(r, n, t, generator=gen) > 0.2
    traj = make_traj(x.numpy(), y.numpy(), h.numpy(), length.numpy(), width.numpy(), num_eval=e)
    traj = ObjectTrajectories(**{**traj.__dict__, "valid": valid})
    got = distance_to_nearest_object(traj)
    rad = 0.35 * torch.minimum(length, width)
    half = torch.stack([length / 2 - rad, width / 2 - rad], -1)
    c = torch.stack([x, y], -1)
    sd = (
        rectangle_signed_distance(
            c[:, :e, None],
            h[:, :e, None],
            half[:e, None, None],
            c[:, None],
            h[:, None],
            half[None, :, None],
        )
        - rad[:e, None, None]
        - rad[None, :, None]
    )
    ok = valid[:, :e, None] & valid[:, None] & ~torch.eye(e, n, dtype=torch.bool)[None, :, :, None]
    want = torch.where(ok, sd, 1e10).amin(2)
    torch.testing.assert_close(got, want, atol=1e-4, rtol=0)


# --------------------------------------------------------------------------- TTC


def _ttc(leader_y=0.0, leader_heading=0.0, leader_speed=5.0, ego_speed=10.0):
    t = np.arange(3) * 0.1
    x = [ego_speed * t, 20.0 + leader_speed * t]
    y = [np.zeros(3), np.full(3, leader_y)]
    h = [np.zeros(3), np.full(3, leader_heading)]
    return time_to_collision(make_traj(x, y, h))[0, 0, 1].item()


def test_time_to_collision_hand_cases():
    # Step 1: ego at x = 1.0, leader at 20.5: long = 19.5 - 2 - 2 = 15.5 m, closing at 5 m/s.
    assert _ttc() == pytest.approx(3.1, abs=1e-4)
    assert _ttc(leader_speed=6.0) == pytest.approx(15.6 / 4.0, abs=1e-4)
    assert _ttc(leader_speed=7.0) == 5.0  # 15.7 / 3 > 5 s: saturated
    assert _ttc(leader_speed=12.0) == 5.0  # leader faster: no collision course
    assert _ttc(leader_y=1.5) == pytest.approx(3.1, abs=1e-4)  # lat = -0.5, aligned: followed
    assert _ttc(leader_y=3.0) == 5.0  # no lateral overlap
    # Rotated leader (0.3 rad > 10 deg): reach 2 cos + 1 sin along, 2 sin + 1 cos across.
    c, s = math.cos(0.3), math.sin(0.3)
    assert _ttc(leader_y=1.0, leader_heading=0.3) == pytest.approx(
        (19.5 - 2.0 - (2 * c + s)) / 5.0, abs=1e-4
    )
    assert _ttc(leader_y=2.3, leader_heading=0.3) == 5.0  # -0.5 < lat < 0 at > 10 deg
    assert _ttc(leader_heading=2 * math.pi) == 5.0  # raw |dyaw| = 2 pi: treated as misaligned
    assert _ttc(leader_heading=math.pi) == 5.0  # oncoming


def test_time_to_collision_nan_speed_gives_max():
    traj = make_traj([[0.0, 1.0], [20.0, 20.5]], [[0.0, 0.0], [0.0, 0.0]])
    ttc = time_to_collision(traj)
    assert ttc.shape == (1, 1, 2)
    assert (ttc == 5.0).all()  # two steps only: every central-difference speed is NaN


# --------------------------------------------------------------------------- road edges


def _map_with_edges(polylines, extra_lanes=()):
    lines = [np.asarray(p, np.float64) for p in polylines] + [np.asarray(p) for p in extra_lanes]
    f = len(lines)
    kinds = [int(MapFeatureType.ROAD_EDGE)] * len(polylines) + [int(MapFeatureType.LANE)] * len(
        extra_lanes
    )
    sub = [int(RoadEdgeType.BOUNDARY)] * len(polylines) + [int(LaneType.SURFACE_STREET)] * len(
        extra_lanes
    )
    return RoadMap.from_polylines(np.arange(1, f + 1), kinds, sub, lines)


def _edges(*polylines):
    scenario = synthetic_scenario(num_agents=2).replace(road_map=_map_with_edges(polylines))
    return road_edge_segments(scenario)


def _line(x0, y0, x1, y1, z=0.0, n=21):
    s = np.linspace(0.0, 1.0, n)[:, None]
    return np.concatenate([(1 - s) * [x0, y0] + s * [x1, y1], np.full((n, 1), z)], 1)


def test_box_just_off_and_just_on_the_road_edge():
    edges = _edges(_line(-50, 0, 50, 0))  # road on the left: y > 0
    # L=4, W=2 box at heading 0: corners at y = centre +- 1.
    d = distance_to_road_edge(make_traj([[0.0, 0.0, 0.0]], [[0.9, 1.1, 5.0]]), edges)
    assert d[0, 0].tolist() == pytest.approx([0.1, -0.1, -4.0], abs=1e-4)
    assert bool(d[0, 0, 0] > 0) and not bool(d[0, 0, 1] > 0)
    # Invalid object: -1e10.
    d = distance_to_road_edge(make_traj([[0.0]], [[0.9]], valid=[[0]]), edges)
    assert d.item() == -1e10


def test_road_edge_uses_bottom_corners_and_z_stretch_at_overpasses():
    # Lower edge at z = 0 along y = 0; an overpass edge 8 m up along y = 1.5, pointing -x.
    edges = _edges(_line(-50, 0, 50, 0), _line(50, 1.5, -50, 1.5, z=8.0))
    traj = make_traj([[0.0]], [[2.2]], z=[[0.75]], height=1.5)  # bottom at z = 0
    d = distance_to_road_edge(traj, edges)
    # With z stretched, every corner picks the ground edge: corners at y = 1.2 and 3.2 are
    # on-road by 1.2 and 3.2, the max is -1.2. A 2-D search would pick the overpass for both and
    # call the y = 3.2 corners off-road (+1.7).
    assert d.item() == pytest.approx(-1.2, abs=1e-4)


def test_road_edge_junction_sign_rules():
    # Hairpin left turn (convex junction): the point beyond the tip is off-road.
    convex = _edges([[0, 0, 0], [10, 0, 0], [0, 1, 0]])
    # Hairpin right turn (concave junction): the same kind of point is on-road.
    concave = _edges([[0, 0, 0], [10, 0, 0], [0, -1, 0]])
    from tbsim_env.metrics.wosac.features_map import signed_distance_to_road_edge_points

    q = torch.tensor([[[12.0, 0.2, 0.0]]])
    ok = torch.ones(1, 1, dtype=torch.bool)
    dist_tip = math.hypot(2.0, 0.2)
    assert signed_distance_to_road_edge_points(q, ok, convex).item() == pytest.approx(
        dist_tip, abs=1e-4
    )
    q = torch.tensor([[[12.0, -0.2, 0.0]]])
    assert signed_distance_to_road_edge_points(q, ok, concave).item() == pytest.approx(
        -dist_tip, abs=1e-4
    )


def test_cyclic_road_edges_wrap_only_at_the_longest_length():
    square = [[0, 0, 0], [10, 0, 0], [10, 10, 0], [0, 10, 0], [0, 0.5, 0]]  # cyclic, 5 points
    small = [[20, 0, 0], [21, 0, 0], [21, 1, 0], [20.3, 0, 0]]  # cyclic, 4 points
    edges = _edges(square, small)
    assert edges.prev[:4].tolist() == [3, 0, 1, 2] and edges.next[:4].tolist() == [1, 2, 3, 0]
    assert edges.prev[4:].tolist() == [4, 4, 5] and edges.next[4:].tolist() == [5, 6, 6]


def test_no_road_edge_is_an_error():
    scenario = synthetic_scenario(num_agents=2)
    scenario = scenario.replace(road_map=_map_with_edges([], extra_lanes=[_line(0, 0, 1, 0)]))
    with pytest.raises(MapFeatureError, match="no road edge"):
        road_edge_segments(scenario)


@pytest.mark.parametrize("pairs_per_run", [1 << 22, 500])
def test_nearest_segment_search_matches_brute_force(monkeypatch, pairs_per_run):
    from tbsim_env.metrics.wosac import segment_search

    monkeypatch.setattr(segment_search, "_PAIRS_PER_RUN", pairs_per_run)
    gen = torch.Generator().manual_seed(3)
    pts = torch.cumsum(torch.rand(400, 3, generator=gen) - 0.5, 0) * torch.tensor([3.0, 3.0, 0.5])
    start, end = pts[:-1].contiguous(), pts[1:].contiguous()
    index = build_segment_index(start, end)
    centres = torch.rand(30, 1, 3, generator=gen) * 40 - 20
    q = centres + torch.randn(30, 16, 3, generator=gen) * 2.0
    scale = torch.tensor([1.0, 1.0, 3.0])
    got = nearest_segment(q, torch.ones(30, 16, dtype=torch.bool), index, (1.0, 1.0, 3.0))
    ab = end - start
    aq = q[..., None, :] - start
    len2 = (ab[:, :2] ** 2).sum(-1)
    t = ((aq[..., :2] * ab[:, :2]).sum(-1) / len2).clamp(0, 1)
    d = (((aq - t[..., None] * ab) * scale) ** 2).sum(-1)
    want = d.argmin(-1)
    same = (got == want) | torch.isclose(d.gather(-1, got[..., None])[..., 0], d.amin(-1))
    assert same.all()


# --------------------------------------------------------------------------- red lights


@pytest.mark.parametrize("lane_pairs", [1 << 22, 1])
def test_red_light_violation_needs_lane_red_and_crossing(monkeypatch, lane_pairs):
    from tbsim_env.metrics.wosac import features_map

    monkeypatch.setattr(features_map, "_LANE_PAIRS_PER_CHUNK", lane_pairs)
    lanes = [_line(-50, 0, 100, 0), _line(-50, 4, 100, 4)]
    road = _map_with_edges([_line(-50, -2, 100, -2)], extra_lanes=lanes)
    scenario = synthetic_scenario(num_agents=2, stop_x=10.0).replace(road_map=road)
    signals = scenario.signals
    signals = type(signals)(
        lane_id=np.array([2], np.int64),  # the lane along y = 0 (feature id 2)
        state=np.full((1, 4), int(SignalState.STOP), np.int8),
        valid=np.ones((1, 4), bool),
        stop_point=np.array([[10.0, 0.0, 0.0]]),
    )
    tl = traffic_light_map(scenario.replace(signals=signals))
    x = [[8.0, 9.5, 10.5, 12.0], [8.0, 9.5, 10.5, 12.0]]
    on_lane = make_traj(x, [[0.0] * 4, [4.0] * 4], num_eval=2)
    v = traffic_light_violation(on_lane, tl)
    assert v[0, 0].tolist() == [False, False, True, False]
    assert not v[0, 1].any()  # crosses the stop line, but on the other lane
    green = type(signals)(
        lane_id=signals.lane_id,
        state=np.full((1, 4), int(SignalState.GO), np.int8),
        valid=signals.valid,
        stop_point=signals.stop_point,
    )
    tl_green = traffic_light_map(scenario.replace(signals=green))
    assert not traffic_light_violation(on_lane, tl_green).any()
