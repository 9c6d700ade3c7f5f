"""Map encoder (docs/model.md §3.1): per-node MLP + 7-d geometry, PointNet, intra-map self layers.

Run once per scenario; the output ``MapTokens`` is reused at every step and by every rollout.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from policies.trafficbots.attention import SelfAttentionLayer
from policies.trafficbots.config import TrafficBotsConfig
from policies.trafficbots.encodings import map_node_geometry, relative_pose, rpe
from policies.trafficbots.knn import knn_relative
from policies.trafficbots.mlp import MLP
from policies.trafficbots.pointnet import PointNet
from tbsim_env.core.constants import NUM_MAP_CLASSES


@dataclass(frozen=True)
class MapTokens:
    """Encoded map pieces.

    Attributes:
        feat: [B, M, d] token features (after the intra-map layers).
        pose: [B, M, 3] token pose = node 0 (x, y, heading of the first segment).
        valid: [B, M] bool = node 0 valid.
        node_pose: [B, M, P, 3] node poses (x, y, segment heading), scene frame.
        node_valid: [B, M, P] bool.
        cls: [B, M] int64 ``MapClass`` (-1 padding).
    """

    feat: torch.Tensor
    pose: torch.Tensor
    valid: torch.Tensor
    node_pose: torch.Tensor
    node_valid: torch.Tensor
    cls: torch.Tensor


class MapEncoder(nn.Module):
    """Encode map pieces into tokens.

    Args:
        cfg: network configuration.
    """

    def __init__(self, cfg: TrafficBotsConfig) -> None:
        super().__init__()
        self.cfg = cfg
        d = cfg.hidden_dim
        n_in = NUM_MAP_CLASSES + cfg.map_nodes
        self.input_mlp = MLP([n_in] + [d - 7] * cfg.mlp_layers)
        self.pointnet = PointNet(d, cfg.pointnet_layers, cfg.dropout)
        self.layers = nn.ModuleList(
            SelfAttentionLayer(d, cfg.n_heads, cfg.ff_mult * d, cfg.rpe_dim, cfg.dropout)
            for _ in range(cfg.map_layers)
        )

    def forward(
        self, node_pose: torch.Tensor, node_valid: torch.Tensor, cls: torch.Tensor
    ) -> MapTokens:
        """Encode.

        Args:
            node_pose: [B, M, P, 3] (x, y, segment heading) per node.
            node_valid: [B, M, P] bool.
            cls: [B, M] int64 ``MapClass`` (-1 padding).

        Returns:
            ``MapTokens``.
        """
        n_sc, n_mp, n_node = node_valid.shape
        if n_node != self.cfg.map_nodes:
            raise ValueError(f"map pieces have {n_node} nodes, config expects {self.cfg.map_nodes}")
        pose = node_pose[:, :, 0]  # [B, M, 3]
        valid = node_valid[:, :, 0]
        local = relative_pose(pose[:, :, None], node_pose)  # [B, M, P, 3]
        type_1h = F.one_hot(cls.clamp(min=0), NUM_MAP_CLASSES).to(node_pose.dtype)
        node_1h = torch.eye(n_node, dtype=node_pose.dtype, device=node_pose.device)
        attr = torch.cat(
            [
                type_1h[:, :, None].expand(-1, -1, n_node, -1),
                node_1h.expand(n_sc, n_mp, -1, -1),
            ],
            dim=-1,
        )  # [B, M, P, 11 + P]
        x = torch.cat([self.input_mlp(attr), map_node_geometry(local)], dim=-1)  # [B, M, P, d]
        x = self.pointnet(x, node_valid) * valid[..., None]  # [B, M, d]
        idx, mask, rel = knn_relative(pose, pose, valid, self.cfg.map_knn, self.cfg.map_dist)
        r = rpe(rel, self.cfg)
        for layer in self.layers:
            x = layer(x, valid, idx, mask, r)
        return MapTokens(x, pose, valid, node_pose, node_valid, cls)
