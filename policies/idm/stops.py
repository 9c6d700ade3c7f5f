"""Where routes meet stop lines and crosswalks (numpy, once per scenario and route set).

A *stop line* is the first point of a controlled lane: a traffic signal's ``stop_point`` (the
start of the lane it controls, in WOMD) or the start of a lane a stop sign controls. A route
passes a stop line when that point lies within ``STOP_MATCH_DISTANCE`` of the route, the route
heads the lane's way there, and the lane's points 5 m and 10 m on stay within
``STOP_FOLLOW_DISTANCE`` of the route (so a straight route does not take the red arrow of the
turn lane that starts at the same point). Matching is by geometry alone, the same for logged and
lane routes and for maps without lane ids.

A stop sign's controlled lanes come from the map (``RoadMap.controlled_lanes``); formats without
them (GPUDrive JSON) use the lanes that start within ``SIGN_LANE_RADIUS`` of the sign, with the
sign behind their start and not on their left.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from policies.idm.lanes import LaneGraph
from policies.idm.params import (
    CROSSWALK_VERTICES,
    MAX_CROSSWALKS,
    MAX_SIGN_STOPS,
    MAX_SIGNAL_STOPS,
    ROUTE_SPACING,
    SCENE_CROSSWALKS,
    SIGN_LANE_RADIUS,
    STOP_FOLLOW_DISTANCE,
    STOP_MATCH_DISTANCE,
)
from tbsim_env.core.constants import MapFeatureType
from tbsim_env.data.scenario import Scenario

FOLLOW_CHECKS = (5.0, 10.0)
"""m along a controlled lane (clipped to its length) that must stay near a matching route."""
ALIGNED_COS = 0.7
"""A route heads a lane's way when their directions' cosine is at least this."""


@dataclass(frozen=True)
class StopLine:
    """A stop line: the first point of a controlled lane.

    Attributes:
        point: [2] m.
        lane: [n, 2] the controlled lane's centre line (n >= 2), or None when the map lacks it.
    """

    point: np.ndarray
    lane: np.ndarray | None


@dataclass(frozen=True)
class RouteEvents:
    """Stop lines and crosswalks along the routes of A agents.

    Attributes:
        signal_arc: [A, Ks] float64 arc (m) of the signal stop lines, +inf padding.
        signal_row: [A, Ks] int64 row of ``Scenario.signals`` (-1 padding).
        sign_arc: [A, Kt] float64 arc of the stop-sign lines, +inf padding.
        crosswalk_arc: [A, Kc] float64 arc where the route enters a crosswalk, +inf padding.
        crosswalk_row: [A, Kc] int64 row of ``crosswalk_polygons`` (-1 padding).
    """

    signal_arc: np.ndarray
    signal_row: np.ndarray
    sign_arc: np.ndarray
    crosswalk_arc: np.ndarray
    crosswalk_row: np.ndarray

    def scattered(self, rows: np.ndarray, a: int) -> RouteEvents:
        """These events (of the routes ``rows`` [R] of A) at their rows of A; the other rows
        have none."""

        def put(x: np.ndarray, pad: float) -> np.ndarray:
            out = np.full((a, x.shape[1]), pad, x.dtype)
            out[rows] = x
            return out

        return RouteEvents(
            put(self.signal_arc, np.inf),
            put(self.signal_row, -1),
            put(self.sign_arc, np.inf),
            put(self.crosswalk_arc, np.inf),
            put(self.crosswalk_row, -1),
        )


def _point_at(poly: np.ndarray, s: float) -> np.ndarray:
    """[2] point ``s`` m along a polyline (clipped to its length)."""
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(poly, axis=0), axis=1))])
    s = min(s, float(cum[-1]))
    return np.array([np.interp(s, cum, poly[:, 0]), np.interp(s, cum, poly[:, 1])])


def _project(points: np.ndarray, q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Nearest route point to ``q`` of every route: (arc [A] m refined along the segment
    there, distance [A] m, unit route direction [A, 2] there).

    Args:
        points: [A, P, 2] routes; q: [2].
    """
    d = np.linalg.norm(points - q, axis=-1)  # [A, P]
    k = np.minimum(np.argmin(d, axis=1), points.shape[1] - 2)
    rows = np.arange(points.shape[0])
    seg = points[rows, k + 1] - points[rows, k]
    u = seg / np.maximum(np.linalg.norm(seg, axis=-1, keepdims=True), 1e-9)
    along = ((q - points[rows, k]) * u).sum(-1)
    return k * ROUTE_SPACING + along, d.min(1), u


