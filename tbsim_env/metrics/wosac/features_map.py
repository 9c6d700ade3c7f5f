"""Map-based WOSAC features (docs/metrics.md, "Map-based features").

* signed distance of a box to the road edge (positive = some corner off-road), and off-road,
* traffic-light (red light) violation.

The road-edge search is exact but pruned (see ``segment_search``): the box corners are grouped
per (evaluated object, step, corner) over all rollouts. The lane search of the red-light feature
only runs where a red stop line was crossed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from tbsim_env.core.boxes import box_corners
from tbsim_env.core.constants import LaneType, MapFeatureType, SignalState
from tbsim_env.core.errors import TbsimError
from tbsim_env.data.scenario import Scenario
from tbsim_env.metrics.wosac.config import (
    CYCLIC_POLYLINE_MAX_GAP_SQ,
    NO_PARTNER_DISTANCE,
    ROAD_EDGE_Z_STRETCH,
)
from tbsim_env.metrics.wosac.segment_search import (
    SegmentIndex,
    build_segment_index,
    nearest_segment,
)
from tbsim_env.metrics.wosac.trajectories import ObjectTrajectories

_STEPS_PER_GROUP = 1
"""Steps of one corner of one evaluated object (all rollouts) searched as one group."""
_LANE_PAIRS_PER_CHUNK = 1 << 22
"""(query, lane segment) pairs of one chunk of the red-light lane search (memory bound)."""


class MapFeatureError(TbsimError, ValueError):
    """The scenario's map cannot support a map-based metric (e.g. no road edges)."""


# --------------------------------------------------------------------------- road edges


@dataclass(frozen=True)
class RoadEdgeSegments:
    """All road-edge segments of a scenario, float32.

    Attributes:
        start, end: [S, 3] segment end points (m), polyline order.
        prev, next: [S] int64 index of the neighbouring segment used by the sign rules; a
            segment is its own neighbour where there is none (open polyline ends, and the
            wrap-around of cyclic polylines shorter than the longest road edge).
        index: bounding boxes for the nearest-segment search.
    """

    start: torch.Tensor
    end: torch.Tensor
    prev: torch.Tensor
    next: torch.Tensor
    index: SegmentIndex

    @property
    def num_segments(self) -> int:
        return int(self.start.shape[0])


def road_edge_segments(scenario: Scenario, device: torch.device | str = "cpu") -> RoadEdgeSegments:
    """Segments of every road-edge polyline with at least 2 points (boundaries and medians).

    A polyline is cyclic if its first and last points are less than 1 m apart; only cyclic
    polylines with as many points as the longest road edge wrap around (the official padding
    quirk, docs/metrics.md, "Distance to road edge").

    Raises:
        MapFeatureError: if the scenario has no usable road edge.
    """
    rm = scenario.road_map
    lines = [
        np.asarray(rm.polylines[i], np.float32) for i in rm.indices_of(MapFeatureType.ROAD_EDGE)
    ]
    lines = [p for p in lines if p.shape[0] >= 2]
    if not lines:
        raise MapFeatureError(f"scenario {scenario.scenario_id}: no road edge in the map")
    longest = max(p.shape[0] for p in lines)
    starts, ends, prevs, nexts = [], [], [], []
    offset = 0
    for p in lines:
        k = p.shape[0] - 1
        own = np.arange(offset, offset + k)
        prev = np.concatenate([[own[0]], own[:-1]])
        nxt = np.concatenate([own[1:], [own[-1]]])
        gap = p[-1, :2] - p[0, :2]
        if p.shape[0] == longest and float(gap @ gap) < CYCLIC_POLYLINE_MAX_GAP_SQ:
            prev[0], nxt[-1] = own[-1], own[0]
        starts.append(p[:-1])
        ends.append(p[1:])
        prevs.append(prev)
        nexts.append(nxt)
        offset += k

    def cat(parts: list[np.ndarray], dtype: torch.dtype) -> torch.Tensor:
        return torch.as_tensor(np.concatenate(parts), dtype=dtype, device=device)

    start, end = cat(starts, torch.float32), cat(ends, torch.float32)
    return RoadEdgeSegments(
        start=start,
        end=end,
        prev=cat(prevs, torch.int64),
        next=cat(nexts, torch.int64),
        index=build_segment_index(start, end),
    )


