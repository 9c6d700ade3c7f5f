"""The lane graph of one scenario (numpy, built once per scenario): lane centre lines, their
successor links and speed limits, and which lane an agent is on.

Links come from the map where the format has them (``RoadMap.exit_lanes`` and
``entry_lanes``: WOMD protos, ScenarioNet); where it has none (GPUDrive and Nocturne JSON,
tf.Example), they are inferred from geometry: lane a leads into lane b when a's last point lies
within ``LINK_TOLERANCE`` of b's first and the heading turns by at most ``LINK_MAX_TURN``
there (on the real samples this gives back the protos' own links: ``tests/test_idm.py``).
Coordinates are the scenario's frame (metres).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from policies.idm.params import (
    LANE_MATCH_COS,
    LANE_MATCH_DISTANCE,
    LINK_MAX_TURN,
    LINK_TOLERANCE,
)
from tbsim_env.core.constants import MPH_TO_MPS, MapFeatureType
from tbsim_env.data.scenario import RoadMap


@dataclass(frozen=True)
class LaneGraph:
    """L lanes of a map with at least two distinct points each.

    Attributes:
        ids: [L] int64 map feature ids.
        polylines: L arrays [n_i, 2] float64, centre lines in driving direction.
        successors: L int64 arrays of lane rows (of this graph) that follow each lane.
        speed_limit: [L] float64 m/s (0: unknown).
        links_inferred: True when the links come from geometry, not from the map.
        seg_start: [E, 2] float64, every lane segment's start (all lanes concatenated).
        seg_vec: [E, 2] float64, segment end - start.
        seg_lane: [E] int64, the lane row of each segment.
        seg_arc: [E] float64, arc length of the segment start along its lane (m).
    """

    ids: np.ndarray
    polylines: tuple[np.ndarray, ...]
    successors: tuple[np.ndarray, ...]
    speed_limit: np.ndarray
    links_inferred: bool
    seg_start: np.ndarray
    seg_vec: np.ndarray
    seg_lane: np.ndarray
    seg_arc: np.ndarray

    @property
    def num_lanes(self) -> int:
        return int(self.ids.shape[0])


def _dedup(xy: np.ndarray) -> np.ndarray:
    """[n, 2] points without consecutive repeats (closer than 1 mm)."""
    if len(xy) < 2:
        return xy
    keep = np.concatenate([[True], np.linalg.norm(np.diff(xy, axis=0), axis=1) > 1e-3])
    return xy[keep]


def _end_heading(xy: np.ndarray, at_start: bool) -> np.ndarray:
    """[2] unit direction of a polyline's first (``at_start``) or last segment."""
    d = xy[1] - xy[0] if at_start else xy[-1] - xy[-2]
    return d / max(float(np.linalg.norm(d)), 1e-9)


def infer_successors(polylines: tuple[np.ndarray, ...]) -> tuple[np.ndarray, ...]:
    """Successor rows of every lane, from geometry alone (see the module docstring).

    Args:
        polylines: L arrays [n_i >= 2, 2], centre lines in driving direction.

    Returns:
        L int64 arrays of lane rows.
    """
    n = len(polylines)
    if n == 0:
        return ()
    starts = np.stack([p[0] for p in polylines])
    ends = np.stack([p[-1] for p in polylines])
    head_in = np.stack([_end_heading(p, True) for p in polylines])
    head_out = np.stack([_end_heading(p, False) for p in polylines])
    near = np.linalg.norm(ends[:, None] - starts[None], axis=-1) <= LINK_TOLERANCE  # [a, b]
    aligned = head_out @ head_in.T >= np.cos(LINK_MAX_TURN)
    link = near & aligned & ~np.eye(n, dtype=bool)
    return tuple(np.flatnonzero(row).astype(np.int64) for row in link)


def _map_successors(m: RoadMap, lanes: np.ndarray, row_of: dict[int, int]) -> tuple:
    """Successor rows from the map's exit lanes and (reversed) entry lanes."""
    succ: list[set[int]] = [set() for _ in lanes]
    for r, k in enumerate(lanes):
        succ[r].update(row_of[int(i)] for i in m.exit_lanes[k] if int(i) in row_of)
        for i in m.entry_lanes[k]:
            if int(i) in row_of:
                succ[row_of[int(i)]].add(r)
    return tuple(np.array(sorted(s - {r}), np.int64) for r, s in enumerate(succ))


