"""Oriented-box overlap (separating axis theorem), batched over all pairs."""

from __future__ import annotations

import torch

from tbsim_env.sim.geometry import cos_sin
from tbsim_env.torch_utils import cached_arange


def box_corners(pose: torch.Tensor, length: torch.Tensor, width: torch.Tensor) -> torch.Tensor:
    """Corners of oriented boxes, counter-clockwise from front-left.

    Args:
        pose: [..., 3] (x, y, yaw) of the box centre.
        length: [...] m along the heading.
        width: [...] m across.

    Returns:
        [..., 4, 2].
    """
    c, s = cos_sin(pose[..., 2])
    hl, hw = 0.5 * length, 0.5 * width
    signs = torch.tensor([[1.0, 1.0], [-1.0, 1.0], [-1.0, -1.0], [1.0, -1.0]], device=pose.device)
    lx = signs[:, 0] * hl[..., None]
    ly = signs[:, 1] * hw[..., None]
    x = pose[..., 0:1] + c[..., None] * lx - s[..., None] * ly
    y = pose[..., 1:2] + s[..., None] * lx + c[..., None] * ly
    return torch.stack([x, y], dim=-1)


def pairwise_overlap(
    pose_a: torch.Tensor,
    size_a: torch.Tensor,
    pose_b: torch.Tensor,
    size_b: torch.Tensor,
) -> torch.Tensor:
    """Whether each box of set a overlaps each box of set b (touching counts as overlap).

    Args:
        pose_a: [..., Na, 3] (x, y, yaw); size_a: [..., Na, 2] (length, width).
        pose_b: [..., Nb, 3]; size_b: [..., Nb, 2].

    Returns:
        [..., Na, Nb] bool.
    """
    d = pose_b[..., None, :, :2] - pose_a[..., :, None, :2]  # [..., Na, Nb, 2]
    ya = pose_a[..., :, None, 2]
    yb = pose_b[..., None, :, 2]
    la, wa = 0.5 * size_a[..., :, None, 0], 0.5 * size_a[..., :, None, 1]
    lb, wb = 0.5 * size_b[..., None, :, 0], 0.5 * size_b[..., None, :, 1]
    cd, sd = cos_sin(yb - ya)
    cd, sd = cd.abs(), sd.abs()
    ca, sa = cos_sin(ya)
    cb, sb = cos_sin(yb)
    # Axes of a: (ca, sa) and (-sa, ca); axes of b likewise.
    sep = (d[..., 0] * ca + d[..., 1] * sa).abs() > la + lb * cd + wb * sd
    sep |= (-d[..., 0] * sa + d[..., 1] * ca).abs() > wa + lb * sd + wb * cd
    sep |= (d[..., 0] * cb + d[..., 1] * sb).abs() > lb + la * cd + wa * sd
    sep |= (-d[..., 0] * sb + d[..., 1] * cb).abs() > wb + la * sd + wa * cd
    return ~sep


def collided_with_others(
    query: torch.Tensor,
    pose: torch.Tensor,
    size: torch.Tensor,
    valid: torch.Tensor,
) -> torch.Tensor:
    """Collision flag of K query agents against every other valid agent (``collided``'s rule).

    The bounding-circle prefilter and the box test of ``collided`` on the same values, laid
    out as [B, K, N] instead of gathered per query, so the per-step cost is a few operations.
    A query agent's own validity is not checked (the caller masks it).

    Args:
        query: [B, K] int64 agent slots.
        pose: [B, N, 3]; size: [B, N, 2] (length, width); valid: [B, N] bool.

    Returns:
        [B, K] bool.
    """
    b_idx = cached_arange(pose.shape[0], pose.device)[:, None]
    pose_q, size_q = pose[b_idx, query], size[b_idx, query]  # [B, K, 3], [B, K, 2]
    radius = 0.5 * torch.linalg.vector_norm(size, dim=-1)  # [B, N]
    gap = torch.linalg.vector_norm(pose[:, None, :, :2] - pose_q[:, :, None, :2], dim=-1)
    near = gap <= radius[:, None] + radius[b_idx, query][..., None]  # [B, K, N]
    others = cached_arange(pose.shape[1], pose.device) != query[..., None]
    near &= valid[:, None] & others
    if not bool(near.any()):
        return torch.zeros_like(query, dtype=torch.bool)
    return (pairwise_overlap(pose_q, size_q, pose, size) & near).any(-1)


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
