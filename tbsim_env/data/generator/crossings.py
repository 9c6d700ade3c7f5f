"""Pedestrians who cross the road on the crosswalks of the junction layouts.

A crossing pedestrian walks in along a walking line beside a junction arm, bends to the kerb
by the arm's crosswalk, waits there until it may cross, crosses on the crosswalk and walks
away on the other side (geometry in ``roads.Crossing``). Its path is a fixed polyline; the
driver (``driver.simulate``) moves it along the path inside its time loop, so that
pedestrians and vehicles react to each other:

* a pedestrian steps off the kerb only inside its walk window (``walk_time_left``: at a
  signalised junction while a phase of the perpendicular arms is green, with time to clear
  the road before that phase ends; always at an unsignalised one), and only when no vehicle
  is on the crosswalk or too close to stop comfortably before it;
* vehicles whose route crosses a crosswalk (``route_crossings``) stop before it, as before a
  stationary leader, while a pedestrian on it has not yet passed their path, and yield to a
  pedestrian about to step off the kerb when they can stop comfortably.

Units: metres, seconds, m/s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tbsim_env.data.generator.geometry import arc_length
from tbsim_env.data.generator.roads import RoadNetwork, SignalPlan
from tbsim_env.data.generator.routes import RouteTable

PED_ACCEL = 1.0
"""Acceleration and deceleration of a crossing pedestrian, m/s^2."""

CROSSWALK_BUFFER = 1.0
"""A route crosses a crosswalk where its centre line comes within this of the polygon, m."""

START_UP_S = 1.5
"""Seconds the next phase's vehicles need to start from their stop line: at a signalised
junction a pedestrian only steps off the kerb if it will have cleared the road by the end of
the walk window's phase plus this (vehicles still yield to one that has not)."""

PATH_CLEARANCE = 2.5
"""A pedestrian has passed a vehicle's path once it is this far beyond the path's extent
across the crosswalk (half the widest vehicle plus half a pedestrian, with a margin), m."""


@dataclass(frozen=True)
class CrossingPlan:
    """P crossing pedestrians: paths and walking parameters.

    Every path has six vertices: far end of the approach walking line, bend, kerb point
    (where the pedestrian waits), far kerb point, bend, far end of the leaving line.

    Attributes:
        crossing: [P] int64 index into ``RoadNetwork.crossings`` (one pedestrian each).
        path: [P, 6, 2] float64 path vertices, metres.
        path_s: [P, 6] float64 arc length of the vertices, metres.
        direction: [P] float64 +1 or -1, sense of the crossing along the crosswalk axis.
        kerb: [P] float64 distance of the kerb points from the arm's centre line, metres.
        s_clear: [P] float64 arc length where the pedestrian has left the road again
            (its box clear of the far road edge), metres.
        speed: [P] float64 walking speed, m/s.
        s0: [P] float64 arc length at the first simulated step, metres.
        size: [P, 3] float64 (length, width, height), metres.
    """

    crossing: np.ndarray
    path: np.ndarray
    path_s: np.ndarray
    direction: np.ndarray
    kerb: np.ndarray
    s_clear: np.ndarray
    speed: np.ndarray
    s0: np.ndarray
    size: np.ndarray

    @property
    def num(self) -> int:
        return int(self.crossing.shape[0])

    @property
    def s_wait(self) -> np.ndarray:
        """[P] arc length of the kerb point where the pedestrian waits, metres."""
        return self.path_s[:, 2]

    @property
    def s_far(self) -> np.ndarray:
        """[P] arc length of the far kerb point, metres."""
        return self.path_s[:, 3]

    def axis_coordinate(self, s: np.ndarray) -> np.ndarray:
        """[P] position across the crosswalk (crosswalk axis, 0 on the arm's centre line)
        at arc lengths s [P], clamped to the kerb points."""
        cross = np.clip(s - self.s_wait, 0.0, self.s_far - self.s_wait)
        return self.direction * (cross - self.kerb)

    def poses(self, s: np.ndarray, speed: np.ndarray) -> tuple[np.ndarray, ...]:
        """Tracks along the paths: (xy [P, T, 2], heading [P, T], velocity [P, T, 2]).

        Args:
            s: [P, T] arc lengths, metres.
            speed: [P, T] speeds, m/s.

        The heading is the one of the path segment ahead (a waiting pedestrian faces the
        road).
        """
        xy = np.zeros(s.shape + (2,))
        heading = np.zeros(s.shape)
        seg = np.diff(self.path, axis=1)  # [P, 5, 2]
        seg_heading = np.arctan2(seg[..., 1], seg[..., 0])
        for i in range(s.shape[0]):
            for d in range(2):
                xy[i, :, d] = np.interp(s[i], self.path_s[i], self.path[i, :, d])
            k = np.searchsorted(self.path_s[i], s[i], side="right") - 1
            heading[i] = seg_heading[i, np.clip(k, 0, seg.shape[1] - 1)]
        vel = speed[..., None] * np.stack([np.cos(heading), np.sin(heading)], axis=-1)
        return xy, heading, vel


