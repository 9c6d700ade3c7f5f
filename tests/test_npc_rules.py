"""Inference-side rules of the TrafficBots NPC (policies/trafficbots/rules.py, InferenceConfig).

The shipped NPC holds parked vehicles; these tests pin that down so that it cannot be switched
off silently (docs/MODEL_CARD.md, "Why it leaves real roads").
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from policies.trafficbots import TrafficBotsConfig
from policies.trafficbots.batch import TokenBatch
from policies.trafficbots.config import GapKeeping, InferenceConfig
from policies.trafficbots.model import TrafficBots
from policies.trafficbots.policy import TrafficBotsPolicy
from policies.trafficbots.rules import (
    clip_history_motion,
    gap_keeping_cap,
    hold_action,
    keep_gap,
    limit_vehicle_curvature,
    parked_vehicles,
    still_agents,
)
from policies.trafficbots.wosac import load_default_model, trafficbots_rollouts
from tbsim_env.core import constants as C
from tbsim_env.core.config import EnvConfig, TerminationConfig, TokenConfig
from tbsim_env.data.generator import generate_scenario
from tbsim_env.data.preprocess import preprocess_scenario
from tbsim_env.data.scenario import Scenario
from tbsim_env.env import TrafficEnv
from tbsim_env.sim.dynamics import unicycle_step

pytestmark = [pytest.mark.usefixtures("torch_one_thread"), pytest.mark.float_sensitive]

VEH, PED = int(C.ObjectType.VEHICLE), int(C.ObjectType.PEDESTRIAN)
LANE, EDGE = int(C.MapClass.SURFACE_STREET), int(C.MapClass.ROAD_EDGE_BOUNDARY)


def _map(cls: int, yaw: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """One map piece along x from (0, 0) to (19, 0), nodes heading ``yaw``."""
    xs = torch.arange(20.0)
    pose = torch.stack([xs, torch.zeros(20), torch.full((20,), yaw)], -1)[None, None]
    return pose, torch.ones(1, 1, 20, dtype=torch.bool), torch.tensor([[cls]])


def _history(xy: list[tuple[float, float]], speed: float, agent_type: list[int]):
    """Agents standing at ``xy`` (heading 0) over an 11-step history at ``speed``."""
    n = len(xy)
    pose = torch.zeros(1, n, 11, 3)
    pose[0, :, :, :2] = torch.tensor(xy)[:, None]
    valid = torch.ones(1, n, 11, dtype=torch.bool)
    return valid, pose, torch.full((1, n, 11), speed), torch.tensor([agent_type])


def test_still_agents_sums_speed_over_valid_history_steps():
    valid = torch.ones(1, 3, 11, dtype=torch.bool)
    speed = torch.tensor([[0.3, 0.6, -0.3]])[..., None].expand(1, 3, 11)  # 0.33 / 0.66 / 0.33 m
    assert still_agents(valid, speed, 0.5).tolist() == [[True, False, True]]
    valid[0, 0, -1] = False  # not valid now: not still (nothing to hold)
    assert not bool(still_agents(valid, speed, 0.5)[0, 0])


def test_parked_vehicle_is_still_vehicle_without_aligned_lane_nearby():
    # Agents at y = 1 (on the lane), y = 6 (beside it), and a pedestrian at y = 6.
    valid, pose, speed, typ = _history([(5.0, 1.0), (5.0, 6.0), (8.0, 6.0)], 0.0, [VEH, VEH, PED])
    parked = parked_vehicles(valid, pose, speed, typ, _map(LANE, 0.0), 0.5, 3.0)
    assert parked.tolist() == [[False, True, False]]
    # A lane running the other way does not make the vehicle on it queued (docs/model.md §1.6 d).
    parked = parked_vehicles(valid, pose, speed, typ, _map(LANE, np.pi), 0.5, 3.0)
    assert parked.tolist() == [[True, True, False]]
    # A road edge is not a vehicle lane; a moving vehicle is never parked.
    assert parked_vehicles(valid, pose, speed, typ, _map(EDGE, 0.0), 0.5, 3.0)[0, 0]
    moving = parked_vehicles(valid, pose, speed + 2.0, typ, _map(EDGE, 0.0), 0.5, 3.0)
    assert not moving.any()


def test_hold_action_stops_in_one_step_keeping_the_heading():
    speed = torch.tensor([[0.3, -0.2, 9.0]])
    typ = torch.tensor([[VEH, VEH, VEH]])
    a = hold_action(speed, typ)
    assert torch.allclose(a[0, :2, 0], torch.tensor([-3.0, 2.0]))
    assert float(a[0, 2, 0]) == -5.0  # within the vehicle's limit
    assert (a[..., 1] == 0).all()
    pose = torch.tensor([[[1.0, 2.0, 0.7], [0.0, 0.0, -2.0], [0.0, 0.0, 0.0]]])
    new_pose, new_speed = unicycle_step(pose, speed, a)
    assert torch.allclose(new_speed[0, :2], torch.zeros(2), atol=1e-6)
    assert torch.allclose(new_pose[..., 2], pose[..., 2], atol=1e-6)


def test_curvature_limit_stops_vehicles_turning_on_the_spot_only():
    action = torch.tensor([[[0.0, 1.0], [0.0, 1.0], [0.0, 1.0]]])
    speed = torch.tensor([[0.0, 10.0, 0.0]])
    typ = torch.tensor([[VEH, VEH, PED]])
    out = limit_vehicle_curvature(action, speed, typ, max_curvature=0.25, slack=0.05)
    assert torch.allclose(out[0, :, 1], torch.tensor([0.05, 1.0, 1.0]))
    assert torch.equal(out[..., 0], action[..., 0])


def test_clip_history_motion_keeps_speed_and_clips_to_type_limits():
    motion = torch.tensor([[[[3.0, 12.0, -4.0]], [[1.0, -9.0, 6.0]]]])  # [1, 2, 1, 3]
    out = clip_history_motion(motion, torch.tensor([[VEH, PED]]))
    assert out[0, 0, 0].tolist() == [3.0, 5.0, -1.5]
    assert out[0, 1, 0].tolist() == [1.0, -7.0, 6.0]


def test_inference_config_defaults_are_the_shipped_rules_and_spec_turns_them_off():
    shipped = InferenceConfig()
    assert shipped.hold_parked and shipped.dest_temperature == 1.0
    assert shipped.gap_keeping == GapKeeping() and shipped.road_keeping is None
    spec = InferenceConfig.spec()
    assert not spec.hold_parked and spec.vehicle_max_curvature is None
    assert spec.gap_keeping is None and spec.road_keeping is None
    assert not spec.clip_history_motion
    with pytest.raises(ValueError):
        InferenceConfig(dest_temperature=0.0)
    with pytest.raises(ValueError):
        InferenceConfig(vehicle_max_curvature=-1.0)


def test_shipped_model_runs_the_shipped_rules():
    """Guards the fix: the default NPC holds parked vehicles (no silent switch-off)."""
    assert load_default_model().inference == InferenceConfig()
    assert TrafficBots(TrafficBotsConfig.small()).inference == InferenceConfig()


def test_rules_are_not_applied_in_training_mode():
    model = TrafficBots(TrafficBotsConfig.small())
    sc, _ = _with_parked_vehicle()
    batch = TokenBatch.from_tokens(preprocess_scenario(sc, TokenConfig()))
    gen = torch.Generator().manual_seed(0)
    model.train()
    assert model.prepare(batch, 1, gen).hold is None
    model.eval()
    hold = model.prepare(batch, 2, gen).hold
    assert hold is not None and hold.shape == (2, batch.ag_type.shape[1])


def _with_parked_vehicle() -> tuple[Scenario, int]:
    """A generated merge scene whose last non-relevant track is now a vehicle parked 6-20 m from
    any lane, inside the map's box; (scene, its track row)."""
    sc = generate_scenario("merge", 10007)
    t, rm = sc.tracks, sc.road_map
    lanes = [p[:, :2] for p, f in zip(rm.polylines, rm.feature_type, strict=True) if f == 0]
    nodes = np.concatenate(lanes)
    everything = np.concatenate([p[:, :2] for p in rm.polylines])
    lo, hi = everything.min(0) + 5.0, everything.max(0) - 5.0  # inside the map's box
    grid = np.stack(np.meshgrid(*(np.arange(a, b, 1.0) for a, b in zip(lo, hi))), -1)
    grid = grid.reshape(-1, 2)
    gap = np.array([np.min(np.hypot(*(nodes - q).T)) for q in grid[::7]])
    ok = np.flatnonzero((gap > 6.0) & (gap < 20.0))
    assert ok.size, "no spot 6-20 m from the lanes inside the map"
    spot = grid[::7][ok[0]]
    relevant = {sc.sdc_index, *sc.tracks_to_predict.tolist()}
    row = max(i for i in range(t.num_tracks) if i not in relevant)
    xyz, valid = t.xyz.copy(), t.valid.copy()
    heading, velocity = t.heading.copy(), t.velocity.copy()
    object_type, size = t.object_type.copy(), t.size.copy()
    xyz[row, :, :2], xyz[row, :, 2] = spot, xyz[sc.sdc_index, sc.current_index, 2]
    valid[row], heading[row], velocity[row] = True, 0.3, 0.0
    object_type[row], size[row] = VEH, (4.5, 1.9, 1.6)
    tracks = dataclasses.replace(
        t,
        xyz=xyz,
        valid=valid,
        heading=heading,
        velocity=velocity,
        object_type=object_type,
        size=size,
        raw_heading=None,
    )
    return dataclasses.replace(sc, tracks=tracks), row


