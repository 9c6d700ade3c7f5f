"""K-nearest-neighbour selection and gathering (docs/model.md §2.4)."""

from __future__ import annotations

import torch

from policies.trafficbots.encodings import relative_pose
from tbsim_env.core.torch_utils import gather_rows
from tbsim_env.observation.map_knn import PieceClusters, nearest_pieces


@torch.no_grad()
def knn_select(
    query_xy: torch.Tensor,
    target_xy: torch.Tensor,
    target_valid: torch.Tensor,
    k: int,
    dist_limit: float,
    clusters: PieceClusters | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Rank valid targets by 2-D distance and keep the ``k`` nearest within ``dist_limit``.

    For same-type attention the query itself is among the targets (distance 0), so it is
    selected (first, unless a target of a lower row lies within the resolution of it).
    ``k`` is capped at the number of targets.

    Ranked by ``tbsim_env.sim.knn.nearest_k``, the environment's rule: 1 cm distance buckets,
    ties broken by the lower target row. Equal distances are common: map pieces that start at
    the same node are equally far from everything, and in a symmetric generated map two lanes
    are equally far from an agent between them. Compared in full float32 precision, such a
    tie is decided by the rounding of the scene frame, so a rotated and shifted copy of the
    scene picked other neighbours (deviation from the reference, docs/model.md §2.4, which ranks
    exact distances). The selection does not depend on the device, on ``topk``'s algorithm or on
    padding rows after the targets either (``TokenBatch.trim``).

    The search is the observations' (``tbsim_env.observation.map_knn.nearest_pieces``): with the
    targets' ``clusters`` (a large map), eagerly on the CPU, it measures the pieces of the
    nearest clusters only, with the same result.

    Args:
        query_xy: [B, Q, 2] query positions.
        target_xy: [B, T, 2] target positions.
        target_valid: [B, T] bool.
        k: neighbours per query.
        dist_limit: neighbours farther than this are masked (metres).
        clusters: optional ``PieceClusters`` of the valid targets.

    Returns:
        (idx [B, Q, K] int64 rows of the targets, mask [B, Q, K] bool valid neighbours).
    """
    k = min(k, target_xy.shape[1])
    points = target_xy.masked_fill(~target_valid[..., None], float("inf"))[:, None]
    idx, dist = nearest_pieces(points, clusters, query_xy, k, dist_limit)
    return idx, dist <= dist_limit


def knn_relative(
    query_pose: torch.Tensor,
    target_pose: torch.Tensor,
    target_valid: torch.Tensor,
    k: int,
    dist_limit: float,
    clusters: PieceClusters | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """KNN selection plus the pose of each selected neighbour in the query frame.

    Args:
        query_pose: [B, Q, 3] (x, y, yaw).
        target_pose: [B, T, 3].
        target_valid: [B, T] bool.
        k: neighbours per query.
        dist_limit: range in metres.
        clusters: optional ``PieceClusters`` of the valid targets (``knn_select``).

    Returns:
        (idx [B, Q, K], mask [B, Q, K] bool, rel_pose [B, Q, K, 3]).
    """
    idx, mask = knn_select(
        query_pose[..., :2], target_pose[..., :2], target_valid, k, dist_limit, clusters
    )
    rel = relative_pose(query_pose[:, :, None, :], gather_rows(target_pose, idx))
    return idx, mask, rel
