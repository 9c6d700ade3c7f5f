"""Routes through a generated lane graph, as padded arrays for vectorised lookups."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tbsim_env.data.generator.geometry import arc_length, vertex_headings
from tbsim_env.data.generator.roads import RoadNetwork

_ROUTE_STRIDE = 1.0e4
"""Key stride (m) that separates routes in flattened searches; longer than any route."""


@dataclass(frozen=True)
class RouteTable:
    """Every source-to-sink path of a lane graph, R routes, P padded points, K padded lanes.

    Route coordinates are arc lengths ``s`` in metres from the route start. Padding repeats
    the last valid entry so that interpolation beyond the end clamps.

    Attributes:
        lanes: lane ids of each route, in driving order.
        source: [R] int64 id of the first lane of each route.
        xy: [R, P, 2] float64 route points in metres.
        heading: [R, P] float64 unwrapped tangent heading at each point, radians.
        s: [R, P] float64 arc length of each point, metres.
        length: [R] float64 route length, metres.
        curvature: [R, P] float64 |curvature| at each point, 1/m.
        lane_offset: [R, L + 1] float64 route ``s`` where lane id l starts (column l),
            NaN where the lane is not on the route (column 0 unused).
        lane_length: [L + 1] float64 length of lane id l (column 0 unused).
    """

    lanes: tuple[tuple[int, ...], ...]
    source: np.ndarray
    xy: np.ndarray
    heading: np.ndarray
    s: np.ndarray
    length: np.ndarray
    curvature: np.ndarray
    lane_offset: np.ndarray
    lane_length: np.ndarray

    @property
    def num_routes(self) -> int:
        return len(self.lanes)

    def _flat_keys(self) -> tuple[np.ndarray, np.ndarray]:
        r = np.arange(self.num_routes)[:, None]
        return (r * _ROUTE_STRIDE + self.s).ravel(), self.s.shape[1]

    def interpolate(self, route: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Position and heading at route coordinates.

        Args:
            route: [...] int route indices.
            s: [...] float arc lengths (clamped to [0, length]).

        Returns:
            xy [..., 2] metres and heading [...] radians (unwrapped).
        """
        keys, p = self._flat_keys()
        s = np.clip(s, 0.0, self.length[route])
        q = route * _ROUTE_STRIDE + s
        hi = np.clip(np.searchsorted(keys, q, side="right"), 1, keys.size - 1)
        hi = np.minimum(hi, route * p + p - 1)
        hi = np.maximum(hi, route * p + 1)
        lo = hi - 1
        s_flat, xy_flat, h_flat = self.s.ravel(), self.xy.reshape(-1, 2), self.heading.ravel()
        span = np.maximum(s_flat[hi] - s_flat[lo], 1e-9)
        w = np.clip((s - s_flat[lo]) / span, 0.0, 1.0)
        xy = xy_flat[lo] * (1 - w)[..., None] + xy_flat[hi] * w[..., None]
        return xy, h_flat[lo] * (1 - w) + h_flat[hi] * w

    def locate(self, route: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Lane id under a route coordinate and the arc length along that lane.

        Args:
            route: [N] int route indices.
            s: [N] float route arc lengths (may be < 0 or > length; clamped to the ends).

        Returns:
            lane id [N] int64 and lane arc length [N] float64 (unclamped, may be negative
            before the route start).
        """
        offs = self.lane_offset[route]  # [N, L+1]
        started = np.where(np.isnan(offs), np.inf, offs) <= s[:, None]
        # The lane whose start is the largest one not after s; the first lane if none.
        cand = np.where(started, offs, -np.inf)
        lane = np.argmax(cand, axis=1)
        none = ~started.any(axis=1)
        first = np.asarray([self.lanes[r][0] for r in range(self.num_routes)])[route]
        lane = np.where(none, first, lane)
        return lane.astype(np.int64), s - offs[np.arange(len(route)), lane]


def _paths(net: RoadNetwork) -> list[tuple[int, ...]]:
    """All lane-id paths from source lanes to lanes without successors (depth first)."""
    out: list[tuple[int, ...]] = []
    stack = [(lid,) for lid in reversed(net.source_lanes)]
    while stack:
        path = stack.pop()
        nxt = net.lane(path[-1]).exit
        if not nxt:
            out.append(path)
        for e in reversed(nxt):
            stack.append(path + (e,))
    return out


def build_routes(net: RoadNetwork) -> RouteTable:
    """Enumerate the routes of a network and pad them into a ``RouteTable``."""
    paths = _paths(net)
    n_lanes = len(net.lanes)
    lane_length = np.zeros(n_lanes + 1)
    for ln in net.lanes:
        lane_length[ln.id] = arc_length(ln.points)[-1]
    pts_list, offsets = [], np.full((len(paths), n_lanes + 1), np.nan)
    for r, path in enumerate(paths):
        parts, start = [], 0.0
        for k, lid in enumerate(path):
            offsets[r, lid] = start
            start += lane_length[lid]
            pts = net.lane(lid).points
            parts.append(pts if k == 0 else pts[1:])
        pts_list.append(np.concatenate(parts))
    p = max(len(x) for x in pts_list)
    xy = np.stack([np.concatenate([x, np.repeat(x[-1:], p - len(x), 0)]) for x in pts_list])
    heading = np.zeros((len(paths), p))
    s = np.zeros((len(paths), p))
    curv = np.zeros((len(paths), p))
    for r, x in enumerate(pts_list):
        n = len(x)
        h = vertex_headings(x)
        sr = arc_length(x)
        k = np.abs(np.gradient(h, sr))
        # Smooth over ~2 m so that polyline kinks do not look like sharp bends.
        k = np.convolve(np.pad(k, 2, mode="edge"), np.ones(5) / 5, mode="valid")
        heading[r] = np.concatenate([h, np.full(p - n, h[-1])])
        s[r] = np.concatenate([sr, sr[-1] + 1e-3 * np.arange(1, p - n + 1)])
        curv[r] = np.concatenate([k, np.zeros(p - n)])
    length = np.asarray([arc_length(x)[-1] for x in pts_list])
    return RouteTable(
        lanes=tuple(paths),
        source=np.asarray([pth[0] for pth in paths], np.int64),
        xy=xy,
        heading=heading,
        s=s,
        length=length,
        curvature=curv,
        lane_offset=offsets,
        lane_length=lane_length,
    )
