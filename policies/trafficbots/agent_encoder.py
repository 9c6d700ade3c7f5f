"""Agent encoders (docs/model.md §3.3): a window of agent states -> one token per agent, then
decoder layers over agent neighbours and over the nearest map and TL tokens."""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from policies.trafficbots.attention import DecoderLayer, Neighbours
from policies.trafficbots.config import TrafficBotsConfig
from policies.trafficbots.encodings import pose_encoding, relative_pose, rpe
from policies.trafficbots.knn import knn_relative
from policies.trafficbots.map_encoder import MapTokens
from policies.trafficbots.mlp import MLP
from policies.trafficbots.pointnet import PointNet
from tbsim_env.core.constants import ObjectType
from tbsim_env.observation.map_knn import PieceClusters

N_AGENT_TYPES = 3
"""Type branches of the model: vehicle, pedestrian, cyclist (docs/model.md §1.4)."""
AGENT_ATTR_DIM = 3 + N_AGENT_TYPES
"""(length, width, height) + type one-hot."""
AGENT_MOTION_DIM = 3
"""(signed speed m/s, acceleration m/s^2, yaw rate rad/s)."""


def type_branch(ag_type: torch.Tensor) -> torch.Tensor:
    """``ObjectType`` -> model branch 0 vehicle, 1 pedestrian, 2 cyclist.

    The spec has no slot for UNSET / OTHER; they use the vehicle branch (as their dynamics
    limits do in ``tbsim_env.core.constants``).

    Args:
        ag_type: [...] int ``ObjectType``.

    Returns:
        [...] int64 in 0..2.
    """
    branch = ag_type.long() - int(ObjectType.VEHICLE)
    return torch.where((branch >= 0) & (branch < N_AGENT_TYPES), branch, torch.zeros_like(branch))


def agent_attributes(ag_type: torch.Tensor, ag_size: torch.Tensor) -> torch.Tensor:
    """``sc/ag_attr``: raw size plus type one-hot.

    Args:
        ag_type: [B, N] ``ObjectType``.
        ag_size: [B, N, 3] (length, width, height) m.

    Returns:
        [B, N, 6].
    """
    one_hot = F.one_hot(type_branch(ag_type), N_AGENT_TYPES).to(ag_size.dtype)
    return torch.cat([ag_size, one_hot], dim=-1)


