"""KNARPE attention (K-nearest-neighbour attention with relative pose encoding) and the two
pre-LayerNorm transformer layers built on it (docs/model.md §2.5 and §3)."""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
import torch.nn.functional as F
from torch import nn

from tbsim_env.core import constants as C
from tbsim_env.core.torch_utils import gather_rows


class Neighbours(NamedTuple):
    """Each token's neighbour rows in a source and their relative pose encodings.

    Attributes:
        idx: [B, N, K] int64 rows of the source.
        mask: [B, N, K] bool, valid neighbours.
        rpe: [B, N, K, rpe_dim] relative pose encodings.
    """

    idx: torch.Tensor
    mask: torch.Tensor
    rpe: torch.Tensor


class KnarpeAttention(nn.Module):
    """Multi-head attention of each query over its own K neighbours, rows of a source.

    ``q_i = W_q x_i``, ``k_ij = W_k s_j + r^k_ij``, ``v_ij = W_v s_j + r^v_ij`` with
    ``[r^k, r^v] = W_r RPE_ij + b_r``; queries get no RPE. A query without a valid neighbour
    outputs zeros.

    The products are factored so that nothing d-wide is made per (query, neighbour, layer)
    except the gathered source projections (docs/model.md §2.5 gives the formula, not the order):

    * ``W_k`` and ``W_v`` project the S source rows once, and the projections are gathered
      (instead of projecting S' >= S gathered copies);
    * ``q_i . (W_rk RPE_ij)`` is ``(W_rk^T q_i) . RPE_ij``, and
      ``sum_j a_ij W_rv RPE_ij`` is ``W_rv (sum_j a_ij RPE_ij)``, so ``W_r`` acts once per
      query instead of once per pair;
    * per-head products over the neighbours run as one batched matmul per query with a
      block-diagonal query (or weight) matrix, so no operand is permuted into a copy.

    This is the same function as the direct transcription (``knarpe_reference``, kept for
    tests and ``bench/policy_step.py``) up to float rounding, with the same parameters.

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
        self.rpe_proj = nn.Linear(rpe_dim, 2 * dim)  # PyTorch default init (docs/model.md §2.5)
        self.dropout = nn.Dropout(dropout)
        nn.init.xavier_uniform_(self.in_proj_weight)
        nn.init.xavier_uniform_(self.out_proj.weight)
        nn.init.zeros_(self.out_proj.bias)

    def project_source(self, src: torch.Tensor) -> torch.Tensor:
        """Keys and values of source rows: [B, S, d] -> [B, S, 2d] (``W_k s_j + b_k``,
        ``W_v s_j + b_v``). A source that does not change between calls (the map) can be
        projected once and passed to ``attend`` each time."""
        d = self.n_heads * self.head_dim
        return F.linear(src, self.in_proj_weight[d:], self.in_proj_bias[d:])

    def forward(
        self,
        x: torch.Tensor,
        src: torch.Tensor,
        idx: torch.Tensor,
        rpe: torch.Tensor,
        mask: torch.Tensor,
        dense: bool | None = None,
    ) -> torch.Tensor:
        """Attend (``attend`` on ``project_source(src)``).

        Args:
            x: [B, Q, d] query features.
            src: [B, S, d] source features; query i's neighbours are rows ``idx[:, i]``.
            idx, rpe, mask, dense: as ``attend``.

        Returns:
            [B, Q, d].
        """
        return self.attend(x, self.project_source(src), idx, rpe, mask, dense)

    def attend(
        self,
        x: torch.Tensor,
        kv: torch.Tensor,
        idx: torch.Tensor,
        rpe: torch.Tensor,
        mask: torch.Tensor,
        dense: bool | None = None,
    ) -> torch.Tensor:
        """Attend over projected source rows.

        Args:
            x: [B, Q, d] query features.
            kv: [B, S, 2d] ``project_source`` of the source rows.
            idx: [B, Q, K] int64 neighbour rows of the source (any value where masked).
            rpe: [B, Q, K, rpe_dim] encoding of each neighbour's pose in the query frame.
            mask: [B, Q, K] bool valid neighbours.
            dense: score every source row and pick the neighbours' scores (True), or gather
                the neighbours' projected rows (False). None picks the one with the smaller
                per-query intermediate (dense when h S <= 2 d K), the faster one in
                ``bench/policy_step.py``'s shapes. Both give the same result.

        Returns:
            [B, Q, d].
        """
        h, d = self.n_heads, x.shape[-1]
        n_b, n_q, n_src, n_k = x.shape[0], x.shape[1], kv.shape[1], idx.shape[-1]
        if dense is None:
            dense = h * n_src <= 2 * d * n_k
        # On a CPU the large per-batch intermediates ([B, h, Q, S] scores or [B, Q, K, 2d]
        # gathered rows) fall out of the caches and into fresh pages: one call on 64 rollouts
        # of a real scene took 121 ms, 64 calls on one rollout 54 ms. Chunks of the batch keep
        # each call's working set small.
        # Not with active dropout, whose draws would then depend on the chunking.
        per_row = n_q * (h * n_src if dense else 2 * d * n_k)
        rows = max(1, C.CPU_ATTENTION_CHUNK_ELEMENTS // per_row)
        active_dropout = self.training and getattr(self.dropout, "p", 1.0) > 0
        if x.device.type != "cpu" or rows >= n_b or active_dropout:
            return self._attend(x, kv, idx, rpe, mask, dense)
        chunks = [
            self._attend(*(t[i : i + rows] for t in (x, kv, idx, rpe, mask)), dense)
            for i in range(0, n_b, rows)
        ]
        return torch.cat(chunks)

    def _attend(
        self,
        x: torch.Tensor,
        kv: torch.Tensor,
        idx: torch.Tensor,
        rpe: torch.Tensor,
        mask: torch.Tensor,
        dense: bool,
    ) -> torch.Tensor:
        """``attend`` on one chunk of the batch (``dense`` decided)."""
        h, c = self.n_heads, self.head_dim
        d = h * c
        w_q, b_q = self.in_proj_weight[:d], self.in_proj_bias[:d]
        w_rk, w_rv = self.rpe_proj.weight.view(2, h, c, -1).unbind(0)  # [h, c, r] each
        # The key part of b_r adds q_i . b_rk to every logit of query i and head h alike, so
        # it cancels in the softmax; only the value part acts.
        b_rv = self.rpe_proj.bias[d:].view(h, c)
        q = F.linear(x, w_q, b_q).unflatten(-1, (h, c)) / math.sqrt(c)  # [B, Q, h, c]
        q_rpe = torch.einsum("bqhc,hcr->bqrh", q, w_rk)  # [B, Q, r, h]
        logits = rpe @ q_rpe  # [B, Q, K, h]
        if dense:
            k_src, v_src = kv.unflatten(-1, (2, h, c)).unbind(-3)
            scores = q.transpose(1, 2) @ k_src.permute(0, 2, 3, 1)  # [B, h, Q, S]
            pick = idx[:, None].expand(-1, h, -1, -1)  # [B, h, Q, K]
            logits = logits + scores.gather(-1, pick).permute(0, 2, 3, 1)
        else:
            kv_nb = gather_rows(kv, idx)  # [B, Q, K, 2d]
            k, v = kv_nb[..., :d], kv_nb[..., d:]  # views, [B, Q, K, d]
            eye = torch.eye(h, dtype=x.dtype, device=x.device)
            q_blk = (q[..., None] * eye[:, None, :]).flatten(-3, -2)  # [B, Q, d, h] block diag
            logits = logits + k @ q_blk
        any_valid = mask.any(dim=-1)  # [B, Q]
        # Rows without a valid neighbour attend uniformly (no NaN) and are zeroed below.
        keep = mask | ~any_valid[..., None]
        logits = logits.masked_fill(~keep[..., None], float("-inf"))
        # Softmax in float32 on every device (CUDA's autocast does so; CPU's would not).
        attn = self.dropout(torch.softmax(logits, dim=-2, dtype=torch.float32))
        attn = attn.transpose(-1, -2)  # [B, Q, h, K]
        if dense:
            weights = attn.new_zeros(scores.shape).scatter_add_(-1, pick, attn.transpose(1, 2))
            out = (weights @ v_src.transpose(1, 2)).transpose(1, 2)  # [B, Q, h, c]
        else:
            out = (attn @ v).unflatten(-1, (h, c))  # [B, Q, h, h, c]: head g's weights, head h
            out = out.diagonal(dim1=-3, dim2=-2).transpose(-1, -2)  # [B, Q, h, c]
        out = out + torch.einsum("bqhr,hcr->bqhc", attn @ rpe, w_rv)
        out = out + attn.sum(-1)[..., None] * b_rv  # sum_j a_ij is 1 unless dropout is on
        return self.out_proj(out.flatten(-2)) * any_valid[..., None]


def knarpe_reference(
    attn: KnarpeAttention,
    x: torch.Tensor,
    src: torch.Tensor,
    idx: torch.Tensor,
    rpe: torch.Tensor,
    mask: torch.Tensor,
) -> torch.Tensor:
    """``attn`` computed as docs/model.md §2.5 writes it: gather, then project every (query,
    neighbour) pair. The oracle of ``KnarpeAttention`` in the tests and its baseline in
    ``bench/policy_step.py``; same arguments and result."""
    h, c = attn.n_heads, attn.head_dim
    w_q, w_k, w_v = attn.in_proj_weight.chunk(3, dim=0)
    b_q, b_k, b_v = attn.in_proj_bias.chunk(3, dim=0)
    kv = gather_rows(src, idx)  # [B, Q, K, d]
    q = F.linear(x, w_q, b_q).unflatten(-1, (h, c))  # [B, Q, h, c]
    r_k, r_v = attn.rpe_proj(rpe).chunk(2, dim=-1)  # [B, Q, K, d] each
    k = (F.linear(kv, w_k, b_k) + r_k).unflatten(-1, (h, c))  # [B, Q, K, h, c]
    v = (F.linear(kv, w_v, b_v) + r_v).unflatten(-1, (h, c))  # [B, Q, K, h, c]
    logits = torch.einsum("...hc,...khc->...hk", q, k) / math.sqrt(c)  # [B, Q, h, K]
    any_valid = mask.any(dim=-1)
    keep = mask | ~any_valid[..., None]
    logits = logits.masked_fill(~keep[..., None, :], float("-inf"))
    p = attn.dropout(torch.softmax(logits, dim=-1))
    out = torch.einsum("...hk,...khc->...hc", p, v).flatten(-2)  # [B, Q, d]
    return attn.out_proj(out) * any_valid[..., None]


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
        x = x + self.dropout(self.attn(h, h, idx, rpe, mask))
        x = x + self.ffn(self.norm2(x))
        return x * valid[..., None]


class DecoderLayer(nn.Module):
    """Pre-LN self + cross layer ("dec_cross_attn"), used by the TL and agent encoders.

    The cross-attention context (other-type source tokens and each token's neighbour rows in
    them) is fixed across layers; the same-type neighbours are rows of the current ``x``. The
    layer takes the context as its keys and values (``context_kv``), so that a caller whose
    context does not change between steps (the map) projects it once.
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
        own: Neighbours,
        ctx_kv: torch.Tensor,
        ctx_nb: Neighbours,
    ) -> torch.Tensor:
        """One layer.

        Args:
            x: [B, N, d] tokens.
            valid: [B, N] bool.
            own: same-type neighbours (rows of ``x``), K = Ks.
            ctx_kv: [B, S, 2d] ``context_kv`` of the other-type source tokens.
            ctx_nb: each token's neighbours among the context rows, K = Kc.

        Returns:
            [B, N, d], zero for invalid tokens.
        """
        h = self.norm_self(x)
        x = x + self.dropout(self.self_attn(h, h, own.idx, own.rpe, own.mask))
        cross = self.cross_attn.attend(self.norm1(x), ctx_kv, ctx_nb.idx, ctx_nb.rpe, ctx_nb.mask)
        x = x + self.dropout(cross)
        x = x + self.ffn(self.norm2(x))
        return x * valid[..., None]

    def context_kv(self, ctx: torch.Tensor) -> torch.Tensor:
        """Cross-attention keys and values of context tokens: [B, S, d] -> [B, S, 2d].

        Per row (LayerNorm, then the projection), so the rows of a concatenated context are
        those of its parts.
        """
        return self.cross_attn.project_source(self.norm_ctx(ctx))