class _EagerHead(torch.nn.Module):
    """An action head that always wants to speed up and turn left (raw (1, 1))."""

    def forward(self, x: torch.Tensor, ag_type: torch.Tensor) -> torch.Tensor:
        return torch.ones(*x.shape[:-1], 2, dtype=x.dtype, device=x.device)


def _eager_model(inference: InferenceConfig) -> TrafficBots:
    """A small model whose every agent accelerates at 3.8 m/s^2 and turns at 1.1 rad/s."""
    model = TrafficBots(TrafficBotsConfig.small(), inference)
    model.action_head = _EagerHead()
    return model.eval()


def _moved(rollouts, sc: Scenario, row: int) -> tuple[float, float]:
    """Largest distance (m) and |heading change| (rad) of track ``row`` over the rollouts."""
    j = int(np.flatnonzero(rollouts.object_id.numpy() == sc.tracks.id[row])[0])
    x0, y0 = sc.tracks.xyz[row, sc.current_index, :2]
    dist = np.hypot(rollouts.x[:, j].numpy() - x0, rollouts.y[:, j].numpy() - y0)
    turn = np.abs(rollouts.heading[:, j].numpy() - sc.tracks.heading[row, sc.current_index])
    return float(dist.max()), float(turn.max())


@pytest.mark.parametrize("model", ["shipped", "eager"])
def test_parked_vehicle_stays_put_in_wosac_rollouts(model):
    sc, row = _with_parked_vehicle()
    net = load_default_model() if model == "shipped" else _eager_model(InferenceConfig())
    r = trafficbots_rollouts(net, sc, num_rollouts=4, num_samples=4, seed=3)
    dist, turn = _moved(r, sc, row)
    assert dist < 0.01 and turn < 1e-5


