"""Oriented-box overlap (separating axis theorem), batched over all pairs."""

from __future__ import annotations

import torch

from tbsim_env.core.torch_utils import cached, cached_arange, const, true_index

# The separating-axis test of two boxes a and b, (x, y, yaw, length, width) each, on the
# columns of one table [..., 15]: a's box (0-4), b's (5-9) and b - a (10-14). The four
# candidate axes (a's length and width axes, b's) go along the last dim, so that the test is
# a few operations on [..., 4] blocks whatever the number of pairs:
#   axis k separates when |dx c1_k + dy c2_k| > h_k + m_k cd_k + n_k sd_k
# with (c1, c2) = (cos, sin) a, (-sin, cos) a, (cos, sin) b, (-sin, cos) b (the unit axis),
# h = half (length a, width a, length b, width b), (m, n) the other box's half length and
# width, and (cd, sd) = |cos|, |sin| of yaw_b - yaw_a (swapped on the width axes), each sum
# in the order that writes it out term by term.
_SAT_YAWS = (12, 2, 7)
"""Table columns of yaw_b - yaw_a, yaw_a, yaw_b: their cos are trig columns 0-2, sin 3-5."""
_SAT_TRIG = (1, 4, 2, 5, 4, 1, 5, 2, 0, 3, 0, 3, 3, 0, 3, 0)
"""Trig columns of c1 (sign in ``_SAT_SIGN``), c2, cd, sd (four each, one per axis)."""
_SAT_SIGN = (1.0, -1.0, 1.0, -1.0)
_SAT_SIZES = (3, 4, 8, 9, 8, 8, 3, 3, 9, 9, 4, 4)
"""Table columns of h, m and n (four each, one per axis): full sizes, halved once."""


def boxes_overlap(box_a: torch.Tensor, box_b: torch.Tensor) -> torch.Tensor:
    """Whether box a overlaps box b (touching counts as overlap), broadcast over the leading
    dims: the separating axis theorem, no axis of a or b separates them.

    Args:
        box_a: [..., 5] (x m, y m, yaw rad, length m, width m).
        box_b: [..., 5], broadcastable with ``box_a``.

    Returns:
        [...] bool, the broadcast shape.
    """
    diff = box_b - box_a
    if box_a.shape != diff.shape or box_b.shape != diff.shape:
        box_a, box_b = box_a.expand_as(diff), box_b.expand_as(diff)
    table = torch.cat([box_a, box_b, diff], -1)  # [..., 15]
    yaw = table.index_select(-1, _index(_SAT_YAWS, table))
    trig = torch.cat([yaw.cos(), yaw.sin()], -1).index_select(-1, _index(_SAT_TRIG, table))
    cdsd = trig[..., 8:].abs_()  # the gathered copy's own memory
    sizes = table.index_select(-1, _index(_SAT_SIZES, table)) * const(0.5, table)
    c1 = trig[..., :4] * const(_SAT_SIGN, trig)
    reach = (diff[..., 0:1] * c1 + diff[..., 1:2] * trig[..., 4:8]).abs_()
    limit = sizes[..., :4] + sizes[..., 4:8] * cdsd[..., :4] + sizes[..., 8:] * cdsd[..., 4:]
    return ~(reach > limit).any(-1)


def _index(columns: tuple[int, ...], like: torch.Tensor) -> torch.Tensor:
    """``columns`` as a cached int64 index on ``like``'s device."""
    return cached(("sat", columns, like.device), lambda: torch.tensor(columns, device=like.device))


def pairwise_overlap(
    pose_a: torch.Tensor,
    size_a: torch.Tensor,
    pose_b: torch.Tensor,
    size_b: torch.Tensor,
) -> torch.Tensor:
    """Whether each box of set a overlaps each box of set b (touching counts as overlap):
    ``boxes_overlap`` of every pair.

    Args:
        pose_a: [..., Na, 3] (x, y, yaw); size_a: [..., Na, 2] (length, width).
        pose_b: [..., Nb, 3]; size_b: [..., Nb, 2].

    Returns:
        [..., Na, Nb] bool.
    """
    return boxes_overlap(_boxes(pose_a, size_a).unsqueeze(-2), _boxes(pose_b, size_b).unsqueeze(-3))


def _boxes(pose: torch.Tensor, size: torch.Tensor) -> torch.Tensor:
    """[..., N, 5] boxes of poses [..., N, 3] and sizes [..., N, 2] (leading dims broadcast)."""
    if pose.shape[:-1] != size.shape[:-1]:
        lead = torch.broadcast_shapes(pose.shape[:-1], size.shape[:-1])
        pose, size = pose.expand(*lead, 3), size.expand(*lead, 2)
    return torch.cat([pose, size], -1)


