"""KNARPE attention (K-nearest-neighbour attention with relative pose encoding) and the two
pre-LayerNorm transformer layers built on it (spec sections 2.5 and 3)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from tbsim_env.torch_utils import gather_rows


class KnarpeAttention(nn.Module):
    """Multi-head attention of each query over its own gathered neighbours.

    ``q_i = W_q x_i``, ``k_ij = W_k x_j + r^k_ij``, ``v_ij = W_v x_j + r^v_ij`` with
    ``[r^k, r^v] = W_r RPE_ij + b_r``; queries get no RPE. A query without a valid neighbour
    outputs zeros.

    Args:
        dim: token width d.
        n_heads: heads h (d_head = d / h).
        rpe_dim: width of the RPE input to W_r.
        dropout: dropout on the attention probabilities.
    """

    def __init__(self, dim: int, n_heads: int, rpe_dim: int, dropout: float = 0.1) -> None:
        super().__init__()
        self.n_heads = n_heads
        self.head_dim = dim // n_heads
        self.in_proj_weight = nn.Parameter(torch.empty(3 * dim, dim))
        self.in_proj_bias = nn.Parameter(torch.zeros(3 * dim))
        self.out_proj = nn.Linear(dim, dim)
        self.rpe_proj = nn.Linear(rpe_dim, 2 * dim)  # PyTorch default init (spec 2.5)
        self.dropout = nn.Dropout(dropout)
        nn.init.xavier_uniform_(self.in_proj_weight)
        nn.init.xavier_uniform_(self.out_proj.weight)
        nn.init.zeros_(self.out_proj.bias)

    def forward(
        self, x: torch.Tensor, kv: torch.Tensor, rpe: torch.Tensor, mask: torch.Tensor
    ) -> torch.Tensor:
        """Attend.

        Args:
            x: [B, Q, d] query features.
            kv: [B, Q, K, d] gathered neighbour features.
            rpe: [B, Q, K, rpe_dim] encoding of each neighbour's pose in the query frame.
            mask: [B, Q, K] bool valid neighbours.

        Returns:
            [B, Q, d].
        """
        w_q, w_k, w_v = self.in_proj_weight.chunk(3, dim=0)
        b_q, b_k, b_v = self.in_proj_bias.chunk(3, dim=0)
        h, c = self.n_heads, self.head_dim
        q = F.linear(x, w_q, b_q).unflatten(-1, (h, c))  # [B, Q, h, c]
        r_k, r_v = self.rpe_proj(rpe).chunk(2, dim=-1)  # [B, Q, K, d] each
        k = (F.linear(kv, w_k, b_k) + r_k).unflatten(-1, (h, c))  # [B, Q, K, h, c]
        v = (F.linear(kv, w_v, b_v) + r_v).unflatten(-1, (h, c))  # [B, Q, K, h, c]
        logits = torch.einsum("...hc,...khc->...hk", q, k) / math.sqrt(c)  # [B, Q, h, K]
        any_valid = mask.any(dim=-1)  # [B, Q]
        # Rows without a valid neighbour attend uniformly (no NaN) and are zeroed below.
        keep = mask | ~any_valid[..., None]
        logits = logits.masked_fill(~keep[..., None, :], float("-inf"))
        attn = self.dropout(torch.softmax(logits, dim=-1))
        out = torch.einsum("...hk,...khc->...hc", attn, v).flatten(-2)  # [B, Q, d]
        return self.out_proj(out) * any_valid[..., None]


class FeedForward(nn.Module):
    """``Drop(W2 Drop(ReLU(W1 x)))`` with inner width ff_mult * d."""

    def __init__(self, dim: int, inner: int, dropout: float) -> None:
        super().__init__()
        self.fc1 = nn.Linear(dim, inner)
        self.fc2 = nn.Linear(inner, dim)
        self.dropout = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """[..., d] -> [..., d]."""
        return self.dropout(self.fc2(self.dropout(torch.relu(self.fc1(x)))))


class SelfAttentionLayer(nn.Module):
    """Pre-LN self layer over same-type KNN neighbours ("enc_self_attn").

    Args:
        dim: token width.
        n_heads: heads.
        ff_dim: FFN inner width.
        rpe_dim: RPE width.
        dropout: dropout rate.
    """

    def __init__(self, dim: int, n_heads: int, ff_dim: int, rpe_dim: int, dropout: float) -> None:
        super().__init__()
        self.norm1 = nn.LayerNorm(dim)
        self.attn = KnarpeAttention(dim, n_heads, rpe_dim, dropout)
        self.norm2 = nn.LayerNorm(dim)
        self.ffn = FeedForward(dim, ff_dim, dropout)
        self.dropout = nn.Dropout(dropout)

    def forward(
        self,
        x: torch.Tensor,
        valid: torch.Tensor,
        idx: torch.Tensor,
        mask: torch.Tensor,
        rpe: torch.Tensor,
    ) -> torch.Tensor:
        """One layer.

        Args:
            x: [B, N, d] tokens.
            valid: [B, N] bool token validity.
            idx: [B, N, K] same-type neighbour rows.
            mask: [B, N, K] bool valid neighbours.
            rpe: [B, N, K, rpe_dim].

        Returns:
            [B, N, d], zero for invalid tokens.
        """
        h = self.norm1(x)
        x = x + self.dropout(self.attn(h, gather_rows(h, idx), rpe, mask))
        x = x + self.ffn(self.norm2(x))
        return x * valid[..., None]


class DecoderLayer(nn.Module):
    """Pre-LN self + cross layer ("dec_cross_attn"), used by the TL and agent encoders.

    The cross-attention context (other-type neighbour features) is gathered by the caller and
    fixed across layers; the same-type neighbours are re-gathered from the current ``x``.
    """

    def __init__(self, dim: int, n_heads: int, ff_dim: int, rpe_dim: int, dropout: float) -> None:
        super().__init__()
        self.norm_self = nn.LayerNorm(dim)
        self.self_attn = KnarpeAttention(dim, n_heads, rpe_dim, dropout)
        self.norm1 = nn.LayerNorm(dim)
        self.norm_ctx = nn.LayerNorm(dim)
        self.cross_attn = KnarpeAttention(dim, n_heads, rpe_dim, dropout)
        self.norm2 = nn.LayerNorm(dim)
        self.ffn = FeedForward(dim, ff_dim, dropout)
        self.dropout = nn.Dropout(dropout)

    def forward(
        self,
        x: torch.Tensor,
        valid: torch.Tensor,
        self_idx: torch.Tensor,
        self_mask: torch.Tensor,
        self_rpe: torch.Tensor,
        ctx: torch.Tensor,
        ctx_mask: torch.Tensor,
        ctx_rpe: torch.Tensor,
    ) -> torch.Tensor:
        """One layer.

        Args:
            x: [B, N, d] tokens.
            valid: [B, N] bool.
            self_idx: [B, N, Ks] same-type neighbour rows.
            self_mask: [B, N, Ks] bool.
            self_rpe: [B, N, Ks, rpe_dim].
            ctx: [B, N, Kc, d] other-type neighbour features (not normalised).
            ctx_mask: [B, N, Kc] bool.
            ctx_rpe: [B, N, Kc, rpe_dim].

        Returns:
            [B, N, d], zero for invalid tokens.
        """
        h = self.norm_self(x)
        x = x + self.dropout(self.self_attn(h, gather_rows(h, self_idx), self_rpe, self_mask))
        x = x + self.dropout(self.cross_attn(self.norm1(x), self.norm_ctx(ctx), ctx_rpe, ctx_mask))
        x = x + self.ffn(self.norm2(x))
        return x * valid[..., None]