def last_valid_pose(valid: torch.Tensor, pose: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Token pose = last valid pose of the window.

    Args:
        valid: [B, N, W] bool.
        pose: [B, N, W, 3].

    Returns:
        (pose [B, N, 3], zero for agents without a valid step; token valid [B, N] bool).
    """
    steps = torch.arange(valid.shape[-1], device=valid.device)
    last = torch.where(valid, steps, -1).amax(dim=-1).clamp(min=0)  # [B, N]
    token_pose = pose.gather(2, last[..., None, None].expand(-1, -1, 1, 3))[:, :, 0]
    token_valid = valid.any(dim=-1)
    return token_pose * token_valid[..., None], token_valid


class AgentInputEncoder(nn.Module):
    """Per-step MLP of (attributes, motion, time one-hot) + pose encoding, PointNet over time.

    Args:
        cfg: network configuration.
        n_time: length of the time one-hot (11 in the policy, 19 in the posterior).
    """

    def __init__(self, cfg: TrafficBotsConfig, n_time: int) -> None:
        super().__init__()
        self.cfg = cfg
        self.n_time = n_time
        d_mlp = cfg.hidden_dim - cfg.pose_dim
        n_in = AGENT_ATTR_DIM + AGENT_MOTION_DIM + n_time
        self.input_mlp = MLP([n_in] + [d_mlp] * cfg.mlp_layers)
        self.pointnet = PointNet(cfg.hidden_dim, cfg.pointnet_layers, cfg.dropout)

    def forward(
        self, valid: torch.Tensor, pose: torch.Tensor, motion: torch.Tensor, attr: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Encode a window.

        Args:
            valid: [B, N, W] bool (W <= n_time, newest step last).
            pose: [B, N, W, 3] (x, y, yaw) in the scene frame.
            motion: [B, N, W, 3] (speed, acceleration, yaw rate).
            attr: [B, N, 6] ``agent_attributes``.

        Returns:
            (feat [B, N, d], token pose [B, N, 3], token valid [B, N]).
        """
        n_win = valid.shape[-1]
        token_pose, token_valid = last_valid_pose(valid, pose)
        local = relative_pose(token_pose[:, :, None], pose)  # [B, N, W, 3]
        time_1h = torch.eye(self.n_time, device=pose.device, dtype=pose.dtype)
        time_1h = time_1h[self.n_time - n_win :].expand(*valid.shape, -1)  # [B, N, W, n_time]
        x = torch.cat([attr[:, :, None].expand(-1, -1, n_win, -1), motion, time_1h], dim=-1)
        pe = pose_encoding(local, self.cfg.pose_xy_dim, self.cfg.pose_yaw_dim, self.cfg.pe_base)
        x = torch.cat([self.input_mlp(x), pe], dim=-1)  # [B, N, W, d]
        feat = self.pointnet(x, valid) * token_valid[..., None]
        return feat, token_pose, token_valid


class AgentContext(NamedTuple):
    """What the agent tokens attend to besides each other, at one step.

    Attributes:
        mp: encoded map (features are not detached).
        map_kv: each layer's ``context_kv`` of the map tokens, [B, M, 2d] per layer
            (``AgentEncoder.map_kv``, computed once per rollout).
        tl_feat: [B, L, d] TL features of this step.
        tl_pose: [B, L, 3].
        tl_valid: [B, L] bool.
        map_clusters: the map pieces' ``PieceClusters`` for the nearest-piece search, or None
            (every piece is measured; the same neighbours).
    """

    mp: MapTokens
    map_kv: tuple[torch.Tensor, ...]
    tl_feat: torch.Tensor
    tl_pose: torch.Tensor
    tl_valid: torch.Tensor
    map_clusters: PieceClusters | None = None


class AgentEncoder(nn.Module):
    """Agent token encoder with decoder layers: agent self KNN; cross over map + TL KNN.

    Args:
        cfg: network configuration.
        n_time: window length of the time one-hot.
    """

    def __init__(self, cfg: TrafficBotsConfig, n_time: int) -> None:
        super().__init__()
        self.cfg = cfg
        d = cfg.hidden_dim
        self.input = AgentInputEncoder(cfg, n_time)
        self.layers = nn.ModuleList(
            DecoderLayer(d, cfg.n_heads, cfg.ff_mult * d, cfg.rpe_dim, cfg.dropout)
            for _ in range(cfg.agent_layers)
        )

    def map_kv(self, map_feat: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Each layer's keys and values of the map tokens [B, M, d]: [B, M, 2d] per layer.

        The map does not change during a rollout, so ``prepare`` computes these once
        (``AgentContext.map_kv``) instead of every step.
        """
        return tuple(layer.context_kv(map_feat) for layer in self.layers)

    def forward(
        self,
        valid: torch.Tensor,
        pose: torch.Tensor,
        motion: torch.Tensor,
        attr: torch.Tensor,
        ctx: AgentContext,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Encode agents in context.

        Args:
            valid, pose, motion, attr: the window, as ``AgentInputEncoder.forward``.
            ctx: the map and TL tokens of this step.

        Returns:
            (feat [B, N, d], token pose [B, N, 3], token valid [B, N]).
        """
        cfg, mp = self.cfg, ctx.mp
        x, ag_pose, ag_valid = self.input(valid, pose, motion, attr)
        s_idx, s_mask, s_rel = knn_relative(ag_pose, ag_pose, ag_valid, cfg.ag_knn, cfg.ag_dist)
        m_idx, m_mask, m_rel = knn_relative(
            ag_pose, mp.pose, mp.valid, cfg.ag_map_knn, cfg.ag_map_dist, ctx.map_clusters
        )
        t_idx, t_mask, t_rel = knn_relative(
            ag_pose, ctx.tl_pose, ctx.tl_valid, cfg.ag_tl_knn, cfg.ag_tl_dist
        )
        ctx_idx = torch.cat([m_idx, t_idx + mp.feat.shape[1]], dim=2)  # [B, N, Km + Kt]
        ctx_mask = torch.cat([m_mask, t_mask], dim=2)  # [B, N, Km + Kt]
        ctx_rpe = rpe(torch.cat([m_rel, t_rel], dim=2), cfg)
        s_rpe = rpe(s_rel, cfg)
        own = Neighbours(s_idx, s_mask, s_rpe)
        near = Neighbours(ctx_idx, ctx_mask, ctx_rpe)
        for layer, kv in zip(self.layers, ctx.map_kv, strict=True):
            # Context rows: the map pieces, then the TL tokens.
            ctx_kv = torch.cat([kv, layer.context_kv(ctx.tl_feat)], dim=1)  # [B, M + L, 2d]
            x = layer(x, ag_valid, own, ctx_kv, near)
        return x, ag_pose, ag_valid
