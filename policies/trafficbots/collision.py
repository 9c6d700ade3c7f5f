"""Batched WOSAC-style collision check between rounded boxes (docs/model.md §7.2).

Each box (length, width) is scaled by 1.1; its corners are rounded with radius
``s = 0.7 * min(l, w) / 2``, i.e. it is the inner box (l - 2s, w - 2s) dilated by a disc of
radius s. Two such boxes collide when the inner boxes overlap, or when the distance between the
inner boxes is below ``s_i + s_j`` (equivalently: signed distance of the origin to the Minkowski
difference of the inner boxes, minus s_i + s_j, is negative).
"""

from __future__ import annotations

import torch

from tbsim_env.core.boxes import box_corners
from tbsim_env.sim.geometry import segment_projection

CORNER_ROUNDING_FACTOR = 0.7
COLLISION_SIZE_SCALE = 1.1


def _point_segment_distance(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """|p - closest point of segment ab| for broadcastable [..., 2] inputs."""
    return segment_projection(p, a, b - a)[1]


def _boxes_overlap(ca: torch.Tensor, cb: torch.Tensor) -> torch.Tensor:
    """Separating-axis test of two convex quadrilaterals given by corners [..., 4, 2]."""
    edges = torch.cat([ca.roll(-1, -2) - ca, cb.roll(-1, -2) - cb], dim=-2)  # [..., 8, 2]
    normals = torch.stack([-edges[..., 1], edges[..., 0]], dim=-1)  # [..., 8, 2]
    proj_a = torch.einsum("...kc,...ac->...ka", normals, ca)  # [..., 8, 4]
    proj_b = torch.einsum("...kc,...ac->...ka", normals, cb)
    separated = (proj_a.amax(-1) < proj_b.amin(-1)) | (proj_b.amax(-1) < proj_a.amin(-1))
    return ~separated.any(-1)


def rounded_box_collision(
    pose_a: torch.Tensor,
    size_a: torch.Tensor,
    pose_b: torch.Tensor,
    size_b: torch.Tensor,
    factor: float = CORNER_ROUNDING_FACTOR,
    scale: float = COLLISION_SIZE_SCALE,
) -> torch.Tensor:
    """Do two rounded boxes collide?

    Args:
        pose_a: [..., 3] (x, y, yaw).
        size_a: [..., 2] (length, width) m, unscaled.
        pose_b: [..., 3], broadcastable against ``pose_a``.
        size_b: [..., 2].
        factor: corner-rounding factor (0.7).
        scale: size scale (1.1).

    Returns:
        [...] bool.
    """
    la, wa = size_a[..., 0] * scale, size_a[..., 1] * scale
    lb, wb = size_b[..., 0] * scale, size_b[..., 1] * scale
    ra = factor * torch.minimum(la, wa) / 2
    rb = factor * torch.minimum(lb, wb) / 2
    ca = box_corners(pose_a, la - 2 * ra, wa - 2 * ra)  # [..., 4, 2], inner boxes
    cb = box_corners(pose_b, lb - 2 * rb, wb - 2 * rb)
    ca, cb = torch.broadcast_tensors(ca, cb)
    # Distance between disjoint convex polygons: the smallest vertex-to-edge distance.
    d_ab = _point_segment_distance(
        ca[..., :, None, :], cb[..., None, :, :], cb.roll(-1, -2)[..., None, :, :]
    )
    d_ba = _point_segment_distance(
        cb[..., :, None, :], ca[..., None, :, :], ca.roll(-1, -2)[..., None, :, :]
    )
    dist = torch.minimum(d_ab.flatten(-2).amin(-1), d_ba.flatten(-2).amin(-1))
    return _boxes_overlap(ca, cb) | (dist < ra + rb)


def collision_flags(
    pose: torch.Tensor,
    valid: torch.Tensor,
    size: torch.Tensor,
    start: int,
    steps_per_chunk: int = 16,
) -> torch.Tensor:
    """Per-agent collision flag, OR-ed over steps ``start`` .. T-1, all pairs of valid agents.

    Broad phase first: a rounded box lies inside its scaled box, hence inside the circle of
    half its scaled diagonal, so two boxes whose centres are farther apart than the sum of
    those radii cannot touch. The exact ``rounded_box_collision`` runs only on the pairs
    (i < j) and steps that pass, a few percent of all of them in traffic. Steps are taken
    ``steps_per_chunk`` at a time to bound the [B, N, N, chunk] broad-phase memory.

    Args:
        pose: [B, N, T, 3].
        valid: [B, N, T] bool.
        size: [B, N, >=2] (length, width, ...) m.
        start: first step checked.
        steps_per_chunk: steps per broad-phase chunk.

    Returns:
        [B, N] bool.
    """
    n_sc, n_ag, n_t = valid.shape
    lw = size[..., :2]
    reach = 0.5 * COLLISION_SIZE_SCALE * torch.linalg.vector_norm(lw, dim=-1)  # [B, N]
    reach2 = (reach[:, :, None] + reach[:, None, :]).square()[..., None]  # [B, N, N, 1]
    upper = torch.ones(n_ag, n_ag, dtype=torch.bool, device=pose.device).triu(1)[..., None]
    flags = torch.zeros((n_sc, n_ag), dtype=torch.bool, device=pose.device)
    for t0 in range(start, n_t, steps_per_chunk):
        p, v = pose[:, :, t0 : t0 + steps_per_chunk], valid[:, :, t0 : t0 + steps_per_chunk]
        x, y = p[..., 0], p[..., 1]  # [B, N, C]
        d2 = (x[:, :, None] - x[:, None]).square() + (y[:, :, None] - y[:, None]).square()
        near = (d2 <= reach2) & v[:, :, None] & v[:, None] & upper  # [B, N, N, C]
        b, i, j, t = near.nonzero(as_tuple=True)
        if len(b) == 0:
            continue
        hit = rounded_box_collision(p[b, i, t], lw[b, i], p[b, j, t], lw[b, j])
        flags[b[hit], i[hit]] = True
        flags[b[hit], j[hit]] = True
    return flags