def box_bottom_corners(traj: ObjectTrajectories) -> torch.Tensor:
    """The 4 bottom corners (x, y, z - H/2) of the full boxes of the evaluated objects.

    Returns:
        [R, E, T, 4, 3] corners in metres.
    """
    e = traj.num_eval
    pose = torch.stack([traj.x[:, :e], traj.y[:, :e], traj.heading[:, :e]], -1)  # [R, E, T, 3]
    xy = box_corners(pose, traj.length[None, :e, None], traj.width[None, :e, None])
    z = (traj.z[:, :e] - traj.height[:e, None] / 2.0)[..., None, None].expand(*xy.shape[:-1], 1)
    return torch.cat([xy, z], dim=-1)


def _group_queries(points: torch.Tensor, steps_per_group: int) -> tuple[torch.Tensor, int]:
    """[R, E, T, K, D] -> [G, M, D]: one group per (object, step chunk, corner), all rollouts.

    T is padded to a multiple of ``steps_per_group`` by repeating the last step.
    """
    r, e, t, k, d = points.shape
    pad = (-t) % steps_per_group
    if pad:
        points = torch.cat([points, points[:, :, -1:].expand(r, e, pad, k, d)], dim=2)
    tg = (t + pad) // steps_per_group
    grouped = points.reshape(r, e, tg, steps_per_group, k, d).permute(1, 2, 4, 0, 3, 5)
    return grouped.reshape(e * tg * k, r * steps_per_group, d), pad


def _ungroup(
    values: torch.Tensor, shape: tuple[int, int, int, int], steps_per_group: int, pad: int
) -> torch.Tensor:
    """Inverse of ``_group_queries`` for [G, M] values -> [R, E, T, K]."""
    r, e, t, k = shape
    tg = (t + pad) // steps_per_group
    v = values.reshape(e, tg, k, r, steps_per_group).permute(3, 0, 1, 4, 2)
    return v.reshape(r, e, tg * steps_per_group, k)[:, :, :t]


def _cross2(u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]


def signed_distance_to_road_edge_points(
    points: torch.Tensor, include: torch.Tensor, segs: RoadEdgeSegments
) -> torch.Tensor:
    """Signed 2-D distance of grouped points to the road edge (positive = off-road side).

    The segment is chosen by the 3-D distance with z stretched by 3; the magnitude is the 2-D
    distance to it and the sign comes from the side (right of the polyline is off-road), with
    the convex/concave junction rules at segment ends (docs/metrics.md, "Distance to road edge").

    Args:
        points: [G, M, 3] query points (m), grouped by proximity.
        include: [G, M] bool points that bound their group (see ``nearest_segment``).
        segs: the road edges.

    Returns:
        [G, M] signed distance (m).
    """
    seg = nearest_segment(points, include, segs.index, (1.0, 1.0, ROAD_EDGE_Z_STRETCH))
    return _signed_distance_to_segment(points, seg, segs)


def _signed_distance_to_segment(
    points: torch.Tensor, seg: torch.Tensor, segs: RoadEdgeSegments
) -> torch.Tensor:
    """Signed 2-D distance of points [..., 3] to their chosen segments [...] (index)."""
    a, b = segs.start[seg], segs.end[seg]
    ab = b - a
    aq = points - a
    len2 = (ab[..., :2] * ab[..., :2]).sum(-1)
    t = (aq[..., :2] * ab[..., :2]).sum(-1) / torch.where(len2 > 0, len2, 1.0)
    t = torch.where(len2 > 0, t, 0.0)
    diff = aq - t.clamp(0.0, 1.0).unsqueeze(-1) * ab
    dist2 = torch.linalg.vector_norm(diff[..., :2], dim=-1)
    n = torch.sign(_cross2(aq, ab))

    def neighbour_sign(nb: torch.Tensor, convex: torch.Tensor) -> torch.Tensor:
        an, bn = segs.start[nb], segs.end[nb]
        n_nb = torch.sign(_cross2(points - an, bn - an))
        return torch.where(convex, torch.maximum(n, n_nb), torch.minimum(n, n_nb))

    prev, nxt = segs.prev[seg], segs.next[seg]
    d_prev = segs.end[prev] - segs.start[prev]
    d_next = segs.end[nxt] - segs.start[nxt]
    sign_prev = neighbour_sign(prev, _cross2(d_prev, ab) > 0.0)
    sign_next = neighbour_sign(nxt, _cross2(ab, d_next) > 0.0)
    sign = torch.where((t < 0.0) & (prev != seg), sign_prev, n)
    sign = torch.where((t > 1.0) & (nxt != seg), sign_next, sign)
    return sign * dist2


