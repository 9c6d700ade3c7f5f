"""Exact nearest-segment search for groups of query points, pruned with bounding boxes.

The metric is the one the road-edge feature uses to choose a segment: the point of the segment
is found by a 2-D (x, y) projection clipped to the segment, and the distance to it is measured
with the axes scaled (z stretched). The arg-min is over all segments, ties going to the lowest
segment index, exactly as a brute-force search would give; the pruning only skips segments that
provably cannot win.

Pruning: the query points come in groups (close together in space). For a group with bounding
box B, a segment s is kept only if a lower bound of the distance from any point of B to s (the
x/y distance between B and the segment's bounding box) is at most the smallest upper bound over
segments (the chosen point lies on the segment, so its scaled distance is at most the farthest
pair of points of B and the segment's bounding box). The bound pass runs first on chunks of
consecutive segments, then on the segments of the kept chunks.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

_CHUNK = 16
"""Consecutive segments per chunk of the first pruning pass."""
_PAIRS_PER_RUN = 1 << 22
"""About this many (point, segment) pairs are evaluated at once (memory bound)."""
_REL_TOL = 1e-5
_ABS_TOL = 1e-3
"""Slack (relative, metres) on the bound comparisons against float32 rounding."""


@dataclass(frozen=True)
class SegmentIndex:
    """Segments with the bounding boxes used for pruning (all float32, one device).

    Attributes:
        start, end: [S, 3] end points (m).
        lo, hi: [S, 3] bounding box of each segment.
        chunk_lo, chunk_hi: [K, 3] bounding box of each chunk of ``_CHUNK`` consecutive segments.
    """

    start: torch.Tensor
    end: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor
    chunk_lo: torch.Tensor
    chunk_hi: torch.Tensor

    @property
    def num_segments(self) -> int:
        return int(self.start.shape[0])


def build_segment_index(start: torch.Tensor, end: torch.Tensor) -> SegmentIndex:
    """Index segments [S, 3] (S >= 1) for ``nearest_segment``."""
    lo, hi = torch.minimum(start, end), torch.maximum(start, end)
    s = start.shape[0]
    pad = (-s) % _CHUNK
    lo_p = torch.cat([lo, lo[-1:].expand(pad, 3)]).reshape(-1, _CHUNK, 3)
    hi_p = torch.cat([hi, hi[-1:].expand(pad, 3)]).reshape(-1, _CHUNK, 3)
    return SegmentIndex(
        start=start,
        end=end,
        lo=lo,
        hi=hi,
        chunk_lo=lo_p.amin(1),
        chunk_hi=hi_p.amax(1),
    )


def _box_gap_xy(lo_a: torch.Tensor, hi_a: torch.Tensor, lo_b: torch.Tensor, hi_b: torch.Tensor):
    """x/y distance between boxes (0 when they overlap), broadcast over leading dims."""
    gap = torch.maximum(lo_b[..., :2] - hi_a[..., :2], lo_a[..., :2] - hi_b[..., :2])
    return torch.linalg.vector_norm(gap.clamp_min(0.0), dim=-1)


def _box_far(
    lo_a: torch.Tensor, hi_a: torch.Tensor, lo_b: torch.Tensor, hi_b: torch.Tensor, scale
) -> torch.Tensor:
    """Largest scaled distance between a point of box a and a point of box b."""
    far = torch.maximum((hi_b - lo_a).abs(), (hi_a - lo_b).abs())
    return torch.linalg.vector_norm(far * scale, dim=-1)


def _candidates(
    lo: torch.Tensor, hi: torch.Tensor, index: SegmentIndex, scale: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Candidate (group, segment) pairs, sorted by group then segment.

    Args:
        lo, hi: [G, 3] group bounding boxes.

    Returns:
        (group [C] int64, segment [C] int64).
    """
    # Pass 1: chunks.
    lower = _box_gap_xy(lo[:, None], hi[:, None], index.chunk_lo[None], index.chunk_hi[None])
    upper = _box_far(lo[:, None], hi[:, None], index.chunk_lo[None], index.chunk_hi[None], scale)
    bound = upper.amin(1)  # [G]
    keep = lower <= bound[:, None] * (1.0 + _REL_TOL) + _ABS_TOL
    grp, chunk = keep.nonzero(as_tuple=True)
    # Pass 2: the segments of the kept chunks.
    offs = torch.arange(_CHUNK, device=lo.device)
    seg = (chunk[:, None] * _CHUNK + offs).reshape(-1)
    grp = grp.repeat_interleave(_CHUNK)
    real = seg < index.num_segments
    seg, grp = seg[real], grp[real]
    lower = _box_gap_xy(lo[grp], hi[grp], index.lo[seg], index.hi[seg])
    upper = _box_far(lo[grp], hi[grp], index.lo[seg], index.hi[seg], scale)
    bound = bound.scatter_reduce(0, grp, upper, "amin")
    keep = lower <= bound[grp] * (1.0 + _REL_TOL) + _ABS_TOL
    return grp[keep], seg[keep]