def _passes(points: np.ndarray, line: StopLine) -> tuple[np.ndarray, np.ndarray]:
    """(does each route pass the stop line [A] bool, its arc [A] m)."""
    arc, dist, u = _project(points, line.point)
    ok = dist <= STOP_MATCH_DISTANCE
    if line.lane is not None:
        lane_dir = line.lane[1] - line.lane[0]
        lane_dir = lane_dir / max(float(np.linalg.norm(lane_dir)), 1e-9)
        ok &= u @ lane_dir >= ALIGNED_COS
        for s in FOLLOW_CHECKS:
            q = _point_at(line.lane, s)
            ok &= np.linalg.norm(points - q, axis=-1).min(1) <= STOP_FOLLOW_DISTANCE
    return ok, arc


def _first_k(
    arcs: list[np.ndarray], hits: list[np.ndarray], k: int, a: int
) -> tuple[np.ndarray, ...]:
    """The ``k`` smallest arcs of the hits (C lists of [A]) per route of A: (arc [A, k] +inf
    padded, column [A, k] of the candidate, -1 padded)."""
    if not hits:
        return np.full((a, k), np.inf), np.full((a, k), -1, np.int64)
    arc = np.where(np.stack(hits, 1), np.stack(arcs, 1), np.inf)  # [A, C]
    order = np.argsort(arc, axis=1, kind="stable")[:, :k]
    out = np.take_along_axis(arc, order, 1)
    col = np.where(np.isfinite(out), order, -1)
    pad = k - out.shape[1]
    return np.pad(out, ((0, 0), (0, pad)), constant_values=np.inf), np.pad(
        col, ((0, 0), (0, pad)), constant_values=-1
    )


def signal_lines(scenario: Scenario, graph: LaneGraph) -> list[StopLine]:
    """The stop line of every signal row of the scenario (in row order)."""
    row_of = {int(i): r for r, i in enumerate(graph.ids)}
    lines = []
    for r in range(scenario.signals.num_signals):
        lane = row_of.get(int(scenario.signals.lane_id[r]))
        poly = graph.polylines[lane] if lane is not None else None
        lines.append(StopLine(scenario.signals.stop_point[r, :2].astype(np.float64), poly))
    return lines


def sign_lines(scenario: Scenario, graph: LaneGraph) -> list[StopLine]:
    """The stop lines of every stop sign (the starts of its controlled lanes)."""
    m = scenario.road_map
    row_of = {int(i): r for r, i in enumerate(graph.ids)}
    lines = []
    for k in m.indices_of(MapFeatureType.STOP_SIGN):
        rows = [row_of[int(i)] for i in m.controlled_lanes[k] if int(i) in row_of]
        if not len(m.controlled_lanes[k]):
            rows = infer_sign_lanes(m.polylines[k][0, :2].astype(np.float64), graph)
        lines += [StopLine(graph.polylines[r][0], graph.polylines[r]) for r in rows]
    return lines


def infer_sign_lanes(sign: np.ndarray, graph: LaneGraph) -> list[int]:
    """Lane rows a stop sign at ``sign`` [2] controls when the map does not say (see the
    module docstring)."""
    out = []
    for r, poly in enumerate(graph.polylines):
        rel = sign - poly[0]
        d = poly[1] - poly[0]
        d = d / max(float(np.linalg.norm(d)), 1e-9)
        along, left = float(rel @ d), float(d[0] * rel[1] - d[1] * rel[0])
        if np.hypot(along, left) <= SIGN_LANE_RADIUS and along <= 0.0 and left <= 0.0:
            out.append(r)
    return out