def near_limits(
    query: torch.Tensor,
    size_q: torch.Tensor,
    size: torch.Tensor,
    slots: torch.Tensor | None = None,
) -> torch.Tensor:
    """Bounding-circle prefilter distances of K query agents to every agent slot, or to the
    slots ``slots``.

    Args:
        query: [B, K] int64 agent slots; size_q: [B, K, 2] their (length, width).
        size: [B, N, 2] (length, width) of every slot, or [B, C, 2] of the slots ``slots``.
        slots: optional [B, C] int64, the slot of each row of ``size`` (``valid_first``).

    Returns:
        [B, K, N or C] m: the sum of the two bounding-circle radii (half diagonals), -inf for
        the query agent itself (so that no distance passes the prefilter).
    """
    radius = const(0.5, size) * torch.linalg.vector_norm(size, dim=-1)  # [B, N]
    radius_q = const(0.5, size_q) * torch.linalg.vector_norm(size_q, dim=-1)  # [B, K]
    limit = radius.unsqueeze(1) + radius_q.unsqueeze(-1)
    if slots is None:
        itself = cached_arange(size.shape[1], size.device) == query.unsqueeze(-1)
    else:
        itself = slots.unsqueeze(1) == query.unsqueeze(-1)
    return limit.masked_fill(itself, float("-inf"))


def agent_distances(pose_q: torch.Tensor, pose: torch.Tensor) -> torch.Tensor:
    """[B, K, N] m centre distances of K query poses [B, K, 3] to every pose [B, N, 3].

    x and y apart and ``hypot`` (no [B, K, N, 2] difference and no norm over a dim of 2: a
    third of the time of ``vector_norm``)."""
    dx = pose[:, None, :, 0] - pose_q[:, :, None, 0]
    dy = pose[:, None, :, 1] - pose_q[:, :, None, 1]
    return torch.hypot(dx, dy)


def collided_with_others(
    pose_q: torch.Tensor,
    size_q: torch.Tensor,
    pose: torch.Tensor,
    size: torch.Tensor,
    valid: torch.Tensor,
    near_limit: torch.Tensor,
    cos_sin_q: tuple[torch.Tensor, torch.Tensor] | None = None,
    gap: torch.Tensor | None = None,
) -> torch.Tensor:
    """Collision flag of K query agents against every other valid agent (``collided``'s rule).

    The bounding-circle prefilter and the box test of ``collided`` on the same values, laid
    out as [B, K, N] instead of gathered per query, so the per-step cost is a few operations.
    A query agent's own validity is not checked (the caller masks it).

    Args:
        pose_q: [B, K, 3] and size_q: [B, K, 2] the query agents' poses and (length, width).
        pose: [B, N, 3]; size: [B, N, 2] (length, width); valid: [B, N] bool.
        near_limit: [B, K, N] ``near_limits(query, size_q, size)`` of the query slots (fixed
            while the sizes are; -inf at each query agent itself, which is never a partner).
        cos_sin_q: optional ``cos_sin`` of the query yaws, [B, K, 1] each.
        gap: optional ``agent_distances(pose_q, pose)`` [B, K, N].

    Returns:
        [B, K] bool.
    """
    if gap is None:
        gap = agent_distances(pose_q, pose)
    near = (gap <= near_limit) & valid.unsqueeze(1)  # [B, K, N]
    box_q, box = _boxes(pose_q, size_q), _boxes(pose, size)
    if torch.compiler.is_compiling():
        # A compiled graph cannot size tensors by data: it tests every pair (fused into few
        # kernels).
        return (near & boxes_overlap(box_q.unsqueeze(2), box.unsqueeze(1))).any(-1)
    # Eagerly, only the near pairs (a few per agent) get the box test.
    b, k, n = near.shape
    flat = true_index(near)  # (row K + query) N + slot
    out = torch.zeros(b * k, dtype=torch.bool, device=near.device)
    if not len(flat):
        return out.view(b, k)
    qi = flat.div(n, rounding_mode="floor")  # the query's row in [B K]
    # The partner's row in [B N]: row N + slot = flat - (query) N.
    si = flat if k == 1 else flat - (qi - qi.div(k, rounding_mode="floor")) * n
    hit = boxes_overlap(box_q.view(b * k, 5)[qi], box.view(b * n, 5)[si])
    return out.index_put_((qi,), hit, accumulate=True).view(b, k)


def collided(
    pose: torch.Tensor, size: torch.Tensor, valid: torch.Tensor, query: torch.Tensor | None = None
) -> torch.Tensor:
    """Per-agent collision flag against every other valid agent.

    Args:
        pose: [B, N, 3]; size: [B, N, 2] (length, width); valid: [B, N] bool.
        query: optional [B, N] bool, compute only for these agents (others return False);
            all valid agents by default. Restricting the query keeps the cost O(K N).

    Returns:
        [B, N] bool.
    """
    if query is None:
        query = valid
    q = query & valid
    out = torch.zeros_like(valid)
    if not bool(q.any()):
        return out
    b_idx, n_idx = torch.nonzero(q, as_tuple=True)
    # Bounding circles first: without a close pair no box test is needed.
    radius = 0.5 * torch.linalg.vector_norm(size, dim=-1)  # [B, N]
    gap = torch.linalg.vector_norm(pose[b_idx, :, :2] - pose[b_idx, n_idx, None, :2], dim=-1)
    near = (gap <= radius[b_idx] + radius[b_idx, n_idx, None]) & valid[b_idx]
    near[torch.arange(len(n_idx)), n_idx] = False
    if not bool(near.any()):
        return out
    overlap = pairwise_overlap(
        pose[b_idx, n_idx][:, None], size[b_idx, n_idx][:, None], pose[b_idx], size[b_idx]
    )[:, 0]  # [K, N]
    overlap &= near
    out[b_idx, n_idx] = overlap.any(-1)
    return out
