"""Signed distance to road edges (positive = off-road), with the WOSAC sign convention.

Road edges are oriented with the road on their left. For a query point the closest segment over
all road edges is found; the sign is that of ``cross(q - a, b - a)`` (positive on the right),
corrected at polyline joints by the convexity rule of the WOSAC reference (docs/wosac.md 4.4).
This is the environment's fast 2-D check; ``tbsim_env.metrics`` carries the exact WOSAC feature.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from tbsim_env.sim.collision import box_corner_xy, box_corners
from tbsim_env.sim.state import RoadEdges
from tbsim_env.torch_utils import const, gather_rows

NO_EDGE_DISTANCE = -1.0e10
"""Distance reported when a scenario has no road edge (always on-road)."""


SIDE_FEATURES = 16
"""Per candidate segment (``EdgeCandidates.sides``): start x, start y, direction x, direction y
of the segment, its predecessor and its successor (3 each, in that order), then 0/1 flags:
convex joint with the predecessor, convex joint with the successor, has a predecessor, has a
successor."""


@dataclass(frozen=True)
class EdgeCandidates:
    """The C road-edge segments nearest to K query boxes at a reference position.

    Any segment closer than ``reach`` to ``center`` is in ``index``, so a query point whose
    nearest candidate is at distance d, and which lies within s of ``center``, has its true
    nearest segment among the candidates whenever d + s <= reach (triangle inequality).

    The candidates' own geometry is gathered once when the set is built, laid out for the
    per-step distance (``box_offroad_distance``), which then needs no gather of segments.

    Attributes:
        index: [B, K, C] int64 segment indices.
        center: [B, K, 2] reference positions.
        reach: [B, K] distance of the C-th nearest segment from ``center`` (inf if fewer).
        segments: [B, K, 5, 1, C] float32 rows: start x, start y, direction (end - start) x,
            direction y (m), squared length (m^2, clamped at 1e-12; inf for a zero-length
            segment, which makes its projection parameter 0 as in
            ``point_segment_distance``).
        invalid: [B, K, 1, C] bool, padding segments (never nearest).
        sides: [B, K, C, SIDE_FEATURES] float32, what the sign at polyline joints needs.
        no_edge: [B, 1, 1] bool, the scenario has no valid road edge.
    """

    index: torch.Tensor
    center: torch.Tensor
    reach: torch.Tensor
    segments: torch.Tensor
    invalid: torch.Tensor
    sides: torch.Tensor
    no_edge: torch.Tensor

    @staticmethod
    def build(pose: torch.Tensor, edges: RoadEdges, count: int = 256) -> EdgeCandidates:
        """Candidates around ``pose`` [B, K, 3] (``count`` segments, fewer if E is smaller)."""
        dist, _ = point_segment_distance(pose[..., :2], edges)
        c = min(count, dist.shape[-1])
        top, index = torch.topk(dist, c, dim=-1, largest=False, sorted=True)
        reach = top[..., -1] if c < dist.shape[-1] else torch.full_like(top[..., -1], float("inf"))
        return EdgeCandidates(
            index=index,
            center=pose[..., :2].clone(),
            reach=reach,
            **_candidate_geometry(edges, index),
        )


def _candidate_geometry(edges: RoadEdges, index: torch.Tensor) -> dict[str, torch.Tensor]:
    """The geometry fields of ``EdgeCandidates`` for the segments ``index`` [B, K, C].

    Made with the operations of ``point_segment_distance`` and ``_signed_and_unsigned`` on the
    same values, so distances and signs from the cache are bit-identical to theirs.
    """
    start = gather_rows(edges.start, index)
    direction = gather_rows(edges.end, index) - start
    length2 = (direction * direction).sum(-1)
    length2 = torch.where(length2 > 0, length2.clamp_min(1e-12), float("inf"))
    seg = torch.cat([start, direction, length2[..., None]], -1)  # [B, K, C, 5]
    prev = gather_rows(edges.prev_index, index)
    nxt = gather_rows(edges.next_index, index)
    prev_start = gather_rows(edges.start, prev)
    prev_dir = gather_rows(edges.end, prev) - prev_start
    next_start = gather_rows(edges.start, nxt)
    next_dir = gather_rows(edges.end, nxt) - next_start
    flags = torch.stack(
        [
            _cross(prev_dir, direction) > 0,
            _cross(direction, next_dir) > 0,
            prev != index,
            nxt != index,
        ],
        dim=-1,
    ).to(start.dtype)
    starts = torch.stack([start, prev_start, next_start], -1).flatten(-2)  # x x x y y y
    dirs = torch.stack([direction, prev_dir, next_dir], -1).flatten(-2)
    sides = torch.cat([starts, dirs, flags], -1)  # [B, K, C, 16]
    valid = gather_rows(edges.valid, index)
    return {
        "segments": seg.permute(0, 1, 3, 2)[:, :, :, None].contiguous(),
        "invalid": ~valid[:, :, None],
        "sides": sides.contiguous(),
        "no_edge": ~edges.valid.any(-1)[:, None, None],
    }


def _cross(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def point_segment_distance(
    points: torch.Tensor, edges: RoadEdges, segment_index: torch.Tensor | None = None
) -> tuple[torch.Tensor, torch.Tensor]:
    """Distance of each point to each (candidate) segment and the projection parameter.

    Args:
        points: [B, K, 2].
        edges: road edges.
        segment_index: optional [B, K, C] candidate segments per point (all E by default).

    Returns:
        (distance [B, K, C or E] with +inf for invalid segments, t [B, K, C or E]).
    """
    if segment_index is None:
        a, b, valid = edges.start[:, None], edges.end[:, None], edges.valid[:, None]
    else:
        a = gather_rows(edges.start, segment_index)
        b = gather_rows(edges.end, segment_index)
        valid = gather_rows(edges.valid, segment_index)
    ab = b - a
    q = points[:, :, None]
    len2 = (ab * ab).sum(-1)
    t = ((q - a) * ab).sum(-1) / len2.clamp_min(1e-12)
    t = torch.where(len2 > 0, t, torch.zeros_like(t))
    closest = a + t.clamp(0.0, 1.0)[..., None] * ab
    offset = q - closest
    dist = torch.hypot(offset[..., 0], offset[..., 1])
    return torch.where(valid, dist, torch.full_like(dist, float("inf"))), t


def signed_distance_to_edges(
    points: torch.Tensor, edges: RoadEdges, segment_index: torch.Tensor | None = None
) -> torch.Tensor:
    """Signed distance of points to the nearest road edge.

    Args:
        points: [B, K, 2] m.
        edges: road-edge segments of the B scenarios.
        segment_index: optional [B, K, C] candidate segments per point; the nearest segment
            must be among them for the result to be exact (see ``EdgeCandidates``).

    Returns:
        [B, K] m; positive off-road, negative on-road, ``NO_EDGE_DISTANCE`` without edges.
    """
    return _signed_and_unsigned(points, edges, segment_index)[0]


def _signed_and_unsigned(
    points: torch.Tensor, edges: RoadEdges, segment_index: torch.Tensor | None
) -> tuple[torch.Tensor, torch.Tensor]:
    """(signed distance [B, K], unsigned distance to the nearest candidate [B, K])."""
    dist, t = point_segment_distance(points, edges, segment_index)
    local = dist.argmin(-1, keepdim=True)  # [B, K, 1]
    d = dist.gather(2, local)[..., 0]
    t_best = t.gather(2, local)[..., 0]
    best = local[..., 0] if segment_index is None else segment_index.gather(2, local)[..., 0]

    def side(seg: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        sa = gather_rows(edges.start, seg)
        sab = gather_rows(edges.end, seg) - sa
        return torch.sign(_cross(points - sa, sab)), sab

    n, dir_this = side(best)
    prev = gather_rows(edges.prev_index, best)
    nxt = gather_rows(edges.next_index, best)
    n_prev, dir_prev = side(prev)
    n_next, dir_next = side(nxt)
    convex_prev = _cross(dir_prev, dir_this) > 0
    convex_next = _cross(dir_this, dir_next) > 0
    with_prev = torch.where(convex_prev, torch.maximum(n, n_prev), torch.minimum(n, n_prev))
    with_next = torch.where(convex_next, torch.maximum(n, n_next), torch.minimum(n, n_next))
    sign = torch.where((t_best < 0) & (prev != best), with_prev, n)
    sign = torch.where((t_best > 1) & (nxt != best), with_next, sign)
    out = sign * d
    has_edge = edges.valid.any(-1, keepdim=True)
    return torch.where(has_edge, out, torch.full_like(out, NO_EDGE_DISTANCE)), d


_JOINT_SCALE = (-1.0, 1.0)
_JOINT_LIMIT = (0.0, 1.0)
"""``t * scale > limit``: (t < 0, t > 1), the projection falls before / after the segment."""


def _candidate_signed_and_unsigned(
    x: torch.Tensor, y: torch.Tensor, cand: EdgeCandidates
) -> tuple[torch.Tensor, torch.Tensor]:
    """``_signed_and_unsigned`` of P points per query box over its cached candidates.

    The reference arithmetic on the same values (bit-identical results), on the candidates'
    precomputed geometry broadcast over the points instead of gathered per point.

    Args:
        x, y: [B, K, P, 1] m, point coordinates (e.g. the box corners).
        cand: the candidates of the K boxes.

    Returns:
        (signed distance [B, K, P, 1] m, unsigned distance to the nearest candidate
        [B, K, P, 1]).
    """
    ax, ay, abx, aby, length2 = cand.segments.unbind(2)  # [B, K, 1, C] each
    dx, dy = x - ax, y - ay
    t = (dx * abx + dy * aby) / length2  # [B, K, P, C]
    tc = t.clamp(0.0, 1.0)
    # hypot, not the norm of a stacked pair: the same value in one operation instead of two
    # (and ``point_segment_distance`` uses it too, so both give the same bits).
    dist = torch.hypot(x - (ax + tc * abx), y - (ay + tc * aby))
    dist = dist.masked_fill_(cand.invalid, float("inf"))
    local = dist.argmin(-1, keepdim=True)  # [B, K, P, 1]
    d = dist.gather(-1, local)
    t_best = t.gather(-1, local)
    row = cand.sides.gather(2, local.expand(-1, -1, -1, SIDE_FEATURES))  # [B, K, P, 16]
    sx, sy, vx, vy, flags = row.split_with_sizes([3, 3, 3, 3, 4], -1)
    # Side of the nearest segment, its predecessor and its successor: [B, K, P, 3].
    n3 = torch.sign((x - sx) * vy - (y - sy) * vx)
    n, n_pn = n3.split_with_sizes([1, 2], -1)
    convex, has = (flags > const(0.5, flags)).split_with_sizes([2, 2], -1)
    joint = torch.where(convex, torch.maximum(n, n_pn), torch.minimum(n, n_pn))
    # (t < 0 and a predecessor, t > 1 and a successor).
    use = (t_best * const(_JOINT_SCALE, t) > const(_JOINT_LIMIT, t)) & has
    use_prev, use_next = use.split_with_sizes([1, 1], -1)
    joint_prev, joint_next = joint.split_with_sizes([1, 1], -1)
    sign = torch.where(use_next, joint_next, torch.where(use_prev, joint_prev, n))
    out = (sign * d).masked_fill_(cand.no_edge.unsqueeze(-1), NO_EDGE_DISTANCE)
    return out, d


def candidate_offroad_distance(
    candidates: EdgeCandidates,
    pose: torch.Tensor,
    corners: tuple[torch.Tensor, torch.Tensor],
    half_diag: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``box_offroad_distance`` from the cached candidates alone: no refresh, no branch (so it
    compiles to one graph), and a flag where the cache cannot vouch for the answer.

    Args:
        candidates: the cached candidate segments of these K boxes.
        pose: [B, K, 3]; corners: their corners (x, y [B, K, 4]); half_diag: [B, K] m,
            ``0.5 * |size|``.

    Returns:
        (max signed distance over the corners [B, K] m, stale [B, K] bool: a segment outside
        the candidates could be nearer to a corner, so the distance may be wrong there).
    """
    x, y = corners[0].unsqueeze(-1), corners[1].unsqueeze(-1)  # [B, K, 4, 1]
    moved = torch.linalg.vector_norm(pose[..., :2] - candidates.center, dim=-1) + half_diag
    signed, nearest = _candidate_signed_and_unsigned(x, y, candidates)
    # Exact while every segment that could be nearest to a corner is in the candidate set.
    stale = nearest.amax((-2, -1)) + moved > candidates.reach
    return signed.amax((-2, -1)), stale


