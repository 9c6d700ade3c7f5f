"""Personality latent (docs/model.md §3.5, §3.6): posterior encoder, the N(0, I) prior,
AddNaviLatent.

The prior is the fixed standard normal. The original code also builds separate "prior" TL and
agent encoders (~2.7 M parameters) that are never called; they are deliberately NOT built here.
"""

from __future__ import annotations

import torch
from torch import nn

from policies.trafficbots.agent_encoder import AgentContext, AgentEncoder
from policies.trafficbots.config import TrafficBotsConfig
from policies.trafficbots.map_encoder import MapTokens
from policies.trafficbots.mlp import MLP
from policies.trafficbots.tl_encoder import TLContext, TLEncoder


class Posterior(nn.Module):
    """q(z | whole ground-truth episode): diagonal Gaussian with a learnable, input-independent
    log sigma. Runs separate TL and agent encoders over steps 0, 5, ..., 90 (19 steps).

    Args:
        cfg: network configuration.
    """

    def __init__(self, cfg: TrafficBotsConfig) -> None:
        super().__init__()
        self.cfg = cfg
        d, n_time = cfg.hidden_dim, cfg.n_posterior_steps
        self.tl_encoder = TLEncoder(cfg, n_time)
        self.agent_encoder = AgentEncoder(cfg, n_time)
        self.mean = MLP([d] * cfg.mlp_layers + [cfg.latent_dim])
        self.log_std = nn.Parameter(torch.full((cfg.latent_dim,), cfg.posterior_log_std_init))

    def forward(
        self,
        ag_valid: torch.Tensor,
        ag_pose: torch.Tensor,
        ag_motion: torch.Tensor,
        ag_attr: torch.Tensor,
        tl_state: torch.Tensor,
        mp: MapTokens,
        tl_ctx: TLContext,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Posterior parameters.

        Args:
            ag_valid: [B, N, T] bool ground truth (T = cfg.n_steps).
            ag_pose: [B, N, T, 3].
            ag_motion: [B, N, T, 3].
            ag_attr: [B, N, 6].
            tl_state: [B, L, T] int64 ground-truth TL states (UNKNOWN where invalid).
            mp: encoded map (not detached).
            tl_ctx: static TL tensors (token valid from the ground truth).

        Returns:
            (mean [B, N, Z], log_std [B, N, Z], valid [B, N] bool).
        """
        steps = torch.arange(
            0, ag_valid.shape[-1], self.cfg.posterior_stride, device=ag_valid.device
        )
        tl_win = tl_state[..., steps]  # [B, L, 19]
        tl_step_valid = tl_ctx.valid[..., None].expand_as(tl_win)
        tl_feat = self.tl_encoder(tl_win, tl_step_valid, tl_ctx, self.tl_encoder.map_kv(mp.feat))
        feat, _, valid = self.agent_encoder(
            ag_valid[..., steps],
            ag_pose[..., steps, :],
            ag_motion[..., steps, :],
            ag_attr,
            AgentContext(
                mp, self.agent_encoder.map_kv(mp.feat), tl_feat, tl_ctx.pose, tl_ctx.valid
            ),
        )
        mean = self.mean(feat)
        return mean, self.log_std.expand_as(mean), valid


def kl_std_normal(mean: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    """KL(N(mean, exp(log_std)^2) || N(0, I)) summed over the last dimension.

    Args:
        mean: [..., Z].
        log_std: [..., Z].

    Returns:
        [...] nats.
    """
    return 0.5 * (torch.exp(2.0 * log_std) + mean.square() - 1.0 - 2.0 * log_std).sum(-1)


class AddNaviLatent(nn.Module):
    """Residual conditioning ``x + valid * MLP_out([x, MLP_in(c)])`` (mode ``cat``, res_add).

    Both MLPs have ReLU and dropout after every layer, the last one included (docs/model.md §3.5).

    Args:
        in_dim: width of the conditioning input (d for the destination, 16 for the latent).
        dim: token width d.
        n_layers: Linear layers per MLP (3).
        dropout: dropout rate.
    """

    def __init__(self, in_dim: int, dim: int, n_layers: int, dropout: float) -> None:
        super().__init__()
        self.mlp_in = MLP([in_dim] + [dim] * n_layers, dropout, end_activation=True)
        self.mlp_out = MLP([2 * dim] + [dim] * n_layers, dropout, end_activation=True)

    def forward(self, x: torch.Tensor, cond: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """Condition.

        Args:
            x: [B, N, d] agent features.
            cond: [B, N, in_dim] conditioning input.
            valid: [B, N] bool, the conditioning exists for this agent.

        Returns:
            [B, N, d].
        """
        h = self.mlp_out(torch.cat([x, self.mlp_in(cond)], dim=-1))
        return x + h * valid[..., None]
