"""WOSAC-style sampling (docs/model.md §7.1-7.3): N joint rollouts with prior z and sampled
destinations, mean actions, then keep the K rollouts with the fewest collided relevant agents."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from policies.trafficbots.batch import TokenBatch
from policies.trafficbots.collision import collision_flags
from policies.trafficbots.model import TrafficBots
from policies.trafficbots.rollout import rollout
from tbsim_env.data.tokens import SceneTokens


@dataclass(frozen=True)
class RolloutSamples:
    """The kept rollouts of B scenes.

    Attributes:
        pose: [B, K, N, T, 3] (x, y, yaw), scene frame of the tokens.
        speed: [B, K, N, T].
        valid: [B, K, N, T] bool.
        tl_state: [B, K, L, T] int64.
        collided: [B, K, N] bool, collision at some step >= 11.
        score: [B, K] int64 number of collided relevant agents.
        index: [B, K] int64 index of each kept rollout among the N sampled.
    """

    pose: torch.Tensor
    speed: torch.Tensor
    valid: torch.Tensor
    tl_state: torch.Tensor
    collided: torch.Tensor
    score: torch.Tensor
    index: torch.Tensor


@torch.no_grad()
def sample_rollouts(
    model: TrafficBots,
    tokens: SceneTokens | list[SceneTokens] | TokenBatch,
    n: int = 128,
    k: int = 32,
    generator: torch.Generator | None = None,
) -> RolloutSamples:
    """Sample ``n`` rollouts per scene and keep the ``k`` with the fewest collided relevant agents.

    Runs the model in eval mode (restored afterwards). Ties in the score keep the lower rollout
    index (stable sort), so the result is a deterministic function of the generator state.

    Args:
        model: the network.
        tokens: one scene, several scenes, or a ``TokenBatch``.
        n: rollouts per scene (128 in the submission).
        k: rollouts kept (32).
        generator: random source of z and destinations.

    Returns:
        ``RolloutSamples``.
    """
    if k > n:
        raise ValueError(f"cannot keep k={k} of n={n} rollouts")
    batch = tokens if isinstance(tokens, TokenBatch) else TokenBatch.from_tokens(tokens)
    batch = batch.to(model.device)
    sim = batch.trim()  # the padding is masked anyway; skipping it is ~2x faster
    was_training = model.training
    model.eval()
    try:
        ctx = model.prepare(sim, n, generator)
        traj = rollout(model, ctx, sim, gt_steps=model.cfg.n_history)
    finally:
        model.train(was_training)
    size = sim.ag_size.repeat_interleave(n, 0)
    collided = collision_flags(traj.pose, traj.valid, size, start=model.cfg.n_history)
    relevant = sim.ag_role.any(-1).repeat_interleave(n, 0)
    n_sc = batch.n_scenes
    score = (collided & relevant).sum(-1).view(n_sc, n)  # [B, n]
    keep = torch.sort(score, dim=1, stable=True).indices[:, :k]  # [B, k]
    rows = (keep + torch.arange(n_sc, device=keep.device)[:, None] * n).flatten()
    n_ag, n_tl = batch.ag_type.shape[1], batch.tl_piece.shape[1]

    def pick(x: torch.Tensor, size: int) -> torch.Tensor:
        """Kept rollouts, the trimmed rows padded back with zeros (invalid, UNKNOWN)."""
        x = x[rows]
        if x.shape[1] < size:
            x = torch.cat([x, x.new_zeros((x.shape[0], size - x.shape[1], *x.shape[2:]))], 1)
        return x.unflatten(0, (n_sc, k))

    return RolloutSamples(
        pose=pick(traj.pose, n_ag),
        speed=pick(traj.speed, n_ag),
        valid=pick(traj.valid, n_ag),
        tl_state=pick(traj.tl_state, n_tl),
        collided=pick(collided, n_ag),
        score=score.gather(1, keep),
        index=keep,
    )