def lane_graph(road_map: RoadMap) -> LaneGraph:
    """The lane graph of a map (lanes of fewer than two distinct points are left out)."""
    lanes, polys = [], []
    for k in road_map.indices_of(MapFeatureType.LANE):
        xy = _dedup(np.asarray(road_map.polylines[k][:, :2], np.float64))
        if len(xy) >= 2:
            lanes.append(int(k))
            polys.append(xy)
    lanes_arr = np.array(lanes, np.int64)
    ids = road_map.id[lanes_arr] if lanes else np.zeros(0, np.int64)
    row_of = {int(i): r for r, i in enumerate(ids)}
    has_links = any(len(road_map.exit_lanes[k]) or len(road_map.entry_lanes[k]) for k in lanes_arr)
    polylines = tuple(polys)
    if has_links:
        succ = _map_successors(road_map, lanes_arr, row_of)
    else:
        succ = infer_successors(polylines)
    limit = road_map.speed_limit_mph[lanes_arr].astype(np.float64) * MPH_TO_MPS
    starts = [p[:-1] for p in polylines]
    vecs = [np.diff(p, axis=0) for p in polylines]
    arcs = [np.concatenate([[0.0], np.cumsum(np.linalg.norm(v, axis=1))[:-1]]) for v in vecs]
    cat = lambda parts, shape: np.concatenate(parts) if parts else np.zeros(shape)  # noqa: E731
    return LaneGraph(
        ids=ids,
        polylines=polylines,
        successors=succ,
        speed_limit=limit,
        links_inferred=not has_links,
        seg_start=cat(starts, (0, 2)),
        seg_vec=cat(vecs, (0, 2)),
        seg_lane=np.repeat(np.arange(len(polys)), [len(v) for v in vecs]).astype(np.int64),
        seg_arc=cat(arcs, (0,)),
    )


def match_lanes(graph: LaneGraph, xy: np.ndarray, yaw: np.ndarray) -> tuple[np.ndarray, ...]:
    """The lane each agent is on: the nearest lane segment within ``LANE_MATCH_DISTANCE``
    whose direction is within 45 degrees of the agent's heading.

    Args:
        xy: [A, 2] positions (m); yaw: [A] headings (rad).

    Returns:
        (lane [A] int64 row, -1 where none; arc [A] float64 m of the agent's projection
        along that lane).
    """
    a = xy.shape[0]
    lane = np.full(a, -1, np.int64)
    arc = np.zeros(a)
    if graph.seg_lane.size == 0 or a == 0:
        return lane, arc
    for lo in range(0, a, _MATCH_CHUNK):  # bounds the [agents, segments] temporaries
        part = slice(lo, lo + _MATCH_CHUNK)
        lane[part], arc[part] = _match_chunk(graph, xy[part], yaw[part])
    return lane, arc


_MATCH_CHUNK = 32
"""Agents matched at once (their [agents, segments] distances: ~10k segments per real map)."""


def _match_chunk(graph: LaneGraph, xy: np.ndarray, yaw: np.ndarray) -> tuple[np.ndarray, ...]:
    """``match_lanes`` of a few agents."""
    a = xy.shape[0]
    lane = np.full(a, -1, np.int64)
    arc = np.zeros(a)
    vec = graph.seg_vec
    len2 = np.maximum((vec**2).sum(-1), 1e-12)  # [E]
    rel = xy[:, None, :] - graph.seg_start[None]  # [A, E, 2]
    t = np.clip((rel * vec[None]).sum(-1) / len2, 0.0, 1.0)
    dist = np.linalg.norm(rel - t[..., None] * vec[None], axis=-1)
    seg_len = np.sqrt(len2)
    heading = np.stack([np.cos(yaw), np.sin(yaw)], -1)  # [A, 2]
    cos = (heading @ vec.T) / seg_len[None]
    dist = np.where(cos >= LANE_MATCH_COS, dist, np.inf)
    best = np.argmin(dist, axis=1)
    ok = dist[np.arange(a), best] <= LANE_MATCH_DISTANCE
    lane[ok] = graph.seg_lane[best[ok]]
    arc[ok] = graph.seg_arc[best[ok]] + t[np.arange(a), best][ok] * seg_len[best[ok]]
    return lane, arc


__all__ = ["LaneGraph", "infer_successors", "lane_graph", "match_lanes"]