def test_without_the_rule_the_eager_model_moves_the_parked_vehicle():
    """The tests above would pass vacuously if the vehicle were not driven at all."""
    sc, row = _with_parked_vehicle()
    r = trafficbots_rollouts(
        _eager_model(InferenceConfig.spec()), sc, num_rollouts=2, num_samples=2, seed=3
    )
    dist, turn = _moved(r, sc, row)
    assert dist > 5.0 and turn > 1.0


def test_parked_vehicle_stays_put_in_the_env():
    sc, row = _with_parked_vehicle()
    never = EnvConfig(termination=TerminationConfig(collision=False, goal=False))
    policy = TrafficBotsPolicy(_eager_model(InferenceConfig()), trim=True)
    env = TrafficEnv([sc], npc_policy=policy, config=never)
    env.reset(seed=0)
    a = env.agents[0]
    slot = int(np.flatnonzero(env.sim_state.agents.track_index[0].numpy() == row)[0])
    start = env.sim_state.pose[0, slot].clone()
    other = env.sim_state.pose[0].clone()
    for _ in range(40):
        env.step({a: env.expert_actions()[a]})
    end = env.sim_state.pose[0, slot]
    assert float(torch.hypot(*(end[:2] - start[:2]))) < 0.01
    assert abs(float(end[2] - start[2])) < 1e-5
    # ... while the eager network turns the agents it drives.
    turned = (env.sim_state.pose[0, :, 2] - other[:, 2]).abs()
    assert float(turned.max()) > 1.0


