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
        cell_keys: [C] int64 sorted keys (``_cell_key``) of the ``MATCH_CELL`` grid cells
            near some segment; cell_bounds: [C + 1] int64 offsets into ``cell_segments``;
            cell_segments: per cell, in increasing order, the segments within
            ``LANE_MATCH_DISTANCE`` of its square (by their bounding boxes).
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
    cell_keys: np.ndarray
    cell_bounds: np.ndarray
    cell_segments: np.ndarray

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
    seg_start, seg_vec = cat(starts, (0, 2)), cat(vecs, (0, 2))
    keys, bounds, members = _segment_cells(seg_start, seg_vec)
    return LaneGraph(
        ids=ids,
        polylines=polylines,
        successors=succ,
        speed_limit=limit,
        links_inferred=not has_links,
        seg_start=seg_start,
        seg_vec=seg_vec,
        seg_lane=np.repeat(np.arange(len(polys)), [len(v) for v in vecs]).astype(np.int64),
        seg_arc=cat(arcs, (0,)),
        cell_keys=keys,
        cell_bounds=bounds,
        cell_segments=members,
    )


MATCH_CELL = 8.0
"""m, side of the grid cells that list the lane segments an agent in them can match."""
_KEY_SPAN = 1 << 31
"""Cell key = ix * _KEY_SPAN + iy (cell indices of any map fit in 31 bits)."""


def _cell_key(ix: np.ndarray, iy: np.ndarray) -> np.ndarray:
    return ix.astype(np.int64) * _KEY_SPAN + iy.astype(np.int64)


def _segment_cells(start: np.ndarray, vec: np.ndarray) -> tuple[np.ndarray, ...]:
    """(keys [C], bounds [C + 1], members) of the cells each segment [E] (start, vector)
    can be matched from: those its bounding box widened by ``LANE_MATCH_DISTANCE`` meets."""
    end = start + vec
    lo = np.floor((np.minimum(start, end) - LANE_MATCH_DISTANCE) / MATCH_CELL).astype(np.int64)
    hi = np.floor((np.maximum(start, end) + LANE_MATCH_DISTANCE) / MATCH_CELL).astype(np.int64)
    nx, ny = hi[:, 0] - lo[:, 0] + 1, hi[:, 1] - lo[:, 1] + 1
    count = nx * ny
    seg = np.repeat(np.arange(len(start), dtype=np.int64), count)
    k = np.arange(len(seg)) - np.repeat(np.cumsum(count) - count, count)  # index in own box
    ix = lo[seg, 0] + k % nx[seg]
    iy = lo[seg, 1] + k // nx[seg]
    key = _cell_key(ix, iy)
    order = np.lexsort((seg, key))  # by cell, then segment
    key, seg = key[order], seg[order]
    keys, first = np.unique(key, return_index=True)
    return keys, np.append(first, len(key)).astype(np.int64), seg


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


_MATCH_CHUNK = 256
"""Agents matched at once (their [agents, segments of their cells] distances)."""


def _match_chunk(graph: LaneGraph, xy: np.ndarray, yaw: np.ndarray) -> tuple[np.ndarray, ...]:
    """``match_lanes`` of a few agents."""
    a = xy.shape[0]
    lane = np.full(a, -1, np.int64)
    arc = np.zeros(a)
    cand = _candidates(graph, xy)  # [A, K] segment rows in increasing order, -1 padding
    if cand.shape[1] == 0:
        return lane, arc
    seg = np.maximum(cand, 0)
    vec = graph.seg_vec[seg]  # [A, K, 2]
    len2 = np.maximum((vec**2).sum(-1), 1e-12)
    rel = xy[:, None, :] - graph.seg_start[seg]
    t = np.clip((rel * vec).sum(-1) / len2, 0.0, 1.0)
    dist = np.linalg.norm(rel - t[..., None] * vec, axis=-1)
    seg_len = np.sqrt(len2)
    heading = np.stack([np.cos(yaw), np.sin(yaw)], -1)  # [A, 2]
    cos = (vec * heading[:, None]).sum(-1) / seg_len
    dist = np.where((cos >= LANE_MATCH_COS) & (cand >= 0), dist, np.inf)
    best = np.argmin(dist, axis=1)  # the first of equals: the lowest segment row, as over all
    rows = np.arange(a)
    ok = dist[rows, best] <= LANE_MATCH_DISTANCE
    hit = seg[rows, best][ok]
    lane[ok] = graph.seg_lane[hit]
    arc[ok] = graph.seg_arc[hit] + t[rows, best][ok] * seg_len[rows, best][ok]
    return lane, arc


def _candidates(graph: LaneGraph, xy: np.ndarray) -> np.ndarray:
    """[A, K] int64: the segments listed in each position's grid cell (every segment within
    ``LANE_MATCH_DISTANCE`` of it is), in increasing order, -1 padding."""
    cell = np.floor(xy / MATCH_CELL).astype(np.int64)
    key = _cell_key(cell[:, 0], cell[:, 1])
    at = np.searchsorted(graph.cell_keys, key).clip(max=max(len(graph.cell_keys) - 1, 0))
    found = len(graph.cell_keys) > 0
    found = found & (graph.cell_keys[at] == key) if found else np.zeros(len(xy), bool)
    lo = np.where(found, graph.cell_bounds[at], 0)
    n = np.where(found, graph.cell_bounds[at + 1] - lo, 0)
    k = np.arange(int(n.max()) if len(n) else 0)
    pick = lo[:, None] + k[None]
    return np.where(
        k[None] < n[:, None],
        graph.cell_segments[np.minimum(pick, len(graph.cell_segments) - 1)],
        -1,
    )


__all__ = ["LaneGraph", "infer_successors", "lane_graph", "match_lanes"]
