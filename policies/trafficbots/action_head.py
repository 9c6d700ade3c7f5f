"""Per-type action head (docs/model.md §3.7): one MLP per agent type; only the mean is used.

The original head also owns a learnable per-type log sigma (init -2) that never affects a
rollout and gets no gradient (mean actions in training and inference); it is not built here.
"""

from __future__ import annotations

import torch
from torch import nn

from policies.trafficbots.agent_encoder import N_AGENT_TYPES, type_branch
from policies.trafficbots.config import TrafficBotsConfig
from policies.trafficbots.mlp import MLP


class ActionHead(nn.Module):
    """Unbounded action mean (u_acc, u_yaw) from the branch of the agent's type."""

    def __init__(self, cfg: TrafficBotsConfig) -> None:
        super().__init__()
        d = cfg.hidden_dim
        self.branches = nn.ModuleList(MLP([d] * cfg.mlp_layers + [2]) for _ in range(N_AGENT_TYPES))

    def forward(self, x: torch.Tensor, ag_type: torch.Tensor) -> torch.Tensor:
        """Action mean.

        Args:
            x: [B, N, d] conditioned agent features.
            ag_type: [B, N] ``ObjectType``.

        Returns:
            [B, N, 2] unbounded (pass through ``squash_action``).
        """
        out = torch.stack([branch(x) for branch in self.branches], dim=-2)  # [B, N, 3, 2]
        idx = type_branch(ag_type)[..., None, None].expand(-1, -1, 1, 2)
        return out.gather(-2, idx)[..., 0, :]
