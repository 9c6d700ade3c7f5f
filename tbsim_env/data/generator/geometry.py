"""Small polyline helpers for the procedural generator (pure numpy, 2-D, metres)."""

from __future__ import annotations

import numpy as np

LANE_POINT_SPACING = 0.5
"""Target spacing of generated polyline points in metres (WOMD lanes use ~0.5 m)."""


def arc_length(points: np.ndarray) -> np.ndarray:
    """Cumulative arc length of a polyline (or of a batch of them).

    Args:
        points: [..., n, 2] polylines in metres.

    Returns:
        [..., n] float64, 0 at the first point.
    """
    seg = np.linalg.norm(np.diff(points, axis=-2), axis=-1)
    return np.concatenate([np.zeros(seg.shape[:-1] + (1,)), np.cumsum(seg, axis=-1)], axis=-1)


def resample(points: np.ndarray, spacing: float = LANE_POINT_SPACING) -> np.ndarray:
    """Resample a polyline to (almost) equal spacing, keeping both end points exactly.

    Args:
        points: [n, 2] dense polyline in metres, n >= 2.
        spacing: largest allowed spacing in metres.

    Returns:
        [m, 2] polyline whose consecutive points are ``length / (m - 1) <= spacing`` apart
        along the input polyline.
    """
    s = arc_length(points)
    n = max(int(np.ceil(s[-1] / spacing)), 1) + 1
    targets = np.linspace(0.0, s[-1], n)
    out = np.stack([np.interp(targets, s, points[:, k]) for k in range(2)], axis=1)
    out[0], out[-1] = points[0], points[-1]
    return out


def line(p0: np.ndarray, p1: np.ndarray) -> np.ndarray:
    """Straight polyline from ``p0`` to ``p1`` ([2] each), resampled to the lane spacing."""
    return resample(np.stack([np.asarray(p0, float), np.asarray(p1, float)]))


def bezier(p0: np.ndarray, h0: float, p1: np.ndarray, h1: float, num: int = 400) -> np.ndarray:
    """Smooth cubic connector from pose (p0, h0) to pose (p1, h1), resampled to the lane spacing.

    The handles lie along both headings and have 0.5523 times the distance from each end to
    the crossing of the two tangent lines, which makes a right-angle turn with equal legs a
    close approximation of a circular arc. Parallel tangents use a third of the chord.

    Args:
        p0, p1: [2] end points in metres.
        h0, h1: headings at the end points in radians.
        num: dense samples before resampling.
    """
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    d0 = np.array([np.cos(h0), np.sin(h0)])
    d1 = np.array([np.cos(h1), np.sin(h1)])
    cross = d0[0] * d1[1] - d0[1] * d1[0]
    chord = float(np.linalg.norm(p1 - p0))
    if abs(cross) < 1e-6:
        k0 = k1 = chord / 3.0
    else:
        rhs = p1 - p0
        # p0 + d0 * t0 = p1 - d1 * t1  ->  [d0, d1] [t0, t1]^T = p1 - p0
        t0, t1 = np.linalg.solve(np.stack([d0, d1], axis=1), rhs)
        k0, k1 = 0.5523 * abs(t0), 0.5523 * abs(t1)
    c0, c1 = p0 + d0 * k0, p1 - d1 * k1
    u = np.linspace(0.0, 1.0, num)[:, None]
    pts = (1 - u) ** 3 * p0 + 3 * (1 - u) ** 2 * u * c0 + 3 * (1 - u) * u**2 * c1 + u**3 * p1
    return resample(pts)


def circle_arc(centre: np.ndarray, radius: float, a0: float, a1: float) -> np.ndarray:
    """Circular arc around ``centre`` from polar angle ``a0`` to ``a1`` (radians, either way).

    Returns:
        [m, 2] polyline resampled to the lane spacing.
    """
    a = np.linspace(a0, a1, 200)
    pts = np.asarray(centre, float) + radius * np.stack([np.cos(a), np.sin(a)], axis=1)
    return resample(pts)


def vertex_headings(points: np.ndarray) -> np.ndarray:
    """Unwrapped tangent heading at each polyline vertex (mean of the adjacent segments).

    Args:
        points: [n, 2], n >= 2.

    Returns:
        [n] float64 radians, unwrapped (continuous along the polyline).
    """
    d = np.diff(points, axis=0)
    seg = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    mid = 0.5 * (seg[:-1] + seg[1:])
    return np.concatenate([seg[:1], mid, seg[-1:]])


def offset(points: np.ndarray, dist: float) -> np.ndarray:
    """Shift a polyline sideways; positive ``dist`` moves it to the left of its direction.

    Args:
        points: [n, 2] polyline.
        dist: lateral offset in metres.

    Returns:
        [n, 2] shifted polyline (not resampled).
    """
    h = vertex_headings(points)
    normal = np.stack([-np.sin(h), np.cos(h)], axis=1)
    return points + dist * normal
