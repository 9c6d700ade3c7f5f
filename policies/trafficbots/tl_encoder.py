"""Traffic-light encoder and TL-state head (docs/model.md §3.2).

TL tokens sit on the map piece of their controlled lane (``tl_mode: lane``): pose = node 0 of
that piece. Everything that depends only on the static poses (KNN, RPE, map neighbour rows)
is precomputed once per scenario in a ``TLContext``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn

from policies.trafficbots.attention import DecoderLayer, Neighbours
from policies.trafficbots.config import TrafficBotsConfig
from policies.trafficbots.encodings import rpe
from policies.trafficbots.knn import knn_relative
from policies.trafficbots.map_encoder import MapTokens
from policies.trafficbots.mlp import MLP
from policies.trafficbots.pointnet import PointNet
from tbsim_env.core.constants import NUM_TL_STATES
from tbsim_env.core.torch_utils import listed
from tbsim_env.observation.rows import take_rows


def _rows(x: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
    """x [B, M, ...] at rows idx [B, L] -> [B, L, ...]."""
    b = torch.arange(x.shape[0], device=x.device)[:, None]
    return x[b, idx]


@dataclass(frozen=True)
class TLContext:
    """Static per-scenario TL tensors.

    Attributes:
        pose: [B, L, 3] token pose (node 0 of the controlled lane piece).
        valid: [B, L] bool token validity.
        lane_feat: [B, L, d] map feature of the lane piece, detached (docs/model.md §3.2 step 3).
        self_idx, self_mask, self_rpe: TL -> TL neighbours [B, L, Ks], [B, L, Ks],
            [B, L, Ks, rpe_dim].
        map_idx, map_mask, map_rpe: TL -> map neighbours, rows of the map tokens [B, L, Km],
            [B, L, Km], [B, L, Km, rpe_dim] (the encoder reads the map as ``TLEncoder.map_kv``
            of its features).
    """

    pose: torch.Tensor
    valid: torch.Tensor
    lane_feat: torch.Tensor
    self_idx: torch.Tensor
    self_mask: torch.Tensor
    self_rpe: torch.Tensor
    map_idx: torch.Tensor
    map_mask: torch.Tensor
    map_rpe: torch.Tensor


def tl_context(
    cfg: TrafficBotsConfig, tl_piece: torch.Tensor, tl_valid: torch.Tensor, mp: MapTokens
) -> TLContext:
    """Precompute the static TL tensors.

    Args:
        cfg: network configuration.
        tl_piece: [B, L] int64 map row of the controlled lane piece (-1 padding).
        tl_valid: [B, L] bool token validity (any valid step of the source used).
        mp: the encoded map.

    Returns:
        ``TLContext``.
    """
    rows = tl_piece.clamp(min=0)
    valid = tl_valid & (tl_piece >= 0) & _rows(mp.valid, rows)
    pose = _rows(mp.pose, rows) * valid[..., None]
    lane_feat = _rows(mp.feat, rows).detach() * valid[..., None]
    s_idx, s_mask, s_rel = knn_relative(pose, pose, valid, cfg.tl_knn, cfg.tl_dist)
    m_idx, m_mask, m_rel = knn_relative(pose, mp.pose, mp.valid, cfg.tl_map_knn, cfg.tl_map_dist)
    return TLContext(
        pose=pose,
        valid=valid,
        lane_feat=lane_feat,
        self_idx=s_idx,
        self_mask=s_mask,
        self_rpe=rpe(s_rel, cfg),
        map_idx=m_idx,
        map_mask=m_mask,
        map_rpe=rpe(m_rel, cfg),
    )


class TLEncoder(nn.Module):
    """Encode a window of TL states: MLP, PointNet over time, decoder layers (TL self, TL->map).

    Args:
        cfg: network configuration.
        n_time: length of the time one-hot (11 in the policy, 19 in the posterior).
    """

    def __init__(self, cfg: TrafficBotsConfig, n_time: int) -> None:
        super().__init__()
        d = cfg.hidden_dim
        self.n_time = n_time
        self.input_mlp = MLP([NUM_TL_STATES + n_time] + [d] * cfg.mlp_layers)
        self.pointnet = PointNet(d, cfg.pointnet_layers, cfg.dropout)
        self.layers = nn.ModuleList(
            DecoderLayer(d, cfg.n_heads, cfg.ff_mult * d, cfg.rpe_dim, cfg.dropout)
            for _ in range(cfg.tl_layers)
        )

    def map_kv(self, map_feat: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Each layer's keys and values of the map tokens [B, M, d] (features not detached):
        [B, M, 2d] per layer, what ``forward`` reads of the map.

        The map does not change during a rollout: ``prepare`` computes these once instead of
        projecting the map every step.
        """
        return tuple(layer.context_kv(map_feat) for layer in self.layers)

    def forward(
        self,
        state: torch.Tensor,
        step_valid: torch.Tensor,
        ctx: TLContext,
        map_kv: tuple[torch.Tensor, ...],
        previous: tuple[torch.Tensor, torch.Tensor] | None = None,
    ) -> torch.Tensor:
        """Encode.

        In inference, eagerly on the CPU (``torch_utils.listed``), only the scenes that need
        it are encoded: not those without a valid TL token (every token is 0 anyway; generated
        and real batches often mix scenes with and without signals), nor those whose window
        is the one of ``previous`` (their features are those).

        Args:
            state: [B, L, W] int64 ``TLState`` per window step (W <= n_time, newest last).
            step_valid: [B, L, W] bool, the window step exists.
            ctx: static TL tensors.
            map_kv: ``map_kv`` of the encoded map.
            previous: optional (same [B] bool, features [B, L, d]): the rows ``same`` have
                the window (``state`` and ``step_valid``) that ``features`` were encoded from,
                in the same ``ctx``; they keep those features.

        Returns:
            [B, L, d] TL token features (0 for invalid tokens).
        """
        need = ctx.valid.any(-1, keepdim=True)  # [B, 1]
        if previous is not None:
            need = need & ~previous[0][:, None]
        lit = None if self.training else listed(need)
        if lit is None:
            return self._encode(state, step_valid, ctx, map_kv)
        rows = lit[0]
        if previous is None:
            out = ctx.lane_feat.new_zeros(ctx.lane_feat.shape)  # [B, L, d]
        else:
            same, feat = previous
            out = feat * same[:, None, None].to(feat.dtype)
        if rows.numel():
            kv = tuple(t.index_select(0, rows) for t in map_kv)
            out[rows] = self._encode(state[rows], step_valid[rows], take_rows(ctx, rows), kv)
        return out

    def _encode(
        self,
        state: torch.Tensor,
        step_valid: torch.Tensor,
        ctx: TLContext,
        map_kv: tuple[torch.Tensor, ...],
    ) -> torch.Tensor:
        """``forward`` on every row of the batch."""
        x = self._step_features(state) + ctx.lane_feat[:, :, None]
        x = self.pointnet(x, step_valid & ctx.valid[..., None]) * ctx.valid[..., None]
        own = Neighbours(ctx.self_idx, ctx.self_mask, ctx.self_rpe)
        near_map = Neighbours(ctx.map_idx, ctx.map_mask, ctx.map_rpe)
        for layer, kv in zip(self.layers, map_kv, strict=True):
            x = layer(x, ctx.valid, own, kv, near_map)
        return x

    def _step_features(self, state: torch.Tensor) -> torch.Tensor:
        """``MLP([one_hot(state), one_hot(time)])`` per window step: [B, L, W] -> [B, L, W, d].

        Both inputs are categorical, so the MLP runs on the NUM_TL_STATES x W table of their
        pairs and each step picks its row (the same values, without a [B, L, W] MLP).
        """
        n_win = state.shape[-1]
        time_1h = torch.eye(self.n_time, device=state.device)[self.n_time - n_win :]  # [W, n_time]
        state_1h = torch.eye(NUM_TL_STATES, device=state.device)
        pairs = torch.cat(
            [
                state_1h[:, None].expand(-1, n_win, -1),
                time_1h[None].expand(NUM_TL_STATES, -1, -1),
            ],
            dim=-1,
        )  # [S, W, S + n_time]
        table = self.input_mlp(pairs)  # [S, W, d]
        steps = torch.arange(n_win, device=state.device)
        return table[state.clamp(0, NUM_TL_STATES - 1), steps]


class TLStateHead(nn.Module):
    """Next-TL-state logits from the detached TL token feature, clamped to [-3, 3]."""

    def __init__(self, cfg: TrafficBotsConfig) -> None:
        super().__init__()
        d = cfg.hidden_dim
        self.mlp = MLP([d] * cfg.mlp_layers + [NUM_TL_STATES])
        self.clamp = cfg.tl_logit_clamp

    def forward(self, feat: torch.Tensor) -> torch.Tensor:
        """[B, L, d] -> [B, L, 5] logits."""
        return self.mlp(feat.detach()).clamp(-self.clamp, self.clamp)