def distance_to_road_edge(traj: ObjectTrajectories, segs: RoadEdgeSegments) -> torch.Tensor:
    """Signed distance of each evaluated box to the road edge: max over its 4 bottom corners.

    Positive means at least one corner is off-road. Invalid objects get -1e10.

    Args:
        traj: [R, N, T] trajectories, evaluated first.
        segs: the scenario's road edges.

    Returns:
        [R, E, T] distance in metres.
    """
    corners = box_bottom_corners(traj)  # [R, E, T, 4, 3]
    r, e, t = corners.shape[:3]
    ok = traj.valid[:, :e, :, None] & torch.isfinite(corners).all(-1)  # [R, E, T, 4]
    grouped, pad = _group_queries(corners, _STEPS_PER_GROUP)
    finite, _ = _group_queries(ok.unsqueeze(-1), _STEPS_PER_GROUP)
    dist = signed_distance_to_road_edge_points(grouped, finite[..., 0], segs)
    dist = _ungroup(dist, (r, e, t, 4), _STEPS_PER_GROUP, pad).amax(-1)
    return torch.where(traj.valid[:, :e], dist, -NO_PARTNER_DISTANCE)


# --------------------------------------------------------------------------- traffic lights

_RED_STATES = (int(SignalState.STOP), int(SignalState.ARROW_STOP))


@dataclass(frozen=True)
class TrafficLightMap:
    """Surface-street lane segments and the red-light stop lines of a scenario.

    Attributes:
        lane_start, lane_end: [L, 2] float32 segments of every surface-street lane (m).
        lane_of_segment: [L] int64 index of the segment's lane.
        signal_lane: [K] int64 lane index of each signal (-1: not a surface-street lane).
        stop_point: [K, 2] float32 stop point (m).
        stop_dir: [K, 2] float32 direction of the signal lane's segment nearest the stop point.
        red: [K, T] bool, signal valid and in STOP or ARROW_STOP at step t.
    """

    lane_start: torch.Tensor
    lane_end: torch.Tensor
    lane_of_segment: torch.Tensor
    signal_lane: torch.Tensor
    stop_point: torch.Tensor
    stop_dir: torch.Tensor
    red: torch.Tensor

    @property
    def is_empty(self) -> bool:
        return self.lane_start.shape[0] == 0 or self.signal_lane.shape[0] == 0


