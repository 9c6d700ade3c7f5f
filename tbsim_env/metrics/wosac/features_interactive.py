"""Interactive WOSAC features (docs/metrics.md, "Interactive features").

* distance to the nearest object between rounded rectangles (2-D), and collision (< 0),
* time to collision with the object followed in front.

Inputs are ``ObjectTrajectories`` ([R, N, T], evaluated objects first); outputs are [R, E, T].
The rollout axis is processed in chunks to bound memory; objects and steps are vectorised.
"""

from __future__ import annotations

import torch

from tbsim_env.core.boxes import box_corners
from tbsim_env.core.constants import DT
from tbsim_env.metrics.wosac.config import (
    BOX_ROUNDING_FACTOR,
    NO_PARTNER_DISTANCE,
    TTC_MAX_HEADING_DIFF,
    TTC_MAX_SECONDS,
    TTC_MIN_LATERAL_OVERLAP,
    TTC_SMALL_HEADING_DIFF,
)
from tbsim_env.metrics.wosac.features_kinematic import central_diff
from tbsim_env.metrics.wosac.trajectories import ObjectTrajectories

_PAIRS_PER_CHUNK = 1 << 19
"""Rollouts are processed so that one chunk holds about this many (e, o, t) pairs."""


def _corners(center: torch.Tensor, heading: torch.Tensor, half: torch.Tensor) -> torch.Tensor:
    """[..., 4, 2] corners (m) of boxes at ``center`` [..., 2] m, ``heading`` [...] rad, with
    half sizes ``half`` [..., 2] m (length, width)."""
    center, heading = torch.broadcast_tensors(center, heading.unsqueeze(-1))
    pose = torch.cat([center, heading[..., :1]], -1)
    return box_corners(pose, 2.0 * half[..., 0], 2.0 * half[..., 1])


