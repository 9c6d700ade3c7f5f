"""Batched simulation core: log replay, spawn/departure, collisions, off-road."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tbsim_env.core import constants as C
from tbsim_env.core.boxes import box_corner_xy
from tbsim_env.data import load_scenarios
from tbsim_env.data.generator import generate_scenario
from tbsim_env.data.scenario import RoadMap
from tbsim_env.sim import core
from tbsim_env.sim.build import build_sim_state
from tbsim_env.sim.collision import collided, pairwise_overlap
from tbsim_env.sim.offroad import (
    NO_EDGE_DISTANCE,
    box_offroad_distance,
    point_segment_distance,
    signed_distance_to_edges,
)
from tbsim_env.sim.state import RoadEdges


@pytest.fixture(scope="module")
def real(womd_dir):
    return load_scenarios(womd_dir / "waymo-open-dataset" / "motion_data_one_scenario.tfrecord")[0]


def _run_log_replay(state):
    states = [state]
    zero = torch.zeros(*state.pose.shape[:2], 2)
    while int(state.step[0]) < state.log.num_steps - 1:
        state = core.step(state, zero)
        states.append(state)
    return states


def test_log_replay_reproduces_the_log_exactly(real):
    state = build_sim_state([real])
    seen_and_left = torch.zeros_like(state.valid)
    for s in _run_log_replay(state):
        t = int(s.step[0])
        log_valid = s.log.take("valid")[:, :, t]
        # Agents present now are exactly at their logged pose.
        assert torch.equal(s.pose[s.valid], s.log.take("pose")[:, :, t][s.valid])
        # Present implies logged; logged and never departed implies present.
        assert not (s.valid & ~log_valid).any()
        seen_and_left |= ~s.valid & (s.log.first_valid < t)
        assert torch.equal(s.valid, log_valid & ~seen_and_left)


def test_departed_agents_never_come_back():
    sc = generate_scenario("intersection", seed=0)
    valid = sc.tracks.valid.copy()
    k = int(np.flatnonzero(valid[:, 10:].all(axis=1))[0])
    valid[k, 20:30] = False  # a hole in the log
    sc = sc.replace(tracks=sc.tracks.__class__(**{**sc.tracks.__dict__, "valid": valid}))
    states = _run_log_replay(build_sim_state([sc]))
    present = torch.stack([s.valid[0, k] for s in states])  # steps 10..90
    assert present[:10].all() and not present[10:].any()


def test_controlled_agents_integrate_and_late_agents_spawn():
    sc = generate_scenario("merge", seed=1)
    state = build_sim_state([sc])
    state = state.replace(controlled=state.agents.mask.clone())
    late = (state.log.first_valid > 10) & state.agents.mask
    action = torch.zeros(*state.pose.shape[:2], 2)
    s1 = core.step(state, action)
    moving = state.valid[0]
    # Zero action = constant speed along the heading.
    exp = state.pose[0, moving, :2] + 0.1 * state.speed[0, moving, None] * torch.stack(
        [torch.cos(state.pose[0, moving, 2]), torch.sin(state.pose[0, moving, 2])], -1
    )
    assert torch.allclose(s1.pose[0, moving, :2], exp, atol=1e-5)
    if late.any():
        k = int(torch.nonzero(late[0])[0])
        s = state
        while int(s.step[0]) < int(state.log.first_valid[0, k]):
            s = core.step(s, action)
        assert bool(s.valid[0, k])
        assert torch.equal(s.pose[0, k], state.log.take("pose")[0, k, int(s.step[0])])


def test_actions_are_clipped_to_type_limits():
    sc = generate_scenario("intersection", seed=0)
    state = build_sim_state([sc])
    state = state.replace(controlled=state.valid.clone())
    huge = torch.full((*state.pose.shape[:2], 2), 1e3)
    s1 = core.step(state, huge)
    dv = s1.speed - state.speed
    limit = torch.tensor(C.MAX_ACCEL)[state.agents.object_type] * 0.1
    assert torch.allclose(dv[state.valid], limit[state.valid], atol=1e-4)
    veh = state.valid & (state.agents.object_type == C.ObjectType.VEHICLE)
    assert dv[veh].max().item() == pytest.approx(0.5, abs=1e-4)  # vehicles: 5 m/s^2


def _pose(x, y, yaw):
    return torch.tensor([[[x, y, yaw]]], dtype=torch.float32)


@pytest.mark.parametrize(
    "other, expected",
    [
        ((4.0, 0.0, 0.0), True),  # bumper overlap of 0.5 m
        ((4.6, 0.0, 0.0), False),  # 0.1 m gap
        ((0.0, 2.1, 0.0), False),  # side by side, 0.1 m gap
        ((0.0, 1.9, 0.0), True),
        ((3.4, 3.4, math.pi / 4), False),  # rotated, corners apart
        ((2.0, 2.0, math.pi / 4), True),
    ],
)
def test_box_overlap_hand_cases(other, expected):
    size = torch.tensor([[[4.5, 2.0]]])
    got = pairwise_overlap(_pose(0, 0, 0), size, _pose(*other), size)[0, 0, 0]
    assert bool(got) is expected


def test_collided_ignores_self_and_invalid():
    pose = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [20.0, 0.0, 0.0]]])
    size = torch.tensor([[[4.5, 2.0]] * 3])
    valid = torch.tensor([[True, True, True]])
    assert collided(pose, size, valid).tolist() == [[True, True, False]]
    assert collided(pose, size, torch.tensor([[True, False, True]])).tolist() == [
        [False, False, False]
    ]


def _edge_state(points):
    """A state whose only road edge is the polyline ``points`` (road on its left)."""
    sc = generate_scenario("merge", seed=0)
    pts = np.asarray(points, np.float64)
    pts = np.concatenate([pts, np.zeros((len(pts), 1))], axis=1)
    origin = sc.tracks.xyz[sc.sdc_index, sc.current_index, :2]
    pts[:, :2] += origin
    rm = RoadMap.from_polylines([1], [C.MapFeatureType.ROAD_EDGE], [1], [pts])
    return build_sim_state([sc.replace(road_map=rm)])


def test_signed_edge_distance_sign_convention():
    # Edge along +x: the road is on the left (y > 0).
    state = _edge_state([[-50.0, 0.0], [0.0, 0.0], [50.0, 0.0]])
    pts = torch.tensor([[[0.0, 3.0], [10.0, -2.0], [-60.0, 1.0], [60.0, -1.0]]])
    d = signed_distance_to_edges(pts, state.road_edges)[0]
    assert d[0].item() == pytest.approx(-3.0)
    assert d[1].item() == pytest.approx(2.0)
    assert d[2].item() < 0 and d[3].item() > 0


def test_signed_edge_distance_at_convex_and_concave_corners():
    # A left turn of the edge (road inside the corner, on the left): a concave junction.
    state = _edge_state([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    pts = torch.tensor([[[5.0, 5.0], [12.0, -2.0], [9.0, 1.0]]])
    d = signed_distance_to_edges(pts, state.road_edges)[0]
    assert d[0].item() < 0  # inside: on-road
    assert d[1].item() == pytest.approx(math.hypot(2, 2))  # outside beyond the corner
    assert d[2].item() < 0


def test_box_offroad_through_the_grid_is_exact(real):
    state = build_sim_state([real])
    edges = state.road_edges
    gen = torch.Generator().manual_seed(0)
    q = torch.nonzero(state.valid[0])[:, 0][None]
    pose = state.pose[:, q[0]].clone()
    size = state.agents.size[:, q[0], :2]
    for _ in range(60):
        pose = pose + torch.randn(pose.shape, generator=gen) * torch.tensor([2.0, 2.0, 0.05])
        corners = box_corner_xy(pose, size[..., 0], size[..., 1])
        fast, _ = box_offroad_distance(corners, edges)
        full = signed_distance_to_edges(torch.stack(corners, -1).reshape(1, -1, 2), edges)
        assert torch.equal(fast, full.view(1, -1, 4).amax(-1))
    # Most logged vehicles are on the road at the current step.
    veh = state.agents.object_type[0, q[0]] == C.ObjectType.VEHICLE
    corners = box_corner_xy(state.pose[:, q[0]], size[..., 0], size[..., 1])
    d, _ = box_offroad_distance(corners, edges)
    assert (d[0, veh] <= 0).float().mean() > 0.8


def test_simplified_road_edges_stay_within_tolerance(real):
    """The env's edges are the logged polylines simplified to within 2 cm: about ten times
    fewer segments, distances within the tolerance of the logged ones."""
    state = build_sim_state([real])
    logged = [
        real.road_map.polylines[k][:, :2] - state.origin[0].numpy()
        for k in real.road_map.indices_of(C.MapFeatureType.ROAD_EDGE)
    ]
    raw = RoadEdges(
        start=torch.tensor(np.concatenate([p[:-1] for p in logged]), dtype=torch.float32)[None],
        end=torch.tensor(np.concatenate([p[1:] for p in logged]), dtype=torch.float32)[None],
        valid=torch.ones(1, sum(len(p) - 1 for p in logged), dtype=torch.bool),
        prev_index=torch.zeros(1, sum(len(p) - 1 for p in logged), dtype=torch.int64),
        next_index=torch.zeros(1, sum(len(p) - 1 for p in logged), dtype=torch.int64),
    )
    assert raw.start.shape[1] > 4 * int(state.road_edges.valid.sum())
    pts = state.log.take("pose")[0, :, ::10, :2][state.log.take("valid")[0, :, ::10]][None]
    pts = pts + torch.randn(pts.shape, generator=torch.Generator().manual_seed(0))
    d_raw, _ = point_segment_distance(pts, raw)
    d_env, _ = point_segment_distance(pts, state.road_edges)
    gap = d_env.min(-1).values - d_raw.min(-1).values
    assert gap.abs().max() <= C.EDGE_SIMPLIFY_TOLERANCE + 1e-4


def test_no_road_edges_means_on_road():
    sc = generate_scenario("merge", seed=0)
    state = build_sim_state([sc.replace(road_map=RoadMap.empty())])
    d = signed_distance_to_edges(state.pose[:, :3, :2], state.road_edges)
    assert (d == NO_EDGE_DISTANCE).all()


def test_batch_of_different_scenarios_pads(real):
    gen = generate_scenario("intersection", seed=0)
    state = build_sim_state([real, gen])
    assert state.batch_size == 2
    assert state.agents.mask[1].sum() == gen.tracks.num_tracks
    s = core.step(state, torch.zeros(2, state.num_agents, 2))
    assert not (s.valid & ~state.agents.mask).any()
