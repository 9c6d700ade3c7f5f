"""Destination ("navi"): predictor over all map tokens, encoder, reached check.

docs/model.md §3.4.
"""

from __future__ import annotations

import torch
from torch import nn

from policies.trafficbots.agent_encoder import N_AGENT_TYPES, AgentInputEncoder, type_branch
from policies.trafficbots.config import TrafficBotsConfig
from policies.trafficbots.encodings import relative_pose, rpe
from policies.trafficbots.map_encoder import MapTokens
from policies.trafficbots.mlp import MLP
from tbsim_env.core.constants import NUM_MAP_CLASSES, MapClass
from tbsim_env.sim.geometry import wrap_angle


def _allowed_classes() -> torch.Tensor:
    """[3 branches, 11 classes] bool: which map classes may be a destination
    (docs/model.md §3.4)."""
    allowed = torch.zeros(N_AGENT_TYPES, NUM_MAP_CLASSES, dtype=torch.bool)
    allowed[0, [MapClass.FREEWAY, MapClass.SURFACE_STREET, MapClass.STOP_SIGN]] = True
    allowed[0, MapClass.ROAD_EDGE_BOUNDARY] = True  # vehicles: classes 0-4 minus bike lanes
    allowed[1, MapClass.ROAD_EDGE_BOUNDARY] = True  # pedestrians: road-edge boundary only
    allowed[2, [MapClass.BIKE_LANE, MapClass.ROAD_EDGE_BOUNDARY]] = True  # cyclists
    return allowed


ALLOWED_DEST_CLASSES = _allowed_classes()


def destination_mask(
    ag_type: torch.Tensor, mp_cls: torch.Tensor, mp_valid: torch.Tensor
) -> torch.Tensor:
    """Which map tokens each agent may choose.

    Args:
        ag_type: [B, N] ``ObjectType``.
        mp_cls: [B, M] ``MapClass`` (-1 padding).
        mp_valid: [B, M] bool.

    Returns:
        [B, N, M] bool.
    """
    table = ALLOWED_DEST_CLASSES.to(mp_cls.device)
    rows = table[type_branch(ag_type)]  # [B, N, 11]
    cls = mp_cls.clamp(min=0)[:, None, :].expand(-1, rows.shape[1], -1)  # [B, N, M]
    return rows.gather(2, cls) & (mp_cls >= 0)[:, None] & mp_valid[:, None]


class DestinationPredictor(nn.Module):
    """Categorical over map tokens from the history (inputs and map features detached).

    Args:
        cfg: network configuration.
    """

    def __init__(self, cfg: TrafficBotsConfig) -> None:
        super().__init__()
        self.cfg = cfg
        d = cfg.hidden_dim
        self.input = AgentInputEncoder(cfg, cfg.n_history)
        self.mlp = MLP([2 * d + cfg.rpe_dim] + [d] * (cfg.mlp_layers - 1) + [1], layer_norm=True)

    def forward(
        self,
        valid: torch.Tensor,
        pose: torch.Tensor,
        motion: torch.Tensor,
        attr: torch.Tensor,
        ag_type: torch.Tensor,
        mp: MapTokens,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Destination logits.

        Args:
            valid: [B, N, W] bool history window.
            pose: [B, N, W, 3].
            motion: [B, N, W, 3].
            attr: [B, N, 6].
            ag_type: [B, N] ``ObjectType``.
            mp: encoded map.

        Returns:
            (logits [B, N, M] with -inf on forbidden tokens and all 0 for unusable agents,
            usable [B, N] bool: agent valid in history and some token allowed).
        """
        feat, ag_pose, ag_valid = self.input(valid, pose.detach(), motion.detach(), attr.detach())
        n_ag, n_mp = feat.shape[1], mp.feat.shape[1]
        rel = relative_pose(ag_pose[:, :, None], mp.pose[:, None])  # [B, N, M, 3]
        x = torch.cat(
            [
                feat[:, :, None].expand(-1, -1, n_mp, -1),
                mp.feat.detach()[:, None].expand(-1, n_ag, -1, -1),
                rpe(rel, self.cfg),
            ],
            dim=-1,
        )  # [B, N, M, 2d + rpe]
        logits = self.mlp(x)[..., 0]
        allowed = destination_mask(ag_type, mp.cls, mp.valid)
        usable = allowed.any(dim=-1) & ag_valid
        logits = logits.masked_fill(~allowed, float("-inf"))
        return torch.where(usable[..., None], logits, torch.zeros_like(logits)), usable


class DestinationEncoder(nn.Module):
    """``Linear(g_dest.detach()) + Linear(RPE(dest pose in the agent frame))``, every step."""

    def __init__(self, cfg: TrafficBotsConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.feat_proj = nn.Linear(cfg.hidden_dim, cfg.hidden_dim)
        self.pose_proj = nn.Linear(cfg.rpe_dim, cfg.hidden_dim)

    def forward(self, ag_pose: torch.Tensor, dest: torch.Tensor, mp: MapTokens) -> torch.Tensor:
        """Encode.

        Args:
            ag_pose: [B, N, 3] current agent token pose.
            dest: [B, N] int64 destination map rows (any value where unused; clamped).
            mp: encoded map.

        Returns:
            [B, N, d].
        """
        b = torch.arange(dest.shape[0], device=dest.device)[:, None]
        rows = dest.clamp(min=0)
        rel = relative_pose(ag_pose, mp.pose[b, rows])  # [B, N, 3]
        return self.feat_proj(mp.feat[b, rows].detach()) + self.pose_proj(rpe(rel, self.cfg))


def destination_reached(
    ag_pose: torch.Tensor, dest: torch.Tensor, mp: MapTokens, cfg: TrafficBotsConfig
) -> torch.Tensor:
    """Reached check (docs/model.md §5.2 step 7).

    Lane destinations: within ``dest_reach_lane_dist`` of some node whose direction is within
    ``dest_reach_lane_yaw`` of the agent heading. Road-edge (class 4): within
    ``dest_reach_edge_dist`` of some node.

    Args:
        ag_pose: [B, N, 3].
        dest: [B, N] int64 map rows (-1: never reached).
        mp: encoded map (node poses).
        cfg: network configuration.

    Returns:
        [B, N] bool.
    """
    b = torch.arange(dest.shape[0], device=dest.device)[:, None]
    rows = dest.clamp(min=0)
    nodes = mp.node_pose[b, rows]  # [B, N, P, 3]
    node_valid = mp.node_valid[b, rows]  # [B, N, P]
    dist = torch.linalg.vector_norm(nodes[..., :2] - ag_pose[:, :, None, :2], dim=-1)
    dyaw = wrap_angle(nodes[..., 2] - ag_pose[:, :, None, 2]).abs()
    lane_hit = node_valid & (dist < cfg.dest_reach_lane_dist) & (dyaw < cfg.dest_reach_lane_yaw)
    edge_hit = node_valid & (dist < cfg.dest_reach_edge_dist)
    is_edge = mp.cls[b, rows] == int(MapClass.ROAD_EDGE_BOUNDARY)
    reached = torch.where(is_edge, edge_hit.any(-1), lane_hit.any(-1))
    return reached & (dest >= 0)