def box_offroad_distance(
    pose: torch.Tensor,
    size: torch.Tensor,
    edges: RoadEdges,
    candidates: EdgeCandidates | None = None,
    corners: tuple[torch.Tensor, torch.Tensor] | None = None,
    half_diag: torch.Tensor | None = None,
) -> tuple[torch.Tensor, EdgeCandidates | None]:
    """Max signed road-edge distance over the 4 box corners (positive: a corner is off-road).

    Args:
        pose: [B, K, 3]; size: [B, K, 2] (length, width).
        edges: road edges.
        candidates: optional cached candidate segments of these K boxes (``EdgeCandidates``);
            refreshed where the cache cannot guarantee the exact answer.
        corners: optional ``box_corner_xy(pose, length, width)`` (x, y [B, K, 4]), used with
            ``candidates``.
        half_diag: optional [B, K] ``0.5 * |size|`` m, used with ``candidates``.

    Returns:
        ([B, K] m, the candidates to pass next time, or None when none were given).
    """
    bsz, k = pose.shape[:2]
    if candidates is None or corners is None:
        length, width = size.unbind(-1)
    if candidates is None:
        flat = box_corners(pose, length, width).reshape(bsz, k * 4, 2)
        return signed_distance_to_edges(flat, edges).view(bsz, k, 4).amax(-1), None
    if corners is None:
        corners = box_corner_xy(pose, length, width)
    if half_diag is None:
        half_diag = const(0.5, size) * torch.linalg.vector_norm(size, dim=-1)
    dist, stale = candidate_offroad_distance(candidates, pose, corners, half_diag)
    if bool(stale.any()):
        # Rebuilt around the boxes themselves (centre = pose, so the check is nearest +
        # half_diag <= reach).
        candidates = EdgeCandidates.build(pose, edges, candidates.index.shape[-1])
        dist, stale = candidate_offroad_distance(candidates, pose, corners, half_diag)
        if bool(stale.any()):
            # The cache cannot vouch for these boxes (e.g. far from every edge): use all.
            flat = torch.stack(corners, -1).reshape(bsz, k * 4, 2)
            return signed_distance_to_edges(flat, edges).view(bsz, k, 4).amax(-1), candidates
    return dist, candidates
