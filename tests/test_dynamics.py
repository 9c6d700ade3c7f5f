"""Unicycle dynamics: formula, limits, and inverse-then-forward reproducing logs."""

from __future__ import annotations

import math

import pytest
import torch

from tbsim_env.core import constants as C
from tbsim_env.data import load_scenarios
from tbsim_env.sim.build import build_sim_state
from tbsim_env.sim.dynamics import (
    action_limits,
    clip_action,
    inverse_unicycle,
    rollout_from_log,
    signed_speed,
    squash_action,
    unicycle_step,
)

pytestmark = pytest.mark.float_sensitive


def test_midpoint_step_matches_hand_computation():
    pose = torch.tensor([[1.0, 2.0, 0.3]], dtype=torch.float64)
    speed = torch.tensor([4.0], dtype=torch.float64)
    action = torch.tensor([[2.0, 0.5]], dtype=torch.float64)
    new_pose, new_speed = unicycle_step(pose, speed, action, dt=0.1)
    v_mid, yaw_mid = 4.0 + 0.05 * 2.0, 0.3 + 0.05 * 0.5
    assert new_pose[0, 0].item() == pytest.approx(1.0 + 0.1 * v_mid * math.cos(yaw_mid))
    assert new_pose[0, 1].item() == pytest.approx(2.0 + 0.1 * v_mid * math.sin(yaw_mid))
    assert new_pose[0, 2].item() == pytest.approx(0.35)
    assert new_speed[0].item() == pytest.approx(4.2)


def test_yaw_is_wrapped_and_reverse_allowed():
    pose = torch.tensor([[0.0, 0.0, math.pi - 0.01]])
    new_pose, new_speed = unicycle_step(pose, torch.tensor([0.1]), torch.tensor([[-5.0, 1.0]]))
    assert -math.pi <= new_pose[0, 2].item() < math.pi
    assert new_speed[0].item() == pytest.approx(-0.4)


def test_limits_per_type():
    types = torch.tensor([C.ObjectType.VEHICLE, C.ObjectType.PEDESTRIAN, C.ObjectType.CYCLIST])
    acc, yaw = action_limits(types)
    assert acc.tolist() == [5.0, 7.0, 6.0]
    assert yaw.tolist() == [1.5, 7.0, 3.0]
    big = torch.full((3, 2), 100.0)
    assert clip_action(big, types).tolist() == [[5.0, 1.5], [7.0, 7.0], [6.0, 3.0]]
    assert clip_action(-big, types).tolist() == [[-5.0, -1.5], [-7.0, -7.0], [-6.0, -3.0]]
    squashed = squash_action(big, types)
    assert torch.allclose(squashed, clip_action(big, types))
    assert squash_action(torch.zeros(3, 2), types).abs().max() == 0


def test_signed_speed_sign():
    vel = torch.tensor([[3.0, 4.0], [-3.0, -4.0]])
    yaw = torch.tensor([math.atan2(4, 3), math.atan2(4, 3)])
    assert signed_speed(vel, yaw).tolist() == pytest.approx([5.0, -5.0])


def test_inverse_then_forward_is_exact_on_feasible_trajectories():
    gen = torch.Generator().manual_seed(0)
    b, n_t = 32, 91
    types = torch.randint(1, 4, (b,), generator=gen)
    raw = torch.randn(b, n_t - 1, 2, generator=gen, dtype=torch.float64)
    action = squash_action(raw * 0.5, types[:, None].expand(b, n_t - 1)).double()
    pose = [torch.randn(b, 3, generator=gen, dtype=torch.float64) * 20]
    speed = [torch.rand(b, generator=gen, dtype=torch.float64) * 10]
    for t in range(n_t - 1):
        p, v = unicycle_step(pose[-1], speed[-1], action[:, t])
        pose.append(p)
        speed.append(v)
    pose_t, speed_t = torch.stack(pose, 1), torch.stack(speed, 1)
    valid = torch.ones(b, n_t, dtype=torch.bool)
    valid[:4, 30:35] = False  # gaps restart from the log
    rec, rec_valid = inverse_unicycle(pose_t, speed_t, valid, types)
    out_pose, out_speed = rollout_from_log(pose_t, speed_t, valid, rec)
    err = (out_pose - pose_t)[..., :2].norm(dim=-1)[valid]
    assert err.max() < 1e-6
    assert torch.allclose(rec[rec_valid], action[rec_valid], atol=1e-5)


def _log_tracking_error(scenario) -> dict[int, torch.Tensor]:
    state = build_sim_state([scenario])
    log_pose, speed, valid = (state.log.take(k) for k in ("pose", "speed", "valid"))
    action, _ = inverse_unicycle(log_pose, speed, valid, state.agents.object_type)
    pose, _ = rollout_from_log(log_pose, speed, valid, action)
    err = (pose[..., :2] - log_pose[..., :2]).norm(dim=-1)
    types = state.agents.object_type[..., None].expand_as(err)
    return {t: err[valid & (types == t)] for t in (1, 2, 3)}


@pytest.mark.parametrize("name", ["motion_data_one_scenario", "womd_scenario_input"])
def test_inverse_then_forward_reproduces_real_logs(womd_dir, name):
    scenario = load_scenarios(womd_dir / "waymo-open-dataset" / f"{name}.tfrecord")[0]
    err = _log_tracking_error(scenario)
    veh = err[C.ObjectType.VEHICLE]
    # Measured: mean 4-6 cm, p95 7-24 cm; the rest are log steps the limits cannot follow.
    assert veh.mean() < 0.1
    assert torch.quantile(veh, 0.95) < 0.35
    assert torch.quantile(veh, 0.99) < 2.0
    ped = err[C.ObjectType.PEDESTRIAN]
    assert ped.mean() < 0.3


def test_inverse_then_forward_on_generated_scenes():
    from tbsim_env.data.generator import generate_scenario

    for layout in ("intersection", "merge"):
        err = _log_tracking_error(generate_scenario(layout, seed=3))
        veh = err[C.ObjectType.VEHICLE]
        assert veh.mean() < 0.05, layout
        assert torch.quantile(veh, 0.99) < 0.3, layout
