"""Training losses (docs/model.md §6.2) and one differentiable training step (docs/model.md §6.1).

L = L_KL + L_IL + L_dest + L_TL, all top-level weights 1.0.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F

from policies.trafficbots.batch import TokenBatch
from policies.trafficbots.latent import kl_std_normal
from policies.trafficbots.model import PrepareMode, TrafficBots, rand
from policies.trafficbots.rollout import Trajectory, rollout
from tbsim_env.core import constants as C


@dataclass(frozen=True)
class LossConfig:
    """Loss weights and options (docs/model.md §6.2).

    Attributes:
        w_pos: weight of the summed per-coordinate smooth-L1 position error (0.1).
        w_yaw: weight of 0.5 * (1 - cos(yaw error)) (10).
        w_speed: weight of the smooth-L1 speed error (0.1).
        kl_free_nats: free nats of the KL (1.0).
        kl_balance: weight of the KL term with gradient into the posterior (0.2).
        step_start: imitation loss counts absolute steps > step_start (10).
    """

    w_pos: float = 0.1
    w_yaw: float = 10.0
    w_speed: float = 0.1
    kl_free_nats: float = 1.0
    kl_balance: float = 0.2
    step_start: int = C.CURRENT_INDEX


def _masked_mean(x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    return (x * mask).sum() / mask.sum().clamp(min=1)


def imitation_loss(
    traj: Trajectory, batch: TokenBatch, cfg: LossConfig = LossConfig()
) -> tuple[torch.Tensor, torch.Tensor]:
    """Position / yaw / speed imitation loss over loss-valid (agent, step) pairs.

    Args:
        traj: rollouts of the batch (n_rollouts = 1), T' <= T steps.
        batch: ground truth.
        cfg: weights.

    Returns:
        (scalar loss, loss_valid [B, N, T'] bool).
    """
    n_t = traj.pose.shape[2]
    gt_valid = batch.ag_valid[..., :n_t]
    gt_pose = batch.ag_pose[..., :n_t, :]
    steps = torch.arange(n_t, device=gt_valid.device)
    mask = traj.valid & gt_valid & (steps > cfg.step_start)
    pos = F.smooth_l1_loss(traj.pose[..., :2], gt_pose[..., :2], reduction="none", beta=1.0).sum(-1)
    yaw = 0.5 * (1.0 - torch.cos(traj.pose[..., 2] - gt_pose[..., 2]))
    spd = F.smooth_l1_loss(traj.speed, batch.ag_motion[..., :n_t, 0], reduction="none", beta=1.0)
    per = cfg.w_pos * pos + cfg.w_yaw * yaw + cfg.w_speed * spd
    return _masked_mean(per, mask), mask


def kl_loss(
    mean: torch.Tensor,
    log_std: torch.Tensor,
    valid: torch.Tensor,
    cfg: LossConfig = LossConfig(),
) -> tuple[torch.Tensor, torch.Tensor]:
    """Balanced KL with free nats against the fixed N(0, I) prior.

    ``max(KL(sg(q) || p), f) + alpha * max(KL(q || sg(p)), f)``; since p is fixed, the first
    term carries no gradient.

    Args:
        mean: [B, N, Z] posterior mean.
        log_std: [B, N, Z].
        valid: [B, N] bool agents counted.
        cfg: options.

    Returns:
        (scalar loss, mean raw KL in nats over the counted agents, for logging).
    """
    kl = kl_std_normal(mean, log_std)  # [B, N]
    free = cfg.kl_free_nats
    per = kl.detach().clamp(min=free) + cfg.kl_balance * kl.clamp(min=free)
    return _masked_mean(per, valid), _masked_mean(kl.detach(), valid)


def destination_loss(
    logits: torch.Tensor, target: torch.Tensor, valid: torch.Tensor
) -> torch.Tensor:
    """Cross-entropy of the ground-truth destination.

    Agents whose label is a forbidden token (logit -inf, e.g. a label of a class the type may
    not choose) are skipped rather than giving an infinite loss.

    Args:
        logits: [B, N, M].
        target: [B, N] int64 (-1 none).
        valid: [B, N] bool agents counted.

    Returns:
        scalar.
    """
    logp = torch.log_softmax(logits, dim=-1).gather(-1, target.clamp(min=0)[..., None])[..., 0]
    ok = valid & (target >= 0) & torch.isfinite(logp)
    return _masked_mean(torch.where(ok, -logp, torch.zeros_like(logp)), ok)


def tl_state_loss(
    tl_logits: torch.Tensor, gt_state: torch.Tensor, tl_valid: torch.Tensor
) -> torch.Tensor:
    """NLL of the ground-truth TL state at t under the prediction made at t-1, steps 1..T'-1.

    Args:
        tl_logits: [B, L, T'-1, 5].
        gt_state: [B, L, T] int64.
        tl_valid: [B, L] bool token validity.

    Returns:
        scalar.
    """
    n_t = tl_logits.shape[2] + 1
    target = gt_state[..., 1:n_t]
    nll = F.cross_entropy(tl_logits.flatten(0, 2), target.flatten(), reduction="none")
    mask = tl_valid[..., None].expand_as(target)
    return _masked_mean(nll.view_as(target), mask)


def training_step(
    model: TrafficBots,
    batch: TokenBatch,
    *,
    prior_prob: float = 0.1,
    teacher_forcing_p: float = 0.0,
    generator: torch.Generator | None = None,
    n_steps: int | None = None,
    input_dropout_p: float = 0.1,
    loss_cfg: LossConfig = LossConfig(),
) -> tuple[torch.Tensor, dict[str, float]]:
    """One training forward pass (docs/model.md §6.1): posterior or prior latent (chosen once per
    batch), ground-truth destinations and TL states, mean actions, BPTT through the dynamics.

    Args:
        model: the network (call ``model.train()`` first for dropout).
        batch: B scenes with full ground truth.
        prior_prob: probability of rolling out with z from the prior (0.1).
        teacher_forcing_p: per-agent probability of full teacher forcing (0.3 - 0.1 * epoch).
        generator: random source (latent choice, z, forcing draws).
        n_steps: roll out only steps 0 .. n_steps-1 (default all; shorter for cheap tests).
        input_dropout_p: map-node / history input dropout (docs/model.md §1.9), train mode only.
        loss_cfg: loss weights.

    Returns:
        (differentiable total loss, dict of float scalars for logging).
    """
    dev = batch.device
    use_prior = bool(rand((), generator, dev) < prior_prob)
    mode = PrepareMode(
        latent="prior" if use_prior else "posterior",
        dest="gt",
        tl_valid_from="full",
        with_posterior=True,
        input_dropout_p=input_dropout_p,
    )
    ctx = model.prepare(batch, 1, generator, mode)
    n_sc, n_ag = batch.ag_type.shape
    u = rand((n_sc, batch.draw_sizes[0]), generator, dev)[:, :n_ag]  # as ``prepare`` draws
    force = u < teacher_forcing_p
    traj = rollout(model, ctx, batch, gt_steps=batch.n_steps, teacher_force=force, n_steps=n_steps)
    l_il, loss_valid = imitation_loss(traj, batch, loss_cfg)
    has_loss = loss_valid.any(-1)  # [B, N]
    l_kl, kl_raw = kl_loss(ctx.post_mean, ctx.post_log_std, ctx.post_valid & has_loss, loss_cfg)
    hist_valid = batch.ag_valid[..., : model.cfg.n_history].any(-1)
    l_dest = destination_loss(ctx.scene.dest_logits, batch.ag_dest, hist_valid & has_loss)
    l_tl = tl_state_loss(traj.tl_logits, batch.tl_state, ctx.tl.valid)
    loss = l_kl + l_il + l_dest + l_tl
    logs = {
        "loss": float(loss.detach()),
        "imitation": float(l_il.detach()),
        "kl": float(l_kl.detach()),
        "kl_nats": float(kl_raw),
        "destination": float(l_dest.detach()),
        "tl_state": float(l_tl.detach()),
        "use_prior": float(use_prior),
        "n_loss_valid": float(loss_valid.sum()),
    }
    return loss, logs