def empty_plan() -> CrossingPlan:
    """A plan without pedestrians."""
    z = np.zeros(0)
    return CrossingPlan(
        crossing=np.zeros(0, np.int64),
        path=np.zeros((0, 6, 2)),
        path_s=np.zeros((0, 6)),
        direction=z,
        kerb=z,
        s_clear=z,
        speed=z,
        s0=z,
        size=np.zeros((0, 3)),
    )


def road_extent(net: RoadNetwork) -> np.ndarray:
    """[C, 2] distance from the arm's centre line to the road edge on the -axis and +axis
    side along each crossing line, metres."""
    import shapely

    edges = shapely.MultiLineString([e for e in net.road_edges])
    out = np.zeros((len(net.crossings), 2))
    for c, x in enumerate(net.crossings):
        mid = x.centre + 0.5 * (x.offset[0] + x.offset[1]) * x.along
        hit = shapely.LineString([mid - 2 * x.kerb * x.axis, mid + 2 * x.kerb * x.axis])
        pts = shapely.get_coordinates(hit.intersection(edges))
        q = (pts - mid) @ x.axis
        out[c] = [-q[q < 0].max(), q[q > 0].min()]
    return out


@dataclass(frozen=True)
class RouteCrossings:
    """Where each route crosses each crosswalk (R routes, C crossings); inf / NaN if not.

    Attributes:
        s_in: [R, C] route s where the centre line enters the buffered crosswalk, metres.
        s_out: [R, C] route s where it leaves it, metres.
        q_lo, q_hi: [R, C] extent of the route across the crosswalk (axis coordinate of
            its points inside the buffered crosswalk), metres.
    """

    s_in: np.ndarray
    s_out: np.ndarray
    q_lo: np.ndarray
    q_hi: np.ndarray


def route_crossings(net: RoadNetwork, routes: RouteTable) -> RouteCrossings:
    """Which routes cross which crosswalks, and where (see ``RouteCrossings``)."""
    import shapely

    n_r, n_c = routes.num_routes, len(net.crossings)
    s_in = np.full((n_r, n_c), np.inf)
    s_out = np.full((n_r, n_c), np.inf)
    q_lo = np.full((n_r, n_c), np.nan)
    q_hi = np.full((n_r, n_c), np.nan)
    for c, (x, poly) in enumerate(zip(net.crossings, net.crosswalks)):
        zone = shapely.Polygon(poly).buffer(CROSSWALK_BUFFER)
        inside = shapely.contains_xy(zone, routes.xy[..., 0], routes.xy[..., 1])  # [R, P]
        inside &= routes.s <= routes.length[:, None]
        q = (routes.xy - x.centre) @ x.axis
        hit = inside.any(axis=1)
        s_in[hit, c] = np.where(inside, routes.s, np.inf).min(axis=1)[hit]
        s_out[hit, c] = np.where(inside, routes.s, -np.inf).max(axis=1)[hit]
        q_lo[hit, c] = np.where(inside, q, np.inf).min(axis=1)[hit]
        q_hi[hit, c] = np.where(inside, q, -np.inf).max(axis=1)[hit]
    return RouteCrossings(s_in=s_in, s_out=s_out, q_lo=q_lo, q_hi=q_hi)


def _walk_phases(net: RoadNetwork) -> list[set[int]]:
    """Signal phases during which each crossing may be used: those of the arms
    perpendicular to the crossing's arm (their through traffic runs beside it)."""
    plan = net.signals
    assert plan is not None
    arm_phase = {net.lane(lid).approach: ph for lid, ph in zip(plan.lane_ids, plan.phase)}
    return [{ph for a, ph in arm_phase.items() if (a - x.arm) % 2 == 1} for x in net.crossings]