def _point_segment_distance(p: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Euclidean distance of points p [..., 2] to segments [a, b] [..., 2] (broadcast)."""
    ab = b - a
    ap = p - a
    t = (ap * ab).sum(-1) / (ab * ab).sum(-1).clamp_min(1e-12)
    d = ap - t.clamp(0.0, 1.0).unsqueeze(-1) * ab
    return torch.linalg.vector_norm(d, dim=-1)


def _polygon_gap(corners_p: torch.Tensor, corners_q: torch.Tensor) -> torch.Tensor:
    """Minimum distance from the vertices of q to the edges of p, [...] (polygons [..., 4, 2])."""
    a = corners_p.unsqueeze(-3)  # [..., 1, 4, 2] edge starts
    b = torch.roll(corners_p, -1, dims=-2).unsqueeze(-3)
    v = corners_q.unsqueeze(-2)  # [..., 4, 1, 2]
    return _point_segment_distance(v, a, b).flatten(-2).amin(-1)


def rectangle_signed_distance(
    center_a: torch.Tensor,
    heading_a: torch.Tensor,
    half_a: torch.Tensor,
    center_b: torch.Tensor,
    heading_b: torch.Tensor,
    half_b: torch.Tensor,
) -> torch.Tensor:
    """Signed distance between two oriented rectangles (broadcast over leading dims).

    Positive: the gap between them; negative: minus the penetration depth (the distance of the
    origin to the boundary of their Minkowski difference). Overlap and depth come from the four
    separating axes; the gap of separated boxes from the vertex-to-edge distances.

    Args:
        center_a, center_b: [..., 2] centres (m).
        heading_a, heading_b: [...] yaws (rad).
        half_a, half_b: [..., 2] half (length, width) (m).

    Returns:
        [...] signed distance (m).
    """
    ca, sa = torch.cos(heading_a), torch.sin(heading_a)
    cb, sb = torch.cos(heading_b), torch.sin(heading_b)
    axes_a = torch.stack([torch.stack([ca, sa], -1), torch.stack([-sa, ca], -1)], -2)
    axes_b = torch.stack([torch.stack([cb, sb], -1), torch.stack([-sb, cb], -1)], -2)
    axes = torch.cat(torch.broadcast_tensors(axes_a, axes_b), dim=-2)  # [..., 4, 2]
    d = (center_b - center_a).unsqueeze(-2)
    # Projection radius of a box on axis u: hl * |u . e_l| + hw * |u . e_w|.
    rad_a = ((axes @ axes_a.transpose(-1, -2)).abs() * half_a.unsqueeze(-2)).sum(-1)
    rad_b = ((axes @ axes_b.transpose(-1, -2)).abs() * half_b.unsqueeze(-2)).sum(-1)
    gap = (d * axes).sum(-1).abs() - rad_a - rad_b
    separation = gap.amax(-1)
    corners_a = _corners(center_a, heading_a, half_a)
    corners_b = _corners(center_b, heading_b, half_b)
    apart = torch.minimum(_polygon_gap(corners_a, corners_b), _polygon_gap(corners_b, corners_a))
    return torch.where(separation > 0.0, apart, separation)


def _rollout_chunk(traj: ObjectTrajectories) -> int:
    e = traj.num_eval
    n, t = traj.x.shape[1], traj.x.shape[2]
    return max(1, _PAIRS_PER_CHUNK // max(1, e * n * t))


def _separation(
    d: torch.Tensor,
    cos_a: torch.Tensor,
    sin_a: torch.Tensor,
    half_a: torch.Tensor,
    cos_b: torch.Tensor,
    sin_b: torch.Tensor,
    half_b: torch.Tensor,
) -> torch.Tensor:
    """Largest separating-axis gap of two rectangles (the four box axes), elementwise.

    Equal to the signed distance when the boxes overlap (minus the penetration depth), and a
    lower bound of the distance when they are apart.

    Args:
        d: [..., 2] centre of b minus centre of a (m).
        cos_a, sin_a, cos_b, sin_b: [...] of the yaws.
        half_a, half_b: [..., 2] half (length, width) (m).
    """
    cos_d = (cos_a * cos_b + sin_a * sin_b).abs()  # |cos(h_b - h_a)|
    sin_d = (sin_b * cos_a - cos_b * sin_a).abs()
    la, wa = half_a[..., 0], half_a[..., 1]
    lb, wb = half_b[..., 0], half_b[..., 1]
    dx, dy = d[..., 0], d[..., 1]
    gaps = (
        (dx * cos_a + dy * sin_a).abs() - la - (lb * cos_d + wb * sin_d),
        (dy * cos_a - dx * sin_a).abs() - wa - (lb * sin_d + wb * cos_d),
        (dx * cos_b + dy * sin_b).abs() - lb - (la * cos_d + wa * sin_d),
        (dy * cos_b - dx * sin_b).abs() - wb - (la * sin_d + wa * cos_d),
    )
    return torch.maximum(torch.maximum(gaps[0], gaps[1]), torch.maximum(gaps[2], gaps[3]))


def distance_to_nearest_object(traj: ObjectTrajectories) -> torch.Tensor:
    """Signed distance of each evaluated object to its nearest other valid object.

    Objects are rounded rectangles (corner radius r = 0.7 * min(L, W) / 2): the distance is the
    signed distance of the cores minus both radii. Pairs where either object is invalid are
    skipped; with no valid partner the value is 1e10.

    Exact, computed cheaply: overlapping pairs get their separating-axis depth; the vertex-to-edge
    distance of separated pairs is only evaluated where the pair can be the nearest one (its
    separating-axis lower bound is not above the smallest centre-distance upper bound).

    Args:
        traj: [R, N, T] trajectories, evaluated first.

    Returns:
        [R, E, T] distance in metres.
    """
    e = traj.num_eval
    n = traj.x.shape[1]
    dev = traj.x.device
    radius = BOX_ROUNDING_FACTOR * torch.minimum(traj.length, traj.width) / 2.0  # [N]
    core_half = torch.stack([traj.length / 2.0 - radius, traj.width / 2.0 - radius], -1)  # [N, 2]
    radii = radius[:e, None, None] + radius[None, :, None]  # [E, N, 1]
    not_self = torch.ones(e, n, dtype=torch.bool, device=dev)
    not_self[:, :e] &= ~torch.eye(e, dtype=torch.bool, device=dev)
    out = []
    step = _rollout_chunk(traj)
    for r0 in range(0, traj.num_rollouts, step):
        sl = slice(r0, r0 + step)
        center = torch.stack([traj.x[sl], traj.y[sl]], -1)  # [r, N, T, 2]
        head = traj.heading[sl]
        cos, sin = torch.cos(head), torch.sin(head)
        d = center[:, None] - center[:, :e, None]  # [r, E, N, T, 2]
        sep = _separation(
            d,
            cos[:, :e, None],
            sin[:, :e, None],
            core_half[:e, None, None, :],
            cos[:, None],
            sin[:, None],
            core_half[None, :, None, :],
        )  # [r, E, N, T]
        ok = traj.valid[sl][:, :e, None] & traj.valid[sl][:, None] & not_self[None, :, :, None]
        upper = torch.linalg.vector_norm(d, dim=-1) - radii
        upper_min = torch.where(ok, upper, NO_PARTNER_DISTANCE).amin(2, keepdim=True)
        dist = sep - radii  # exact where sep <= 0, a lower bound elsewhere
        need = ok & (sep > 0.0) & (dist <= upper_min)
        ri, ei, oi, ti = need.nonzero(as_tuple=True)
        if ri.numel():
            ra = ri + r0
            exact = rectangle_signed_distance(
                center[ri, ei, ti],
                traj.heading[ra, ei, ti],
                core_half[ei],
                center[ri, oi, ti],
                traj.heading[ra, oi, ti],
                core_half[oi],
            )
            dist = dist.index_put((ri, ei, oi, ti), exact - radius[ei] - radius[oi])
        out.append(torch.where(ok, dist, NO_PARTNER_DISTANCE).amin(dim=2))
    return torch.cat(out, dim=0)


def time_to_collision(traj: ObjectTrajectories, dt: float = DT) -> torch.Tensor:
    """Time to collision with the nearest object followed in front (2-D, saturated at 5 s).

    Per step, for evaluated ego e and every object o (e included): with the raw, unwrapped
    yaw_diff = |h_o - h_e|, o is followed if it is ahead (long > 0), heading within 75 degrees,
    laterally overlapping (lat < 0) by more than 0.5 m or within 10 degrees, and valid. The
    nearest followed object by ``long`` gives TTC = long / (s_e - s_o) if the ego is faster,
    else 5 s. Speeds are central-difference 2-D speeds (NaN at the ends gives 5 s).

    Args:
        traj: [R, N, T] trajectories, evaluated first.
        dt: step in seconds.

    Returns:
        [R, E, T] time to collision in seconds, in [.., 5].
    """
    e = traj.num_eval
    dx_, dy_ = central_diff(traj.x), central_diff(traj.y)
    speed = torch.sqrt(dx_ * dx_ + dy_ * dy_) / dt  # [R, N, T]
    half_l = (traj.length / 2.0)[None, None, :, None]  # other's half sizes, [1, 1, N, 1]
    half_w = (traj.width / 2.0)[None, None, :, None]
    ego_half_l = (traj.length[:e] / 2.0)[None, :, None, None]
    ego_half_w = (traj.width[:e] / 2.0)[None, :, None, None]
    out = []
    step = _rollout_chunk(traj)
    for r0 in range(0, traj.num_rollouts, step):
        sl = slice(r0, r0 + step)
        x, y, h = traj.x[sl], traj.y[sl], traj.heading[sl]
        he = h[:, :e, None]
        yaw_diff = (h[:, None] - he).abs()  # [r, E, N, T]
        c, s = yaw_diff.cos().abs(), yaw_diff.sin().abs()
        dx = x[:, None] - x[:, :e, None]
        dy = y[:, None] - y[:, :e, None]
        ce, se = he.cos(), he.sin()
        rx = dx * ce + dy * se
        ry = -dx * se + dy * ce
        long = rx - ego_half_l - (half_l * c + half_w * s)
        lat = ry.abs() - ego_half_w - (half_l * s + half_w * c)
        followed = (
            (long > 0.0)
            & (yaw_diff <= TTC_MAX_HEADING_DIFF)
            & (lat < 0.0)
            & ((lat < -TTC_MIN_LATERAL_OVERLAP) | (yaw_diff <= TTC_SMALL_HEADING_DIFF))
            & traj.valid[sl][:, None]
        )
        gap = torch.where(followed, long, NO_PARTNER_DISTANCE)
        gap_min, chosen = gap.min(dim=2)  # [r, E, T]
        other_speed = speed[sl].gather(1, chosen)
        rel = speed[sl][:, :e] - other_speed
        ttc = torch.where(
            rel > 0.0, torch.clamp(gap_min / rel, max=TTC_MAX_SECONDS), TTC_MAX_SECONDS
        )
        out.append(ttc)
    return torch.cat(out, dim=0)