def _line_of_two(gap: float = 30.0, speed: float = 8.0) -> tuple[Scenario, int]:
    """A generated scene cut down to two vehicles on the SDC's heading line: the SDC standing
    still and a vehicle ``gap`` metres (centre to centre) behind it driving at ``speed``
    towards it over the whole log; (scene, the follower's track row)."""
    sc = generate_scenario("merge", 10007)
    t, now = sc.tracks, sc.current_index
    sdc = sc.sdc_index
    row = next(i for i in range(t.num_tracks) if i != sdc)
    p0, h0 = t.xyz[sdc, now].copy(), float(t.heading[sdc, now])
    ahead = np.array([np.cos(h0), np.sin(h0), 0.0])
    steps = np.arange(t.valid.shape[1]) - now
    xyz = np.zeros_like(t.xyz)
    xyz[sdc] = p0
    xyz[row] = p0 + (steps * 0.1 * speed - gap)[:, None] * ahead
    valid = np.zeros_like(t.valid)
    valid[[sdc, row]] = True
    velocity = np.zeros_like(t.velocity)
    velocity[row] = speed * ahead[:2]
    size = np.broadcast_to(np.float32([4.5, 1.9, 1.6]), t.size.shape).copy()
    tracks = dataclasses.replace(
        t,
        xyz=xyz,
        heading=np.full_like(t.heading, h0),
        velocity=velocity,
        size=size,
        valid=valid,
        object_type=np.full_like(t.object_type, VEH),
        raw_heading=None,
    )
    scene = dataclasses.replace(
        sc,
        tracks=tracks,
        tracks_to_predict=np.array([row]),
        predict_difficulty=np.zeros(1, np.int8),
    )
    return scene, row


class _ForwardHead(torch.nn.Module):
    """An action head that always wants to speed up straight ahead (raw (1, 0))."""

    def forward(self, x: torch.Tensor, ag_type: torch.Tensor) -> torch.Tensor:
        raw = torch.zeros(*x.shape[:-1], 2, dtype=x.dtype, device=x.device)
        return raw + torch.tensor([1.0, 0.0], dtype=x.dtype, device=x.device)


def _closest_bumper_gap(inference: InferenceConfig) -> float:
    """Smallest bumper gap (m) over 60 steps of ``_line_of_two`` in ``TrafficEnv``, the SDC
    held still, the follower driven by a small model with ``_ForwardHead``."""
    sc, row = _line_of_two()
    model = TrafficBots(TrafficBotsConfig.small(), inference)
    model.action_head = _ForwardHead()
    never = EnvConfig(termination=TerminationConfig(collision=False, goal=False))
    env = TrafficEnv([sc], npc_policy=TrafficBotsPolicy(model.eval(), trim=True), config=never)
    env.reset(seed=0)
    slots = env.sim_state.agents.track_index[0].numpy().tolist()
    sdc, follower = slots.index(sc.sdc_index), slots.index(row)
    gaps = []
    for _ in range(60):
        env.step({a: np.zeros(2, np.float32) for a in env.agents})
        pose = env.sim_state.pose[0]
        gaps.append(float(torch.hypot(*(pose[sdc, :2] - pose[follower, :2]))) - 4.5)
    return min(gaps)


def test_gap_keeping_stops_a_follower_behind_a_standing_vehicle():
    # It stops about the standstill gap (1 m) short of the standing vehicle.
    assert _closest_bumper_gap(InferenceConfig()) > 0.5
    # Without the rule the same network drives into it.
    assert _closest_bumper_gap(InferenceConfig(gap_keeping=None)) < 0.0


def test_gap_keeping_cap_sees_only_the_agent_ahead_in_the_lane():
    # follower at 10 m/s; a standing car 20 m ahead; one 20 m ahead in the next lane; one
    # 10 m behind the follower at 10 m/s; a pedestrian-sized agent far ahead (beyond 40 m).
    pose = torch.tensor([[[0.0, 0, 0], [20, 0, 0.1], [20, 4, 0], [-10, 0, 0], [60, 0, 0]]])
    speed = torch.tensor([[10.0, 0.0, 0.0, 10.0, 0.0]])
    valid = torch.ones(1, 5, dtype=torch.bool)
    size = torch.tensor([[4.5, 2.0]] * 4 + [[0.5, 0.5]])[None]
    cap = gap_keeping_cap(pose, speed, valid, size, GapKeeping())
    assert float(cap[0, 0]) < -2.0  # brakes for the standing car
    assert float(cap[0, 3]) < 0.0  # 5.5 m behind a car at the same speed: too close
    assert torch.isinf(cap[0, [1, 2, 4]]).all()  # nothing ahead within the corridor / horizon
    valid[0, 1] = False  # an absent agent is no obstacle
    assert torch.isinf(gap_keeping_cap(pose, speed, valid, size, GapKeeping())[0, 0])