def walk_time_left(net: RoadNetwork, times: np.ndarray, offset_s: float) -> np.ndarray:
    """Seconds a pedestrian stepping off the kerb has to clear the road, per crossing.

    At a signalised junction a crossing's walk window is the green of a phase of the
    perpendicular arms; the time left runs to the end of that phase (yellow and all-red
    included) plus ``START_UP_S``, when the next phase's movements, some of them through the
    crosswalk, reach it. Outside the windows it is 0. At an unsignalised junction it is
    always inf.

    Args:
        net: road network.
        times: [T] seconds.
        offset_s: signal plan phase offset in seconds.

    Returns:
        [C, T] float64 seconds.
    """
    n_c = len(net.crossings)
    if net.signals is None:
        return np.full((n_c, len(times)), np.inf)
    plan: SignalPlan = net.signals
    t = np.mod(np.asarray(times, float) + offset_s, plan.cycle_s)
    phase = np.floor(t / plan.phase_s).astype(np.int64)
    local = t - phase * plan.phase_s
    out = np.zeros((n_c, len(times)))
    for c, phases in enumerate(_walk_phases(net)):
        open_ = np.isin(phase, list(phases)) & (local < plan.green_s)
        out[c] = np.where(open_, plan.phase_s - local + START_UP_S, 0.0)
    return out


def _signal_timed(
    net: RoadNetwork,
    order: list,
    arrive: np.ndarray,
    offset_s: float,
    rng: np.random.Generator,
) -> tuple[list, np.ndarray]:
    """At a signalised junction: the crossings whose walk window opens first in the logged
    window go first, their pedestrians arriving up to 5 s before it opens; the others 1 s
    later than drawn. Returns (crossing order, arrival times s)."""
    plan = net.signals
    onsets = [
        (ph * plan.phase_s - offset_s + m * plan.cycle_s, ph)
        for ph in range(plan.num_phases)
        for m in range(-2, 3)
    ]
    t_on, ph_on = min((t, ph) for t, ph in onsets if t >= -7.0)
    walk = _walk_phases(net)
    served = [c for c in order if ph_on in walk[c]]
    order = served + [c for c in order if c not in served]
    arrive = np.where(
        np.isin(order, served), t_on + rng.uniform(-5.0, 1.5, len(order)), arrive + 1.0
    )
    return order, arrive


def plan_crossings(
    net: RoadNetwork,
    n: int,
    rng: np.random.Generator,
    warmup_s: float,
    offset_s: float,
    speed_range: tuple[float, float] = (1.2, 1.6),
) -> CrossingPlan:
    """Draw up to n crossing pedestrians (at most one per crossing).

    Each gets a crossing, a side to start from, a crossing line on the crosswalk, a walking
    speed (uniform in ``speed_range``, m/s) and a time to reach the kerb (log time, 0 at the
    first logged step): at a signalised junction, the first two go to the crossings whose
    walk window opens in the logged window (arriving up to 5 s before it opens), the others
    arrive at random; at an unsignalised junction all arrive between -4 s and 5 s.

    Args:
        net: road network (with ``crossings``).
        n: number of pedestrians wanted.
        rng: random generator.
        warmup_s: seconds simulated before the first logged step.
        offset_s: signal plan phase offset in seconds.
        speed_range: walking speed range, m/s.
    """
    n = min(int(n), len(net.crossings))
    if n <= 0:
        return empty_plan()
    order = list(rng.permutation(len(net.crossings)))
    arrive = rng.uniform(-4.0, 5.0, len(order))
    if net.signals is not None:
        order, arrive = _signal_timed(net, order, arrive, offset_s, rng)
    chosen = np.asarray(order[:n], np.int64)
    side = rng.choice([-1.0, 1.0], size=n)
    along = rng.uniform(0.0, 1.0, n)
    speed = rng.uniform(*speed_range, n)
    size = np.stack([rng.uniform(0.6, 0.9, n), rng.uniform(0.6, 0.9, n), rng.uniform(1.6, 1.9, n)])
    extent = road_extent(net)
    path = np.zeros((n, 6, 2))
    kerb = np.zeros(n)
    s_clear = np.zeros(n)
    for i, c in enumerate(chosen):
        x = net.crossings[c]
        u = x.offset[0] + (x.offset[1] - x.offset[0]) * along[i]
        sd = side[i]
        pts = [
            (x.reach, sd * x.walk),
            (x.bend, sd * x.walk),
            (u, sd * x.kerb),
            (u, -sd * x.kerb),
            (x.bend, -sd * x.walk),
            (x.reach, -sd * x.walk),
        ]
        path[i] = [x.centre + a * x.along + q * x.axis for a, q in pts]
        kerb[i] = x.kerb
        far_edge = extent[c, 1] if sd < 0 else extent[c, 0]
        s_clear[i] = x.kerb + far_edge + 0.7  # relative to the kerb point for now
    path_s = arc_length(path)
    s_wait = path_s[:, 2]
    s0 = s_wait - speed * (arrive[:n] + warmup_s)
    return CrossingPlan(
        crossing=chosen,
        path=path,
        path_s=path_s,
        direction=-side,
        kerb=kerb,
        s_clear=s_wait + s_clear,
        speed=speed,
        s0=s0,
        size=size.T,
    )