def nearest_segment(
    points: torch.Tensor,
    include: torch.Tensor,
    index: SegmentIndex,
    scale: tuple[float, float, float],
) -> torch.Tensor:
    """Index of the nearest segment of every query point.

    Args:
        points: [G, M, 3] query points (m), grouped (points of a group should be close).
        include: [G, M] bool, points that define their group's bounding box; the others (e.g.
            placeholders of invalid steps) still get an answer, but not necessarily the nearest.
        index: the segments.
        scale: axis scales of the distance, e.g. (1, 1, 3) to stretch z.

    Returns:
        [G, M] int64 segment index.
    """
    g, m, _ = points.shape
    dev = points.device
    big = torch.finfo(points.dtype).max
    lo = torch.where(include.unsqueeze(-1), points, big).amin(1)
    hi = torch.where(include.unsqueeze(-1), points, -big).amax(1)
    empty = ~include.any(1, keepdim=True)
    lo, hi = torch.where(empty, 0.0, lo), torch.where(empty, 0.0, hi)
    scale_t = torch.tensor(scale, dtype=points.dtype, device=dev)
    cand_grp, cand_seg = _candidates(lo, hi, index, scale_t)
    count = torch.bincount(cand_grp, minlength=g)  # [G]
    first_cand = torch.cumsum(count, 0) - count
    # Bound memory: groups are processed in runs of about _PAIRS_PER_RUN (point, segment) pairs.
    run_of_group = torch.cumsum(count * m, 0).div(_PAIRS_PER_RUN, rounding_mode="floor")
    runs = torch.unique_consecutive(run_of_group, return_counts=True)[1].tolist()
    out, g0 = [], 0
    for size in runs:
        sl = slice(g0, g0 + size)
        out.append(
            _nearest_in_groups(points[sl], count[sl], first_cand[sl], cand_seg, index, scale)
        )
        g0 += size
    return torch.cat(out).reshape(g, m)


def _nearest_in_groups(
    points: torch.Tensor,
    count: torch.Tensor,
    first_cand: torch.Tensor,
    cand_seg: torch.Tensor,
    index: SegmentIndex,
    scale: tuple[float, float, float],
) -> torch.Tensor:
    """Exact arg-min over the candidates of each group, for [G, M, 3] points -> [G * M]."""
    g, m, _ = points.shape
    dev = points.device
    # Every point of group g meets each of its count[g] candidates.
    per_point = count.repeat_interleave(m)  # [G * M]
    point = torch.repeat_interleave(torch.arange(g * m, device=dev), per_point)
    first_pair = torch.cumsum(per_point, 0) - per_point
    rank = torch.arange(point.numel(), device=dev) - first_pair.index_select(0, point)
    group_first = first_cand.repeat_interleave(m).index_select(0, point)
    seg = cand_seg.index_select(0, group_first + rank)  # [P]
    # Component-wise on contiguous 1-D tensors (faster than strided [P, 3] columns).
    flat = points.reshape(g * m, 3)
    a = index.start
    ab = index.end - index.start
    len2 = ab[:, 0] ** 2 + ab[:, 1] ** 2
    inv_len2 = torch.where(len2 > 0, 1.0 / torch.where(len2 > 0, len2, 1.0), 0.0)

    def take(values: torch.Tensor, idx: torch.Tensor) -> torch.Tensor:
        return values.contiguous().index_select(0, idx)

    px = take(flat[:, 0], point) - take(a[:, 0], seg)
    py = take(flat[:, 1], point) - take(a[:, 1], seg)
    pz = take(flat[:, 2], point) - take(a[:, 2], seg)
    dx, dy, dz = take(ab[:, 0], seg), take(ab[:, 1], seg), take(ab[:, 2], seg)
    t = ((px * dx + py * dy) * take(inv_len2, seg)).clamp_(0.0, 1.0)
    sx, sy, sz = scale
    dist2 = (sx * (px - t * dx)) ** 2 + (sy * (py - t * dy)) ** 2 + (sz * (pz - t * dz)) ** 2
    best = torch.full((g * m,), float("inf"), device=dev).scatter_reduce(0, point, dist2, "amin")
    s = index.num_segments
    tie = torch.where(dist2 == best.index_select(0, point), seg, s)
    out = torch.full((g * m,), s, device=dev, dtype=torch.int64).scatter_reduce(
        0, point, tie, "amin"
    )
    return out.clamp_(max=s - 1)
