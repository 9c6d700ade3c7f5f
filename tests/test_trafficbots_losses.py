"""TrafficBots losses against hand-computed values (docs/model.md §6.2)."""

from __future__ import annotations

import math

import pytest
import torch

import tbsim_env  # noqa: F401  (first: avoids the policies <-> tbsim_env.env import cycle)

# isort: split

from policies.trafficbots.batch import TokenBatch
from policies.trafficbots.losses import (
    destination_loss,
    imitation_loss,
    kl_loss,
    tl_state_loss,
)
from policies.trafficbots.rollout import Trajectory
from policies.trafficbots.synthetic import make_synthetic_tokens


def test_imitation_loss_hand_values() -> None:
    gt = TokenBatch.from_tokens(make_synthetic_tokens(n_agents=3, n_map=16, n_tl=2, n_steps=14))
    pose = gt.ag_pose.clone()
    speed = gt.ag_motion[..., 0].clone()
    valid = gt.ag_valid.clone()
    # Agent 0 at step 12: 0.5 m x error (quadratic part), 3 m y error (linear part),
    # yaw error pi/2, speed error 2 m/s. Every other loss-valid pair is exact.
    pose[0, 0, 12, 0] += 0.5
    pose[0, 0, 12, 1] += 3.0
    pose[0, 0, 12, 2] += math.pi / 2
    speed[0, 0, 12] += 2.0
    traj = Trajectory(pose, speed, valid, None, None, None, None)
    loss, mask = imitation_loss(traj, gt)
    assert not mask[..., :11].any() and mask[0, 0, 11:].all()
    per = 0.1 * (0.5 * 0.5**2 + (3.0 - 0.5)) + 10 * 0.5 * (1 - math.cos(math.pi / 2))
    per += 0.1 * (2.0 - 0.5)
    assert loss.item() == pytest.approx(per / mask.sum().item(), rel=1e-5)


def test_kl_free_nats_and_balance() -> None:
    valid = torch.ones(1, 2, dtype=torch.bool)
    # Agent 0: KL = 0 (below the free nat); agent 1: mean 2 in one dim, KL = 2.
    mean = torch.zeros(1, 2, 16)
    mean[0, 1, 0] = 2.0
    mean.requires_grad_(True)
    log_std = torch.zeros(1, 2, 16)
    loss, raw = kl_loss(mean, log_std, valid)
    assert raw.item() == pytest.approx(1.0)  # mean of 0 and 2
    assert loss.item() == pytest.approx(((1 + 0.2) + (2 + 0.2 * 2)) / 2)
    loss.backward()
    # Only the balanced 0.2 term carries gradient, and only above the free nat.
    assert mean.grad[0, 0].abs().sum() == 0
    assert mean.grad[0, 1, 0].item() == pytest.approx(0.2 * 2.0 / 2)


def test_destination_and_tl_losses() -> None:
    logits = torch.tensor([[[0.0, 0.0, float("-inf")], [1.0, 2.0, 3.0]]])
    target = torch.tensor([[2, 0]])  # agent 0's label is forbidden: skipped, no inf
    loss = destination_loss(logits, target, torch.ones(1, 2, dtype=torch.bool))
    assert loss.item() == pytest.approx(-torch.log_softmax(logits[0, 1], -1)[0].item())
    tl_logits = torch.randn(1, 2, 3, 5)
    gt = torch.randint(0, 5, (1, 2, 4))
    tl_valid = torch.tensor([[True, False]])
    got = tl_state_loss(tl_logits, gt, tl_valid)
    ref = torch.nn.functional.cross_entropy(tl_logits[0, 0], gt[0, 0, 1:])
    assert got.item() == pytest.approx(ref.item(), rel=1e-6)
