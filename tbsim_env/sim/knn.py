"""The one rule that ranks neighbours by distance: 1 cm buckets, ties to the lower index.

Observations (``tbsim_env.observation.tokens``) and TrafficBots' attention neighbours
(``policies.trafficbots.knn``) both pick their k nearest targets with ``nearest_k``.

Distances rank in buckets of ``KNN_DISTANCE_RESOLUTION`` (1 cm) whose edges sit
``KNN_BUCKET_OFFSET`` of a bucket off round distances; inside a bucket the lower target id
wins. Targets equally far in exact arithmetic (map pieces starting at one node, mirrored
lanes) are then chosen the same way in any world frame, on any device and whatever the
padding after the targets: compared in full float32 precision, such a tie would be decided by
the rounding of the scene frame.

The rank is one integer key per target, ``bucket * 2**bits + id``, and one ``topk`` over it.
When the caller masks everything beyond ``exact_within`` metres anyway (its radius), the key
is an int32: the buckets beyond a bound well past that radius share the last one (which of
those far targets fills a masked entry is then decided by id). Half the bytes of the int64
key, built in place: this selection is the largest single cost of an observation.
"""

from __future__ import annotations

import math

import torch

from tbsim_env.core.constants import KNN_BUCKET_OFFSET, KNN_DISTANCE_RESOLUTION
from tbsim_env.core.torch_utils import cached_arange, cast, const, scalar

INT64_LAST_BUCKET = 2**30
"""Last bucket of the int64 key (1e7 m): +inf and anything farther share it."""
FLOAT32_EXACT = 2**24
"""Largest bucket of an int32 key: the clamp to it runs in float32, exact up to here."""
INT32_MIN_REACH = 2.0
"""An int32 key is used only when its last bucket lies this many times ``exact_within`` out."""


def _key_layout(num_ids: int, exact_within: float) -> tuple[torch.dtype, int, int]:
    """(key dtype, id bits, last bucket) for ids in [0, num_ids)."""
    bits = max(1, (max(num_ids, 1) - 1).bit_length())
    # The clamp runs in float32, exact up to 2**24.
    last32 = min(2 ** (31 - bits) - 1, FLOAT32_EXACT)
    reach = last32 * KNN_DISTANCE_RESOLUTION
    if math.isfinite(exact_within) and reach >= INT32_MIN_REACH * exact_within:
        return torch.int32, bits, last32
    return torch.int64, 32, INT64_LAST_BUCKET


def nearest_k(
    dist: torch.Tensor,
    k: int,
    ids: torch.Tensor | None = None,
    num_ids: int | None = None,
    exact_within: float = math.inf,
) -> torch.Tensor:
    """Positions [..., k] (along the last dim) of the k nearest targets, nearest first.

    Args:
        dist: [..., M] float distances, >= 0 or +inf (+inf: no target; ranked last).
        k: how many, <= M.
        ids: optional [..., M] int64 id of each column (a subset of the targets, e.g. search
            candidates); ties go to the lower id. The column index by default.
        num_ids: ids lie in [0, num_ids) (default: M; needed with ``ids``).
        exact_within: the caller masks targets farther than this (metres); the ranking is
            exact out to at least ``INT32_MIN_REACH`` times it (inf: everywhere).

    Returns:
        [..., k] int64 positions along the last dim of ``dist``.
    """
    m = dist.shape[-1]
    if ids is not None and num_ids is None:
        raise ValueError("nearest_k needs num_ids with ids")
    dtype, bits, last = _key_layout(m if ids is None else int(num_ids), exact_within)
    # The scaled distances are > 0, so truncation is the floor (``cast``); built in place.
    scaled = dist * const(1.0 / KNN_DISTANCE_RESOLUTION, dist) + const(KNN_BUCKET_OFFSET, dist)
    key = cast(scaled.clamp_max_(const(float(last), scaled)), dtype)
    col = cached_arange(m, dist.device, dtype) if ids is None else ids
    key.bitwise_left_shift_(scalar(bits, dtype, dist.device)).bitwise_or_(col)
    return torch.topk(key, k, dim=-1, largest=False, sorted=True).indices


def planar_distances(xy: torch.Tensor, me_xy: torch.Tensor) -> torch.Tensor:
    """[..., Q, M] distances of target points ``xy`` [..., M, 2] to observers ``me_xy``
    [..., Q, >= 2] (broadcast over the leading dims: [B, 1, M, 2] targets shared by a row's
    observers, or [B, Q, M, 2] per observer). x and y apart: no [..., Q, M, 2] difference and
    no norm over a dim of 2, the same values in a third of the time."""
    return planar_distances_xy(xy[..., 0], xy[..., 1], me_xy)


def planar_distances_xy(x: torch.Tensor, y: torch.Tensor, me_xy: torch.Tensor) -> torch.Tensor:
    """``planar_distances`` of targets given as x [..., M] and y [..., M] apart (columns
    gathered from a table, ``torch_utils.gather_columns``)."""
    dx = x - me_xy[..., 0:1]
    dy = y - me_xy[..., 1:2]
    return torch.sqrt(dx * dx + dy * dy)


def k_nearest(
    dist: torch.Tensor,
    invalid: torch.Tensor | None,
    k: int,
    within: float,
    ids: tuple[torch.Tensor, int] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Indices [B, Q, k] of the k nearest valid targets and their distances [B, Q, k], ranked
    by ``nearest_k`` (1 cm buckets, ties to the lower index).

    Args:
        dist: [B, Q, M] distances (>= 0 or +inf); invalid: [B, Q, M] bool (broadcastable),
            targets to skip (None: none, e.g. distances already +inf where invalid).
        k: how many.
        within: the radius the caller masks beyond, metres.
        ids: optional ([B, Q, M] int64 target index of each column, number of targets): a
            subset of the targets (e.g. ``map_knn`` candidates); the column by default.

    Returns:
        (indices, distances: +inf where there is no valid target; the index of such an
        entry is arbitrary, but a valid target index).
    """
    m = dist.shape[-1]
    d = dist if invalid is None else torch.where(invalid, const(float("inf"), dist), dist)
    # Fewer targets than k: pad with +inf. A compiled graph always pads (by k), so that scenes
    # with fewer and with more than k targets share one graph instead of specialising on it.
    pad = k if torch.compiler.is_compiling() else max(k - m, 0)
    if pad:
        d = torch.nn.functional.pad(d, (0, pad), value=float("inf"))
    if ids is None:
        pos = nearest_k(d, k, exact_within=within)
        top = torch.gather(d, -1, pos)
        return (pos.clamp(max=m - 1) if pad else pos), top
    col = torch.nn.functional.pad(ids[0], (0, pad), value=0) if pad else ids[0]
    pos = nearest_k(d, k, ids=col, num_ids=ids[1], exact_within=within)
    return col.gather(-1, pos), torch.gather(d, -1, pos)


__all__ = ["k_nearest", "nearest_k", "planar_distances", "planar_distances_xy"]
