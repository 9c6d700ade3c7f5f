"""Oriented-box overlap (separating axis theorem), batched over all pairs."""

from __future__ import annotations

from typing import NamedTuple

import torch

from tbsim_env.core.boxes import cos_sin
from tbsim_env.core.torch_utils import cached_arange, const


class _BoxPairs(NamedTuple):
    """What the separating-axis tests of boxes a against boxes b share, [..., Na, Nb]."""

    dx: torch.Tensor  # centre offset b - a, x
    dy: torch.Tensor
    ndx: torch.Tensor  # -dx
    la: torch.Tensor  # half length / width of a [..., Na, 1] and of b [..., 1, Nb]
    wa: torch.Tensor
    lb: torch.Tensor
    wb: torch.Tensor
    cd: torch.Tensor  # |cos|, |sin| of yaw_b - yaw_a
    sd: torch.Tensor
    yaw_b: torch.Tensor  # [..., 1, Nb]


def _box_pairs(
    pose_a: torch.Tensor, size_a: torch.Tensor, pose_b: torch.Tensor, size_b: torch.Tensor
) -> tuple[_BoxPairs, torch.Tensor]:
    """(``_BoxPairs`` of the boxes of ``pairwise_overlap``, yaw of a [..., Na, 1])."""
    xa, ya, yaw_a = pose_a.unsqueeze(-2).unbind(-1)  # [..., Na, 1]
    xb, yb, yaw_b = pose_b.unsqueeze(-3).unbind(-1)  # [..., 1, Nb]
    dx, dy = xb - xa, yb - ya  # [..., Na, Nb]
    half = const(0.5, size_a)
    la, wa = (half * size_a).unsqueeze(-2).unbind(-1)
    lb, wb = (half * size_b).unsqueeze(-3).unbind(-1)
    cd, sd = cos_sin(yaw_b - yaw_a)
    return _BoxPairs(dx, dy, -dx, la, wa, lb, wb, cd.abs(), sd.abs(), yaw_b), yaw_a


def _separated_on_axes_of_a(p: _BoxPairs, ca: torch.Tensor, sa: torch.Tensor) -> torch.Tensor:
    """[..., Na, Nb] bool: a's length or width axis (ca, sa), (-sa, ca) separates the pair."""
    sep = (p.dx * ca + p.dy * sa).abs() > p.la + p.lb * p.cd + p.wb * p.sd
    sep |= (p.ndx * sa + p.dy * ca).abs() > p.wa + p.lb * p.sd + p.wb * p.cd
    return sep


def _separated_on_axes_of_b(p: _BoxPairs) -> torch.Tensor:
    """[..., Na, Nb] bool: b's length or width axis separates the pair."""
    cb, sb = cos_sin(p.yaw_b)
    sep = (p.dx * cb + p.dy * sb).abs() > p.lb + p.la * p.cd + p.wa * p.sd
    sep |= (p.ndx * sb + p.dy * cb).abs() > p.wb + p.la * p.sd + p.wa * p.cd
    return sep


def pairwise_overlap(
    pose_a: torch.Tensor,
    size_a: torch.Tensor,
    pose_b: torch.Tensor,
    size_b: torch.Tensor,
) -> torch.Tensor:
    """Whether each box of set a overlaps each box of set b (touching counts as overlap).

    Separating axis theorem: no axis of a or b separates the pair.

    Args:
        pose_a: [..., Na, 3] (x, y, yaw); size_a: [..., Na, 2] (length, width).
        pose_b: [..., Nb, 3]; size_b: [..., Nb, 2].

    Returns:
        [..., Na, Nb] bool.
    """
    pairs, yaw_a = _box_pairs(pose_a, size_a, pose_b, size_b)
    sep = _separated_on_axes_of_a(pairs, *cos_sin(yaw_a))
    return ~(sep | _separated_on_axes_of_b(pairs))


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
    if not torch.compiler.is_compiling():
        # Eagerly, only the near pairs (a few per agent) get the box test. A compiled graph
        # cannot size tensors by data: it tests every pair (fused into few kernels).
        return _near_pairs_overlap(near, pose_q, size_q, pose, size)
    # ``pairwise_overlap & near``, b's axes only tested when a's leave a near pair unseparated.
    pairs, yaw_q = _box_pairs(pose_q, size_q, pose, size)
    near = near & ~_separated_on_axes_of_a(pairs, *(cos_sin_q or cos_sin(yaw_q)))
    return (near & ~_separated_on_axes_of_b(pairs)).any(-1)


def _near_pairs_overlap(
    near: torch.Tensor,
    pose_q: torch.Tensor,
    size_q: torch.Tensor,
    pose: torch.Tensor,
    size: torch.Tensor,
) -> torch.Tensor:
    """[B, K] bool: some pair flagged in ``near`` [B, K, N] overlaps (``pairwise_overlap`` of
    the gathered pairs, the same arithmetic; arguments as ``collided_with_others``)."""
    b, k, n = near.shape
    pairs = near.nonzero()  # [P, 3]: (row, query, slot)
    out = torch.zeros(b * k, dtype=torch.bool, device=near.device)
    if not len(pairs):
        return out.view(b, k)
    row, query, slot = pairs.unbind(1)
    qi = torch.add(query, row, alpha=k)  # the query's row in [B K]
    box_a = torch.cat([pose_q, size_q], -1).view(b * k, 5).index_select(0, qi)
    si = torch.add(slot, row, alpha=n)  # the partner's row in [B N]
    box_b = torch.cat([pose, size], -1).view(b * n, 5).index_select(0, si)
    hit = _rows_overlap(box_a, box_b)
    return out.index_put_((qi,), hit, accumulate=True).view(b, k)


def _rows_overlap(box_a: torch.Tensor, box_b: torch.Tensor) -> torch.Tensor:
    """[P] bool: box a of each row overlaps box b of the row (``pairwise_overlap``'s test and
    arithmetic): boxes [P, 5] (x, y, yaw, length, width)."""
    xa, ya, yaw_a, length_a, width_a = box_a.unbind(1)
    xb, yb, yaw_b, length_b, width_b = box_b.unbind(1)
    half = const(0.5, box_a)
    dx, dy = xb - xa, yb - ya
    la, wa, lb, wb = half * length_a, half * width_a, half * length_b, half * width_b
    cd, sd = cos_sin(yaw_b - yaw_a)
    cd, sd = cd.abs(), sd.abs()
    ndx = -dx
    ca, sa = cos_sin(yaw_a)
    sep = (dx * ca + dy * sa).abs() > la + lb * cd + wb * sd
    sep |= (ndx * sa + dy * ca).abs() > wa + lb * sd + wb * cd
    cb, sb = cos_sin(yaw_b)
    sep |= (dx * cb + dy * sb).abs() > lb + la * cd + wa * sd
    sep |= (ndx * sb + dy * cb).abs() > wb + la * sd + wa * cd
    return ~sep


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
