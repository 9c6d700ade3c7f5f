"""Closed-loop rollout (docs/model.md §5), shared by training (BPTT) and inference (no_grad).

The only Python loop is over time. Steps 1..10 are forced to the ground-truth history (spawn and
warm start); afterwards agents move by the model's mean actions through the unicycle. Network
inputs are detached at every step; the dynamics chain is not (docs/model.md §6.4).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from policies.trafficbots.batch import TokenBatch
from policies.trafficbots.model import RolloutContext, TrafficBots
from tbsim_env.core import constants as C
from tbsim_env.sim.dynamics import unicycle_step
from tbsim_env.sim.geometry import rotate


@dataclass(frozen=True)
class Trajectory:
    """A batch of rollouts, B' = B * n_rollouts, T simulated steps (step 0 included).

    Attributes:
        pose: [B', N, T, 3] (x, y, yaw); zero where invalid.
        speed: [B', N, T] m/s.
        valid: [B', N, T] bool.
        action: [B', N, T-1, 2] physical action applied from step t to t+1.
        tl_state: [B', L, T] int64 TL state used at each step.
        tl_logits: [B', L, T-1, 5] logits predicted at step t for the TL state at t+1.
        disabled: [B', N] bool, agent disabled for leaving the map boundary.
    """

    pose: torch.Tensor
    speed: torch.Tensor
    valid: torch.Tensor
    action: torch.Tensor
    tl_state: torch.Tensor
    tl_logits: torch.Tensor
    disabled: torch.Tensor


def outside_boundary(xy: torch.Tensor, boundary: torch.Tensor) -> torch.Tensor:
    """[B, N, 2] positions outside the box [B, 5] -> [B, N] bool.

    The box is (x_min, x_max, y_min, y_max) in the frame rotated by its fifth entry (yaw,
    ``TokenBatch.mp_boundary``): the spec's scene frame, so the test turns with the scene.
    """
    b = boundary[:, None]
    local = rotate(xy, -b[..., 4])
    x, y = local[..., 0], local[..., 1]
    return (x < b[..., 0]) | (x > b[..., 1]) | (y < b[..., 2]) | (y > b[..., 3])


def rollout(
    model: TrafficBots,
    ctx: RolloutContext,
    batch: TokenBatch,
    *,
    gt_steps: int,
    teacher_force: torch.Tensor | None = None,
    n_steps: int | None = None,
    disable_outside_map: bool = True,
) -> Trajectory:
    """Roll out ``ctx.n_rollouts`` closed-loop futures of every scene of ``batch``.

    Args:
        model: the network (its train/eval mode is left as is).
        ctx: from ``model.prepare(batch, n_rollouts, ...)``.
        batch: the B scenes (ground truth for forcing and TL overrides).
        gt_steps: ground truth exists for steps < gt_steps: TL states are overridden there and
            it counts for the outside-map rule (training: T; inference: 11).
        teacher_force: [B', N] bool agents replayed from the ground truth at all their valid
            steps (scheduled teacher forcing, docs/model.md §6.3), or None.
        n_steps: simulate steps 0 .. n_steps-1 (default: all steps of the batch).
        disable_outside_map: disable agents leaving ``mp_boundary`` without ground truth.

    Returns:
        ``Trajectory``.
    """
    n = ctx.n_rollouts
    n_steps = n_steps or batch.n_steps
    gt = batch.repeat(n) if n > 1 else batch
    gt_valid, gt_pose, gt_speed = gt.ag_valid, gt.ag_pose, gt.ag_motion[..., 0]
    valid = gt_valid[..., 0]
    pose = gt_pose[..., 0, :] * valid[..., None]
    speed = gt_speed[..., 0] * valid
    tl = gt.tl_state[..., 0]
    disabled = torch.zeros_like(valid)
    forced = teacher_force if teacher_force is not None else torch.zeros_like(valid)
    poses, speeds, valids, tls, actions, logits = [pose], [speed], [valid], [tl], [], []
    state = model.initial_state(ctx)
    for t in range(1, n_steps):
        out, state = model.step(ctx, state, pose, speed, valid, tl)
        next_pose, next_speed = unicycle_step(pose, speed, out.action)
        tl = out.tl_logits.argmax(-1)
        if t < gt_steps:
            tl = torch.where(gt.tl_valid[..., t], gt.tl_state[..., t], tl)
        force = gt_valid[..., t] & (forced | (t <= C.CURRENT_INDEX))
        next_pose = torch.where(force[..., None], gt_pose[..., t, :], next_pose)
        next_speed = torch.where(force, gt_speed[..., t], next_speed)
        next_valid = (valid | force) & ~disabled
        if disable_outside_map:
            has_gt = gt_valid[..., t] & (t < gt_steps)
            leave = next_valid & ~has_gt & outside_boundary(next_pose[..., :2], gt.mp_boundary)
            disabled = disabled | leave
            next_valid = next_valid & ~leave
        pose = next_pose * next_valid[..., None]
        speed = next_speed * next_valid
        valid = next_valid
        poses.append(pose)
        speeds.append(speed)
        valids.append(valid)
        tls.append(tl)
        actions.append(out.action)
        logits.append(out.tl_logits)
    return Trajectory(
        pose=torch.stack(poses, dim=2),
        speed=torch.stack(speeds, dim=2),
        valid=torch.stack(valids, dim=2),
        action=torch.stack(actions, dim=2),
        tl_state=torch.stack(tls, dim=2),
        tl_logits=torch.stack(logits, dim=2),
        disabled=disabled,
    )