def crosswalk_polygons(scenario: Scenario) -> np.ndarray:
    """[W, V, 2] float64 crosswalk outlines (``SCENE_CROSSWALKS``, ``CROSSWALK_VERTICES``;
    shorter outlines repeat their last vertex), at most ``SCENE_CROSSWALKS``."""
    m = scenario.road_map
    out = []
    for k in m.indices_of(MapFeatureType.CROSSWALK)[:SCENE_CROSSWALKS]:
        xy = m.polylines[k][:, :2].astype(np.float64)
        if len(xy) < 3:
            continue
        xy = xy[:CROSSWALK_VERTICES]
        out.append(np.concatenate([xy, np.repeat(xy[-1:], CROSSWALK_VERTICES - len(xy), 0)]))
    return np.stack(out) if out else np.zeros((0, CROSSWALK_VERTICES, 2))


def inside_polygons(xy: np.ndarray, polygons: np.ndarray) -> np.ndarray:
    """[..., W] bool: points [..., 2] inside polygons [W, V, 2] (even-odd rule)."""
    a = polygons
    b = np.roll(polygons, -1, axis=1)
    px, py = xy[..., None, None, 0], xy[..., None, None, 1]
    crosses = (a[..., 1] > py) != (b[..., 1] > py)
    dy = np.where(b[..., 1] == a[..., 1], 1e-12, b[..., 1] - a[..., 1])
    x_at = a[..., 0] + (py - a[..., 1]) * (b[..., 0] - a[..., 0]) / dy
    return (crosses & (px < x_at)).sum(-1) % 2 == 1


def route_events(points: np.ndarray, scenario: Scenario, graph: LaneGraph) -> RouteEvents:
    """Stop lines and crosswalks along routes [A, P, 2] of the scenario's tracks."""
    signal_arc, signal_row = _first_lines(points, signal_lines(scenario, graph), MAX_SIGNAL_STOPS)
    sign_arc, _ = _first_lines(points, sign_lines(scenario, graph), MAX_SIGN_STOPS)
    cw_arc, cw_row = _crosswalk_entries(points, crosswalk_polygons(scenario))
    return RouteEvents(signal_arc, signal_row, sign_arc, cw_arc, cw_row)


def _first_lines(points: np.ndarray, lines: list[StopLine], k: int) -> tuple[np.ndarray, ...]:
    """The first ``k`` of ``lines`` along each route [A, P, 2]: ``_first_k`` of their arcs.

    A line is tested only on the routes whose bounding box, widened by
    ``STOP_MATCH_DISTANCE``, holds its point (no other route comes that near it)."""
    a = len(points)
    lo = points.min(1) - STOP_MATCH_DISTANCE  # [A, 2]
    hi = points.max(1) + STOP_MATCH_DISTANCE
    arcs, hits = [], []
    for line in lines:
        near = np.flatnonzero(((line.point >= lo) & (line.point <= hi)).all(-1))
        ok, arc = np.zeros(a, bool), np.full(a, np.inf)
        if len(near):
            ok[near], arc[near] = _passes(points[near], line)
        arcs.append(arc)
        hits.append(ok)
    return _first_k(arcs, hits, k, a)


def _crosswalk_entries(points: np.ndarray, polygons: np.ndarray) -> tuple[np.ndarray, ...]:
    """(arc [A, Kc] where each route first enters each crosswalk it crosses, row [A, Kc])."""
    a = points.shape[0]
    mid = 0.5 * (points[:, 1:] + points[:, :-1])
    dense = np.stack([points[:, :-1], mid], 2).reshape(a, -1, 2)  # every ROUTE_SPACING / 2
    arcs, hits = [], []
    for poly in polygons:
        lo, hi = poly.min(0), poly.max(0)
        near = ((dense >= lo) & (dense <= hi)).all(-1)  # [A, D], the bounding box first
        inside = np.zeros_like(near)
        if near.any():
            inside[near] = inside_polygons(dense[near], poly[None])[:, 0]
        first = np.argmax(inside, axis=1)
        hits.append(inside.any(1))
        arcs.append(np.maximum(first - 1, 0) * (0.5 * ROUTE_SPACING))
    return _first_k(arcs, hits, MAX_CROSSWALKS, a)


__all__ = [
    "RouteEvents",
    "StopLine",
    "crosswalk_polygons",
    "infer_sign_lanes",
    "inside_polygons",
    "route_events",
    "sign_lines",
    "signal_lines",
]