def test_gap_keeping_cap_is_invariant_to_a_rigid_motion_of_the_world():
    gen = torch.Generator().manual_seed(0)
    pose = torch.rand(3, 12, 3, generator=gen) * torch.tensor([60.0, 60.0, 6.28])
    speed = torch.rand(3, 12, generator=gen) * 15
    valid = torch.rand(3, 12, generator=gen) > 0.2
    size = torch.tensor([4.5, 2.0]).expand(3, 12, 2)
    cap = gap_keeping_cap(pose, speed, valid, size, GapKeeping())
    th = 2.3
    rot = torch.tensor([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]], dtype=torch.float32)
    moved_xy = pose[..., :2] @ rot.T + torch.tensor([3000.0, -1200.0])
    moved = torch.cat([moved_xy, pose[..., 2:] + th], -1)
    cap2 = gap_keeping_cap(moved, speed, valid, size, GapKeeping())
    assert torch.isfinite(cap).sum() > 3
    assert torch.equal(torch.isinf(cap), torch.isinf(cap2))
    finite = torch.isfinite(cap)
    assert torch.allclose(cap[finite], cap2[finite], atol=1e-2, rtol=1e-3)


def test_keep_gap_only_lowers_vehicle_accelerations_within_limits():
    action = torch.tensor([[[3.0, 0.4], [3.0, 0.4], [-1.0, 0.2]]])
    speed = torch.tensor([[15.0, 1.0, 15.0]])
    pose = torch.tensor([[[0.0, 0, 0], [6.0, 0, 0], [12.0, 0, 0]]])
    valid = torch.ones(1, 3, dtype=torch.bool)
    typ = torch.tensor([[VEH, PED, VEH]])
    size = torch.tensor([[[4.5, 2.0], [0.6, 0.6], [4.5, 2.0]]])
    out = keep_gap(action, speed, (pose, valid), (typ, size), GapKeeping())
    assert float(out[0, 0, 0]) == -5.0  # 15 m/s, 3.2 m behind a pedestrian: the braking limit
    assert float(out[0, 1, 0]) == 3.0  # pedestrians keep their actions
    assert float(out[0, 2, 0]) == -1.0  # nothing ahead: unchanged
    assert torch.equal(out[..., 1], action[..., 1])


def test_gap_keeping_parameters_are_checked_and_parsed():
    with pytest.raises(ValueError, match="time_headway"):
        GapKeeping(time_headway=-1.0)
    with pytest.raises(ValueError):
        GapKeeping(min_gap=0.0)
    assert GapKeeping.parse("off") is None
    assert GapKeeping.parse("") == GapKeeping()
    assert GapKeeping.parse("time_headway=1.5, standstill_gap=2") == GapKeeping(
        time_headway=1.5, standstill_gap=2.0
    )
    with pytest.raises(ValueError, match="NAME=VALUE"):
        GapKeeping.parse("headway=1")
    flags = InferenceConfig().with_rule_flags("off", "horizon=1.5")
    assert flags.gap_keeping is None and flags.road_keeping.horizon == 1.5
    assert InferenceConfig().with_rule_flags() == InferenceConfig()


def _first_sdc_collision(path, gap_keeping: bool, seed: int) -> int | None:
    """Step of the first collision of the log-following SDC of the real sample scene among
    shipped TrafficBots NPCs (None: none in the episode)."""
    model = load_default_model()
    if not gap_keeping:
        model.inference = dataclasses.replace(model.inference, gap_keeping=None)
    never = EnvConfig(termination=TerminationConfig(collision=False, goal=False))
    env = TrafficEnv(path, npc_policy=TrafficBotsPolicy(model, trim=True), config=never)
    env.reset(seed=seed)
    step = 0
    while env.agents:
        a = env.agents[0]
        info = env.step({a: env.expert_actions()[a]})[4]
        step += 1
        if info[a]["collision"]:
            return step
    return None


def test_shipped_npcs_do_not_run_into_the_log_following_sdc(one_scenario_path):
    """637f20cafde22ff8: the SDC stands still, as in its log. Without gap keeping the shipped
    NPCs hit it in 7 of 8 seeded episodes (step 31-65); with it, in none."""
    for seed in (1, 3):
        assert _first_sdc_collision(one_scenario_path, True, seed) is None
    assert _first_sdc_collision(one_scenario_path, False, 1) is not None