def _quirk_lane_distance(q: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """The official lane distance ||(q - a) + clip(t, 0, 1) (b - a)|| (a "+" for "-"), 2-D."""
    ab = b - a
    aq = q - a
    len2 = (ab * ab).sum(-1)
    t = (aq * ab).sum(-1) / torch.where(len2 > 0, len2, 1.0)
    t = torch.where(len2 > 0, t, 0.0).clamp(0.0, 1.0)
    return torch.linalg.vector_norm(aq + t.unsqueeze(-1) * ab, dim=-1)


def traffic_light_map(scenario: Scenario, device: torch.device | str = "cpu") -> TrafficLightMap:
    """Collect the surface-street lanes and red-light stop lines of a scenario."""
    rm = scenario.road_map
    lane_idx = [
        int(i)
        for i in rm.indices_of(MapFeatureType.LANE)
        if int(rm.subtype[i]) == int(LaneType.SURFACE_STREET) and rm.polylines[i].shape[0] >= 2
    ]
    lane_pos = {int(rm.id[i]): k for k, i in enumerate(lane_idx)}
    polys = [np.asarray(rm.polylines[i][:, :2], np.float32) for i in lane_idx]
    starts = [p[:-1] for p in polys] or [np.zeros((0, 2), np.float32)]
    ends = [p[1:] for p in polys] or [np.zeros((0, 2), np.float32)]
    owner = [np.full(p.shape[0] - 1, k, np.int64) for k, p in enumerate(polys)]
    owner = owner or [np.zeros(0, np.int64)]
    sig = scenario.signals
    signal_lane = np.array([lane_pos.get(int(i), -1) for i in sig.lane_id], np.int64)
    stop = np.asarray(sig.stop_point[:, :2], np.float32).reshape(-1, 2)
    stop_dir = np.zeros_like(stop)
    for k, lane in enumerate(signal_lane):
        if lane < 0:
            continue
        p = polys[lane]
        a, b = torch.as_tensor(p[:-1]), torch.as_tensor(p[1:])
        near = int(_quirk_lane_distance(torch.as_tensor(stop[k]), a, b).argmin())
        stop_dir[k] = p[near + 1] - p[near]
    red = np.isin(sig.state, _RED_STATES) & sig.valid
    return TrafficLightMap(
        lane_start=torch.as_tensor(np.concatenate(starts), device=device),
        lane_end=torch.as_tensor(np.concatenate(ends), device=device),
        lane_of_segment=torch.as_tensor(np.concatenate(owner), device=device),
        signal_lane=torch.as_tensor(signal_lane, device=device),
        stop_point=torch.as_tensor(stop, device=device),
        stop_dir=torch.as_tensor(stop_dir, device=device),
        red=torch.as_tensor(red, device=device),
    )


def traffic_light_violation(traj: ObjectTrajectories, tl: TrafficLightMap) -> torch.Tensor:
    """Red-light violations of the evaluated objects, per step (every object type).

    Object o violates signal k at step t if o is valid at t, its lane (the lane of the nearest
    surface-street segment, official distance quirk) is k's lane, k is red at t, and o crossed
    k's stop line between t-1 and t (projections on the stop segment's direction: strictly
    behind at t-1, at or past at t). Lanes are only searched where a crossing of a red stop line
    happened, which gives the same result as searching everywhere.

    Args:
        traj: [R, N, T] trajectories, evaluated first.
        tl: the scenario's lanes and signals (T steps).

    Returns:
        [R, E, T] bool.
    """
    e = traj.num_eval
    r, _, t = traj.x.shape
    out = torch.zeros(r, e, t, dtype=torch.bool, device=traj.x.device)
    if tl.is_empty or t < 2:
        return out
    pos = torch.stack([traj.x[:, :e], traj.y[:, :e]], -1)  # [R, E, T, 2]
    along = (pos.unsqueeze(-2) * tl.stop_dir).sum(-1)  # [R, E, T, K]
    line = (tl.stop_point * tl.stop_dir).sum(-1)  # [K]
    crossed = torch.zeros_like(along, dtype=torch.bool)
    crossed[:, :, 1:] = (along[:, :, :-1] < line) & (along[:, :, 1:] >= line)
    cand = crossed & tl.red.T[None, None, :t] & (tl.signal_lane >= 0)
    cand &= traj.valid[:, :e].unsqueeze(-1)
    hit = cand.any(-1)
    if not bool(hit.any()):
        return out
    r_i, e_i, t_i = hit.nonzero(as_tuple=True)
    q = pos[r_i, e_i, t_i]  # [Q, 2]
    step = max(1, _LANE_PAIRS_PER_CHUNK // max(1, tl.lane_start.shape[0]))
    nearest = [
        _quirk_lane_distance(q[i : i + step, None], tl.lane_start[None], tl.lane_end[None]).argmin(
            -1
        )
        for i in range(0, q.shape[0], step)
    ]
    lane = tl.lane_of_segment[torch.cat(nearest)]  # [Q]
    match = cand[r_i, e_i, t_i] & (tl.signal_lane[None, :] == lane[:, None])
    out[r_i, e_i, t_i] = match.any(-1)
    return out
