"""Rule-based driver of the generator: lane routes, IDM car following, signals, merges and
crossing pedestrians.

Every vehicle moves along its route (a lane path chosen at spawn) by its arc length ``s``.
Each step a vehicle takes the lowest of these IDM accelerations:

* free road toward its desired speed, capped by the route curvature ahead (lateral accel);
* following the nearest vehicle ahead on its route (including a vehicle that just diverged
  onto a sibling connector, and the merge partner lane seen in merge coordinates);
* stopping before a stop line, treated as a stationary leader, when the lane's signal is
  red, or yellow and the vehicle can stop comfortably, or when vehicles of another
  intersection approach are still in the box;
* stopping before the conflict point of a merging lane until a gap is accepted;
* at an unsignalised junction (``RoadNetwork.junction``), stopping at the line until the
  vehicle's connector is granted: stop-sign approaches first come to a full stop, lower
  priority movements wait for an accepted time gap to higher priority traffic, and a
  connector is never granted while a conflicting one is held by another vehicle; at a
  signalised junction with permissive turns the same rules order the vehicles whose light
  lets them go (a left turn waits on the green for a gap in oncoming traffic);
* stopping before a crosswalk on its route while a pedestrian crossing there has not yet
  passed the vehicle's path, or is about to step off the kerb and the vehicle can stop
  comfortably (the pedestrians move in the same loop, see ``crossings``).

Drivers differ: each vehicle gets a personality in [-1 (timid), 1 (aggressive)] around a
per-scene mean, which sets its desired speed, headway, standstill gap, acceleration,
braking, reaction time at stop signs and accepted gap; vehicles are cars, vans and
occasional trucks or buses (these keep to routes without sharp turns). On urban roads a
per-scene share of the slots are cyclists (``add_cyclists``): bicycle-sized riders on
kerb-lane routes with lower desired speeds and gentler acceleration, driven by the same
rules (signals, stop signs, priority), so that the vehicles behind them queue.

The loop runs over time only; every per-vehicle operation is vectorised over vehicles (and
pedestrians).
Units: metres, seconds, m/s, m/s^2.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from tbsim_env.core.constants import DT, SignalState
from tbsim_env.data.generator.crossings import (
    PATH_CLEARANCE,
    PED_ACCEL,
    CrossingPlan,
    RouteCrossings,
    empty_plan,
    route_crossings,
    walk_time_left,
)
from tbsim_env.data.generator.roads import STOP, RoadNetwork, connector_conflicts, signal_states
from tbsim_env.data.generator.routes import RouteTable

_BIG = 1.0e9


@dataclass(frozen=True)
class DriverConfig:
    """Ranges of driver parameters (drawn uniformly per vehicle) and global settings.

    Attributes:
        desired_speed: desired speed range, m/s.
        time_headway: IDM time headway range, s.
        min_gap: IDM standstill gap range, m.
        max_accel: IDM maximum acceleration range, m/s^2.
        comfort_decel: IDM comfortable deceleration range, m/s^2.
        max_decel: hard braking limit, m/s^2 (positive).
        lateral_accel: lateral acceleration used to cap speed in bends, m/s^2.
        yellow_decel: a vehicle stops at yellow when this deceleration suffices, m/s^2.
        inflow: mean vehicles per second entering through each source lane.
        warmup_s: seconds simulated before the first logged step.
        diverge_clear: a vehicle on a sibling connector stays a leader until its rear is this
            far past the branch point, m.
        merge_front_gap: accepted merge gap ahead = this + 1.0 s * own speed, m.
        merge_rear_gap: accepted merge gap behind = this + 1.5 s * follower speed + 2 s *
            closing speed, m.
        reaction: range of the dwell after a full stop before a vehicle may go, s.
        gap_time: range of the accepted time gap to higher-priority traffic at a junction, s.
        personality_mean: range of the per-scene mean personality (-1 timid, 1 aggressive).
        personality_spread: standard deviation of the personality around the scene mean.
        van_share: range of the per-scene share of vans (5-6.5 m).
        truck_share: range of the per-scene share of trucks and buses (8-12 m).
        straight_curvature: trucks and buses only take routes whose curvature stays below
            this, 1/m.
        cyclist_share: range of the per-scene share of cyclists (0 on roads without them);
            drawn by ``add_cyclists`` from its own random stream.
        cyclist_speed: desired speed range of cyclists, m/s.
        cyclist_accel: maximum acceleration range of cyclists, m/s^2.
        cyclist_decel: comfortable deceleration range of cyclists, m/s^2.

    All ranges are (timid end, aggressive end) ordered low to high; a vehicle's value is
    placed in its range by its personality (70 %) and independent noise (30 %). The defaults
    are the hand-set values; ``generate_scenario`` replaces the desired speeds, acceleration,
    braking, headway, gap, bend and cyclist parameters by those of its ``Behaviour``
    (``behaviour.CALIBRATED`` by default, fitted to real scenes).
    """

    desired_speed: tuple[float, float]
    time_headway: tuple[float, float] = (0.9, 2.2)
    min_gap: tuple[float, float] = (1.8, 3.5)
    max_accel: tuple[float, float] = (1.1, 2.4)
    comfort_decel: tuple[float, float] = (1.5, 3.0)
    reaction: tuple[float, float] = (0.4, 1.6)
    gap_time: tuple[float, float] = (3.5, 6.5)
    personality_mean: tuple[float, float] = (-0.35, 0.35)
    personality_spread: float = 0.45
    van_share: tuple[float, float] = (0.05, 0.2)
    truck_share: tuple[float, float] = (0.0, 0.1)
    straight_curvature: float = 0.02
    cyclist_share: tuple[float, float] = (0.0, 0.0)
    cyclist_speed: tuple[float, float] = (4.0, 7.0)
    cyclist_accel: tuple[float, float] = (0.8, 1.5)
    cyclist_decel: tuple[float, float] = (1.5, 2.5)
    max_decel: float = 5.0
    lateral_accel: float = 2.0
    yellow_decel: float = 3.0
    inflow: float = 0.08
    warmup_s: float = 12.0
    diverge_clear: float = 10.0
    merge_front_gap: float = 4.0
    merge_rear_gap: float = 6.0


@dataclass(frozen=True)
class Fleet:
    """Static per-vehicle attributes, N vehicle slots (spawned or not).

    Attributes:
        route: [N] int64 route index.
        size: [N, 3] float64 (length, width, height) in metres.
        desired_speed, time_headway, min_gap, max_accel, comfort_decel: [N] float64 IDM
            parameters in SI units.
        reaction: [N] float64 dwell after a full stop, s.
        gap_time: [N] float64 accepted time gap to higher-priority traffic, s.
        personality: [N] float64 in [-1 (timid), 1 (aggressive)].
        cyclist: [N] bool, the slot is a cyclist (kerb-lane routes only), else a motor vehicle.
    """

    route: np.ndarray
    size: np.ndarray
    desired_speed: np.ndarray
    time_headway: np.ndarray
    min_gap: np.ndarray
    max_accel: np.ndarray
    comfort_decel: np.ndarray
    reaction: np.ndarray
    gap_time: np.ndarray
    personality: np.ndarray
    cyclist: np.ndarray

    @property
    def is_long(self) -> np.ndarray:
        """[N] bool, trucks and buses (longer than 7.5 m)."""
        return self.size[:, 0] > 7.5


@dataclass(frozen=True)
class DriveLog:
    """Simulated trajectories along routes, N vehicle slots over T steps.

    Attributes:
        fleet: per-vehicle attributes.
        s: [N, T] float64 route arc length of the box centre, metres.
        speed: [N, T] float64 m/s.
        alive: [N, T] bool, on the map at that step.
        crossing: the crossing pedestrians' plan (P pedestrians).
        ped_s: [P, T] float64 arc length of each crossing pedestrian along its path, m.
        ped_speed: [P, T] float64 m/s.
    """

    fleet: Fleet
    s: np.ndarray
    speed: np.ndarray
    alive: np.ndarray
    crossing: CrossingPlan
    ped_s: np.ndarray
    ped_speed: np.ndarray


CAR_SIZE = (4.6, 1.9, 1.6)
"""(length, width, height) in metres given to a truck slot that can only take turning routes."""


def straight_routes(routes: RouteTable, cfg: DriverConfig) -> np.ndarray:
    """[R] bool, routes that trucks and buses may take (no sharp turns)."""
    return routes.curvature.max(axis=1) < cfg.straight_curvature


def _trait(
    r: tuple[float, float], sign: float, pers: np.ndarray, rng: np.random.Generator
) -> np.ndarray:
    """Value in range r: higher for aggressive drivers if sign > 0, else lower (70 %
    personality, 30 % independent noise)."""
    x = 0.5 + 0.5 * (0.7 * sign * pers + 0.3 * rng.uniform(-1.0, 1.0, pers.shape))
    return r[0] + (r[1] - r[0]) * np.clip(x, 0.0, 1.0)


CAR_SIZE_RANGE: tuple[tuple[float, float], ...] = ((4.2, 5.1), (1.8, 2.05), (1.4, 1.8))
"""Ranges of a car's (length, width, height), m."""

VAN_SIZE_RANGE: tuple[tuple[float, float], ...] = ((5.0, 6.5), (2.0, 2.3), (1.9, 2.8))
"""Ranges of a van's (length, width, height), m."""


def draw_fleet(
    routes: RouteTable,
    route_weights: np.ndarray,
    n: int,
    cfg: DriverConfig,
    rng: np.random.Generator,
) -> Fleet:
    """Draw ``n`` vehicles: route (by weight), size and personality-driven IDM parameters.

    Sizes: cars (4.2-5.1 m), vans (5.0-6.5 m) and trucks/buses (8-12 m, slower and with
    less acceleration) with per-scene shares from ``cfg``; trucks get straight routes only.
    """
    w = route_weights / route_weights.sum()
    route = rng.choice(routes.num_routes, size=n, p=w)
    mean = rng.uniform(*cfg.personality_mean)
    pers = np.clip(rng.normal(mean, cfg.personality_spread, n), -1.0, 1.0)
    kind = rng.random(n)
    van_share, truck_share = rng.uniform(*cfg.van_share), rng.uniform(*cfg.truck_share)
    straight = straight_routes(routes, cfg)
    truck = (kind < truck_share) & straight.any()
    van = ~truck & (kind < truck_share + van_share)
    if truck.any():
        ws = np.where(straight, w, 0.0)
        bent = truck & ~straight[route]
        route[bent] = rng.choice(routes.num_routes, size=int(bent.sum()), p=ws / ws.sum())
    length = np.where(van, rng.uniform(*VAN_SIZE_RANGE[0], n), rng.uniform(*CAR_SIZE_RANGE[0], n))
    width = np.where(van, rng.uniform(*VAN_SIZE_RANGE[1], n), rng.uniform(*CAR_SIZE_RANGE[1], n))
    height = np.where(van, rng.uniform(*VAN_SIZE_RANGE[2], n), rng.uniform(*CAR_SIZE_RANGE[2], n))
    length = np.where(truck, rng.uniform(8.0, 12.0, n), length)
    width = np.where(truck, rng.uniform(2.4, 2.55, n), width)
    height = np.where(truck, rng.uniform(3.0, 3.8, n), height)

    trait = functools.partial(_trait, pers=pers, rng=rng)

    heavy = np.where(truck, 0.6, 1.0)
    return Fleet(
        route=route.astype(np.int64),
        size=np.stack([length, width, height], axis=1),
        desired_speed=trait(cfg.desired_speed, 1.0) * np.where(truck, 0.85, 1.0),
        time_headway=trait(cfg.time_headway, -1.0),
        min_gap=trait(cfg.min_gap, -1.0),
        max_accel=trait(cfg.max_accel, 1.0) * heavy,
        comfort_decel=trait(cfg.comfort_decel, 1.0) * np.where(truck, 0.8, 1.0),
        reaction=trait(cfg.reaction, -1.0),
        gap_time=trait(cfg.gap_time, -1.0),
        personality=pers,
        cyclist=np.zeros(n, bool),
    )


def kerb_routes(net: RoadNetwork, routes: RouteTable) -> np.ndarray:
    """[R] bool, routes that start on a kerb lane (no right neighbour), the ones cyclists take."""
    kerb = np.asarray([not net.lane(int(src)).right for src in routes.source])
    return kerb if kerb.any() else np.ones(routes.num_routes, bool)


def add_cyclists(
    fleet: Fleet,
    route_weights: np.ndarray,
    kerb: np.ndarray,
    cfg: DriverConfig,
    rng: np.random.Generator,
) -> Fleet:
    """Turn a per-scene share (``cfg.cyclist_share``) of the fleet's slots into cyclists.

    Cyclists get kerb-lane routes (by weight), bicycle sizes (length 1.6-1.9 m, width
    0.6-0.8 m, height 1.6-1.8 m), desired speeds in ``cfg.cyclist_speed`` and gentler
    acceleration and braking; headway, gaps and reaction keep the rider's personality.
    All draws come from ``rng`` (a stream of their own, so that scenes without cyclists
    keep their other draws), and nothing is drawn when the share range is (0, 0).

    Args:
        fleet: the drawn fleet (N slots).
        route_weights: [R] relative probability of each route.
        kerb: [R] bool, routes cyclists may take (see ``kerb_routes``).
        cfg: driver configuration.
        rng: random generator of the cyclist stream.
    """
    if cfg.cyclist_share[1] <= 0.0:
        return fleet
    n = fleet.route.shape[0]
    share = rng.uniform(*cfg.cyclist_share)
    cyc = rng.random(n) < share
    k = int(cyc.sum())
    if k == 0:
        return fleet
    w = np.where(kerb, route_weights, 0.0)
    route = fleet.route.copy()
    route[cyc] = rng.choice(route_weights.size, size=k, p=w / w.sum())
    pers = fleet.personality[cyc]
    size = fleet.size.copy()
    size[cyc] = np.stack(
        [rng.uniform(1.6, 1.9, k), rng.uniform(0.6, 0.8, k), rng.uniform(1.6, 1.8, k)], axis=1
    )

    def put(name: str, value: np.ndarray) -> np.ndarray:
        out = getattr(fleet, name).copy()
        out[cyc] = value
        return out

    return dataclasses.replace(
        fleet,
        route=route,
        size=size,
        desired_speed=put("desired_speed", _trait(cfg.cyclist_speed, 1.0, pers, rng)),
        max_accel=put("max_accel", _trait(cfg.cyclist_accel, 1.0, pers, rng)),
        comfort_decel=put("comfort_decel", _trait(cfg.cyclist_decel, 1.0, pers, rng)),
        min_gap=put("min_gap", 0.6 * fleet.min_gap[cyc]),
        cyclist=cyc,
    )


def _idm(
    fleet: Fleet, v: np.ndarray, v0: np.ndarray, gap: np.ndarray, v_lead: np.ndarray
) -> np.ndarray:
    """IDM acceleration [N] for gaps [N] (inf = free road) to leaders moving at v_lead [N]."""
    ab = np.sqrt(fleet.max_accel * fleet.comfort_decel)
    s_star = fleet.min_gap + np.maximum(0.0, v * fleet.time_headway + v * (v - v_lead) / (2 * ab))
    inter = np.where(np.isfinite(gap), (s_star / np.maximum(gap, 0.1)) ** 2, 0.0)
    return fleet.max_accel * (1.0 - (v / np.maximum(v0, 0.1)) ** 4 - inter)


@dataclass(frozen=True)
class _Static:
    """Lookup tables derived once per network (see ``_prepare``)."""

    parent: np.ndarray  # [L+1] branch lane id of a diverging connector, 0 if none
    conn_arm: np.ndarray  # [L+1] approach of a connector lane, -1 otherwise
    signal_row: np.ndarray  # [R] row in the signal table of the route's stop line, -1 if none
    line_s: np.ndarray  # [R] route s of that stop line (inf if none)
    route_arm: np.ndarray  # [R] approach of the route (-1 if none)
    other_phase: np.ndarray  # [R, A] bool, arm A's signal phase is not the route's
    merge_virtual: np.ndarray  # [R, L+1] merge-frame lane offsets for yielding routes
    merge_prio: np.ndarray  # [R, L+1] merge-frame lane offsets of the yield lane for priority
    conflict_s: np.ndarray  # [R] route s of the merge conflict point for yielding routes
    yield_lane: np.ndarray  # [L+1] True for lanes that must yield
    j_kind: np.ndarray  # [R] junction control of the route's approach, -1 if none
    j_line: np.ndarray  # [R] route s of the junction stop line (inf if none)
    j_exit: np.ndarray  # [R] route s where the route's connector ends (inf if none)
    j_conn: np.ndarray  # [R] connector lane id of the route (0 if none)
    j_in: np.ndarray  # [R] inbound lane id ending at the stop line (0 if none)
    j_rank: np.ndarray  # [R] priority rank of the connector (0 highest)
    conflict: np.ndarray  # [L+1, L+1] bool, connector lanes that conflict


def _prepare(net: RoadNetwork, routes: RouteTable) -> _Static:
    n_l = len(net.lanes) + 1
    n_r = routes.num_routes
    parent = np.zeros(n_l, np.int64)
    conn_arm = np.full(n_l, -1, np.int64)
    for ln in net.lanes:
        if len(ln.entry) == 1 and len(net.lane(ln.entry[0]).exit) > 1:
            parent[ln.id] = ln.entry[0]
        if ln.is_connector:
            conn_arm[ln.id] = ln.approach
    signal_row = np.full(n_r, -1, np.int64)
    line_s = np.full(n_r, np.inf)
    route_arm = np.full(n_r, -1, np.int64)
    arm_phase = np.full(max(int(conn_arm.max()) + 1, 1), -1, np.int64)  # -1: no signal
    if net.signals is not None:
        for lid, ph in zip(net.signals.lane_ids, net.signals.phase):
            arm_phase[net.lane(lid).approach] = ph
        rows = {lid: k for k, lid in enumerate(net.signals.lane_ids)}
        for r, path in enumerate(routes.lanes):
            for lid in path:
                if lid in rows:
                    signal_row[r] = rows[lid]
                    line_s[r] = routes.lane_offset[r, lid] + routes.lane_length[lid]
                    route_arm[r] = net.lane(lid).approach
                    break
    merge_virtual = np.full((n_r, n_l), np.nan)
    merge_prio = np.full((n_r, n_l), np.nan)
    conflict_s = np.full(n_r, np.inf)
    yield_lane = np.zeros(n_l, bool)
    off, ll = routes.lane_offset, routes.lane_length
    for m in net.merges:
        p, y = m.priority_lane, m.yield_lane
        yield_lane[y] = True
        on_y = ~np.isnan(off[:, y])
        on_p = ~np.isnan(off[:, p])
        merge_virtual[on_y, p] = off[on_y, y] + ll[y] - ll[p]
        conflict_s[on_y] = off[on_y, y] + m.conflict_s
        merge_prio[on_p, y] = off[on_p, p] + ll[p] - ll[y]
    j_kind = np.full(n_r, -1, np.int64)
    j_line = np.full(n_r, np.inf)
    j_exit = np.full(n_r, np.inf)
    j_conn = np.zeros(n_r, np.int64)
    j_in = np.zeros(n_r, np.int64)
    j_rank = np.zeros(n_r, np.int64)
    conflict = np.zeros((n_l, n_l), bool)
    if net.junction is not None:
        conflict = connector_conflicts(net)
        kinds = dict(zip(net.junction.lane_ids, net.junction.kind))
        for r, path in enumerate(routes.lanes):
            for k, lid in enumerate(path[:-1]):
                if lid in kinds:
                    conn = path[k + 1]
                    j_kind[r] = kinds[lid]
                    j_line[r] = off[r, lid] + ll[lid]
                    j_exit[r] = off[r, conn] + ll[conn]
                    j_conn[r], j_in[r] = conn, lid
                    j_rank[r] = net.junction.rank[conn]
                    break
    route_phase = np.where(route_arm >= 0, arm_phase[np.maximum(route_arm, 0)], -1)
    return _Static(
        j_kind=j_kind,
        j_line=j_line,
        j_exit=j_exit,
        j_conn=j_conn,
        j_in=j_in,
        j_rank=j_rank,
        conflict=conflict,
        parent=parent,
        conn_arm=conn_arm,
        signal_row=signal_row,
        line_s=line_s,
        route_arm=route_arm,
        other_phase=arm_phase[None, :] != route_phase[:, None],
        merge_virtual=merge_virtual,
        merge_prio=merge_prio,
        conflict_s=conflict_s,
        yield_lane=yield_lane,
    )


def _junction_blocked(
    i: int,
    conn: np.ndarray,
    rank: np.ndarray,
    waiting: np.ndarray,
    ttl: np.ndarray,
    gap_time: np.ndarray,
    st: _Static,
    held_conns: list[int],
) -> bool:
    """Whether vehicle i may not take its junction connector now.

    Args:
        i: vehicle index.
        conn: [N] connector lane id of each vehicle's route (0 if none).
        rank: [N] priority rank of that connector (0 highest).
        waiting: [N] vehicles before their stop line without a grant.
        ttl: [N] time to reach the stop line (inf for non-waiting vehicles), s.
        gap_time: [N] accepted time gap of each driver, s.
        st: static lookup tables (conflict matrix).
        held_conns: connector lane ids held by granted vehicles.

    Returns:
        True when a conflicting connector is held, or a higher-ranked vehicle on a
        conflicting connector reaches its line within vehicle i's accepted gap.
    """
    c = conn[i]
    if st.conflict[c, held_conns].any():
        return True
    higher = waiting & (rank < rank[i]) & st.conflict[c, conn]
    return bool((higher & (ttl < gap_time[i])).any())


def _curve_accel(
    routes: RouteTable, r: np.ndarray, s: np.ndarray, v: np.ndarray, a_lat: float
) -> tuple[np.ndarray, np.ndarray]:
    """Bend speed cap at the current point [N] and the braking needed for bends ahead [N].

    Args:
        routes: route table.
        r: [N] route index per vehicle.
        s: [N] route arc length, m.
        v: [N] speed, m/s.
        a_lat: allowed lateral acceleration, m/s^2.
    """
    cap = np.sqrt(a_lat / np.maximum(routes.curvature[r], 1e-4))  # [N, P]
    d = routes.s[r] - s[:, None]
    ahead = (d > 0.0) & (d < 80.0)
    need = np.where(ahead, (cap**2 - v[:, None] ** 2) / (2.0 * np.maximum(d, 0.5)), np.inf)
    here = np.abs(d) <= 1.0
    cap_here = np.where(here, cap, np.inf).min(axis=1)
    return cap_here, need.min(axis=1)


class _Pedestrians:
    """State of the crossing pedestrians inside the driver loop (P pedestrians).

    Every step, ``interact`` lets waiting pedestrians decide to cross and returns the stop
    targets they impose on the vehicles; ``advance`` then records and moves them.
    """

    def __init__(
        self,
        plan: CrossingPlan,
        table: RouteCrossings | None,
        window: np.ndarray,
        num_steps: int,
    ) -> None:
        self.plan = plan
        self.num = plan.num
        self.table = table
        self.window = window  # [C, T] walk time left, s
        self.s = plan.s0.copy()
        self.v = plan.speed.copy()
        self.committed = np.zeros(self.num, bool)
        self.out_s = np.zeros((self.num, num_steps))
        self.out_v = np.zeros((self.num, num_steps))

    @classmethod
    def start(
        cls,
        net: RoadNetwork,
        routes: RouteTable,
        plan: CrossingPlan | None,
        times: np.ndarray,
        offset_s: float,
    ) -> _Pedestrians:
        plan = empty_plan() if plan is None else plan
        if plan.num == 0:
            return cls(plan, None, np.zeros((0, len(times))), len(times))
        window = walk_time_left(net, times, offset_s)
        return cls(plan, route_crossings(net, routes), window, len(times))

    def interact(
        self,
        t: int,
        r: np.ndarray,
        s: np.ndarray,
        v: np.ndarray,
        length: np.ndarray,
        alive: np.ndarray,
        fleet: Fleet,
    ) -> np.ndarray:
        """Pedestrians' crossing decisions at step t, and the vehicles' stop targets [N].

        A pedestrian within 3 m of its kerb point steps off when its walk window leaves
        time to clear the road and no vehicle whose route crosses the crosswalk is on it
        or too close to stop comfortably before it. A vehicle stops before the crosswalk
        (target: where its route enters it) while a committed pedestrian has not passed
        its path, or while a pedestrian is about to step off and the vehicle can stop
        comfortably (and no vehicle is on that crosswalk).

        Args:
            t: step index.
            r, s, v, length: [N] route, route s (m), speed (m/s) and length (m).
            alive: [N] vehicles on the map.
            fleet: the vehicles' attributes.
        """
        p, tab = self.plan, self.table
        c = p.crossing
        front, rear = s + 0.5 * length, s - 0.5 * length
        s_in, s_out = tab.s_in[r][:, c], tab.s_out[r][:, c]  # [N, P]
        crosses = alive[:, None] & np.isfinite(s_in)
        before = front[:, None] < s_in
        stop_d = (v**2 / (2.0 * fleet.comfort_decel))[:, None] + 1.0
        can_stop = before & (s_in - front[:, None] >= stop_d)
        on_it = crosses & ~before & (rear[:, None] < s_out)
        blocker = on_it | (crosses & before & ~can_stop)
        near = ~self.committed & (p.s_wait - self.s <= 3.0)
        need = (p.s_clear - self.s) / p.speed + p.speed / (2.0 * PED_ACCEL)
        allowed = self.window[c, t] >= need
        self.committed |= near & allowed & ~blocker.any(axis=0)
        # Progress across the crosswalk against the far end of each vehicle's path.
        ahead = np.where(p.direction > 0, tab.q_hi[r][:, c], -tab.q_lo[r][:, c])
        progress = p.direction * p.axis_coordinate(self.s)
        crossing = self.committed & (self.s < p.s_far)
        hard = crosses & before & crossing[None, :] & (progress < ahead + PATH_CLEARANCE)
        about = near & ~self.committed & allowed & ~on_it.any(axis=0)
        soft = crosses & can_stop & about[None, :]
        return np.where(hard | soft, s_in, np.inf).min(axis=1)

    def advance(self, t: int) -> None:
        """Record step t and walk one step: toward the walking speed when committed or
        still far from the kerb, else braking (at most ``PED_ACCEL``, constant) to wait at
        the kerb point."""
        p, v = self.plan, self.v
        self.out_s[:, t], self.out_v[:, t] = self.s, v
        to_kerb = np.maximum(p.s_wait - self.s, 0.0)
        brake = ~self.committed & (to_kerb - v * DT <= v**2 / (2.0 * PED_ACCEL))
        decel = np.minimum(v**2 / (2.0 * np.maximum(to_kerb, 1e-6)), 2.0 * PED_ACCEL)
        v_new = np.where(
            brake, np.maximum(v - decel * DT, 0.0), np.minimum(p.speed, v + PED_ACCEL * DT)
        )
        s_new = self.s + 0.5 * (v + v_new) * DT
        arrived = ~self.committed & (s_new >= p.s_wait)
        self.s = np.where(arrived, p.s_wait, s_new)
        self.v = np.where(arrived, 0.0, v_new)


LONG_VEHICLE_M = 7.5
"""Trucks and buses: vehicles longer than this (metres) keep to routes without sharp turns."""
SPAWN_CLEAR_M = 10.0
"""A vehicle enters a source lane only when the last one there is this far (plus its own
length) from the lane start, metres."""
SPAWN_SPEED_SHARE = 0.9
"""An entering vehicle's speed: this share of its desired speed (less behind a slow leader)."""
SPAWN_CLOSING_SPEED = 1.0
"""An entering vehicle is at most this much faster than the leader it enters behind, m/s."""
STOP_ZONE_M = 3.5
"""At a stop sign, a vehicle whose front is within this of the line has reached it, metres."""
STOPPED_SPEED = 0.05
"""Below this speed a vehicle at a stop sign has come to its full stop, m/s."""
CREEP_SPEED = 0.3
"""Below this speed a vehicle held at a stop sign is brought to exactly 0, m/s."""
DECIDE_MARGIN_M = 4.0
"""A priority-approach vehicle decides whether it may go this far (plus its comfortable
stopping distance) before the junction line, metres."""
GRANT_CLEAR_M = 1.0
"""A granted vehicle holds its connector until its rear is this far past the connector end."""
BEND_BRAKE = -0.3
"""Braking for a bend ahead applies when the bend needs a deceleration below this, m/s^2."""


@dataclass(frozen=True)
class DriveSetup:
    """What the driver runs: the road, the vehicle slots and how they start.

    Attributes:
        net: road network.
        routes: its routes.
        fleet: N vehicle slots.
        s0, v0: [N] initial route coordinate (m) and speed (m/s), used for the first
            ``num_initial`` slots only.
        num_initial: vehicles on the map at the first step.
        spawn_prob: [num source lanes] spawn probability per step of each source lane
            (sources in increasing lane id order).
        route_weights: [R] relative probability of each route among those of its source.
        num_steps: steps to simulate (warm-up included).
        signal_offset_s: signal plan phase offset, s.
        crossing: pedestrians who cross on the crosswalks (None: none), moved along their
            paths in the same loop (see ``crossings``).
    """

    net: RoadNetwork
    routes: RouteTable
    fleet: Fleet
    s0: np.ndarray
    v0: np.ndarray
    num_initial: int
    spawn_prob: np.ndarray
    route_weights: np.ndarray
    num_steps: int
    signal_offset_s: float
    crossing: CrossingPlan | None = None


class _Leaders(NamedTuple):
    """Who each vehicle follows this step (N vehicles)."""

    gap: np.ndarray  # [N] bumper gap to the leader, m (inf: free road)
    v_lead: np.ndarray  # [N] the leader's speed, m/s
    front: np.ndarray  # [N] route s of the vehicle's front, m
    committed: np.ndarray  # [N] past its merge decision (or accepted a gap)
    valid_pair: np.ndarray  # [N, N] both on the map, distinct
    v_off: np.ndarray  # [N, N] j's position in i's merge frame (nan: none), m


class _Traffic:
    """The vehicles' state inside the driver loop (N slots); one method per rule.

    Each step: ``locate``, ``spawn``, ``leaders``, the stop targets (``signal_stops``,
    ``merge_stops``, ``junction_stops``), ``acceleration``, ``record`` and ``move``.
    """

    def __init__(self, setup: DriveSetup, cfg: DriverConfig) -> None:
        net, routes, fleet, n0 = setup.net, setup.routes, setup.fleet, setup.num_initial
        self.setup, self.cfg, self.fleet, self.routes = setup, cfg, fleet, routes
        self.st = _prepare(net, routes)
        n = fleet.route.shape[0]
        self.n, self.idx = n, np.arange(n)
        self.size = fleet.size.copy()
        self.length = self.size[:, 0]  # a view: a truck slot turned into a car changes it
        self.straight = straight_routes(routes, cfg)
        self.kerb = kerb_routes(net, routes)
        self.sources = np.unique(routes.source)
        self.kerb_src = np.asarray([self.kerb[routes.source == src].any() for src in self.sources])
        first = self.idx < n0
        self.s = np.where(first, setup.s0, 0.0).astype(float)
        self.v = np.where(first, setup.v0, 0.0).astype(float)
        self.alive, self.spawned = first.copy(), first.copy()
        self.r = fleet.route.copy()
        self.next_slot = n0
        self.granted = np.zeros(n, bool)  # junction connector granted (or stop line passed)
        self.stop_t = np.full(n, -1, np.int64)  # step of the full stop at a stop sign
        self.latch = np.zeros(n, np.int8)  # yellow decision: 0 none, 1 stop, 2 go
        self.merge_ok = np.zeros(n, bool)
        self.out_s = np.zeros((n, setup.num_steps))
        self.out_v = np.zeros((n, setup.num_steps))
        self.out_alive = np.zeros((n, setup.num_steps), bool)

    def locate(self) -> None:
        """Lane and lane coordinate of every vehicle's centre, front and rear."""
        r, s, half = self.r, self.s, 0.5 * self.length
        self.lane_c, self.sig_c = self.routes.locate(r, s)
        self.lane_f, _ = self.routes.locate(r, s + half)
        self.lane_b, _ = self.routes.locate(r, s - half)

    def spawn(self, rng: np.random.Generator) -> None:
        """Each source lane lets the next slot enter with its spawn probability when clear.

        Cyclists only enter on kerb lanes: when the next slot is a cyclist and the source is
        not a kerb lane, the next motor vehicle slot enters instead.
        """
        fleet = self.fleet
        for k, src in enumerate(self.sources):
            if self.next_slot >= self.n or rng.random() >= self.setup.spawn_prob[k]:
                continue
            want = self.next_slot
            if fleet.cyclist[want] and not self.kerb_src[k]:
                motor = np.flatnonzero(~self.spawned[want:] & ~fleet.cyclist[want:])
                if motor.size == 0:
                    continue
                want += int(motor[0])
            self._enter(want, src, rng)

    def _enter(self, want: int, src: int, rng: np.random.Generator) -> None:
        """Slot ``want`` enters at the start of source lane ``src`` if there is room."""
        fleet, routes, length, s = self.fleet, self.routes, self.length, self.s
        on_src = self.alive & ((self.lane_b == src) | (self.lane_c == src))
        rear = np.where(on_src, s - 0.5 * length, np.inf)
        j = int(np.argmin(rear)) if on_src.any() else -1
        if j >= 0 and rear[j] < length[want] + SPAWN_CLEAR_M:
            return
        v_new = fleet.desired_speed[want] * SPAWN_SPEED_SHARE
        if j >= 0:
            room = rear[j] - 0.5 * length[want] - fleet.min_gap[want]
            v_new = min(
                v_new, self.v[j] + SPAWN_CLOSING_SPEED, max(room, 0.0) / fleet.time_headway[want]
            )
        choices = np.flatnonzero(routes.source == src)
        if fleet.cyclist[want]:
            choices = choices[self.kerb[choices]]
        if length[want] > LONG_VEHICLE_M:
            if self.straight[choices].any():
                choices = choices[self.straight[choices]]
            else:
                self.size[want] = CAR_SIZE
        w = self.setup.route_weights[choices]
        self.r[want] = choices[rng.choice(choices.size, p=w / w.sum())]
        s[want], self.v[want], self.alive[want] = 0.0, v_new, True
        lane_new, sig_new = routes.locate(self.r[[want]], s[[want]])
        self.lane_c[want], self.sig_c[want] = lane_new[0], sig_new[0]
        self.lane_f[want] = self.lane_b[want] = lane_new[0]
        self.spawned[want] = True
        while self.next_slot < self.n and self.spawned[self.next_slot]:
            self.next_slot += 1

    def leaders(self) -> _Leaders:
        """The nearest vehicle ahead on each route: on the route's own lanes, on a sibling
        connector it just left, or (in merge coordinates) on the lane it merges with."""
        st, routes, r, s, length = self.st, self.routes, self.r, self.s, self.length
        lane_c, sig_c, idx = self.lane_c, self.sig_c, self.idx
        pos = routes.lane_offset[r[:, None], lane_c[None, :]] + sig_c[None, :]  # [N, N]
        par = st.parent[lane_c]
        par_off = routes.lane_offset[r[:, None], par[None, :]] + routes.lane_length[par][None, :]
        par_ok = (par > 0) & (sig_c - 0.5 * length < self.cfg.diverge_clear)
        pos = np.where(np.isnan(pos) & par_ok[None, :], par_off + sig_c[None, :], pos)
        front = s + 0.5 * length
        committed = self.merge_ok | (front >= st.conflict_s[r])
        v_off = st.merge_virtual[r[:, None], lane_c[None, :]] + sig_c[None, :]
        # A merging vehicle follows priority-lane vehicles only once it has accepted a gap;
        # before that it is held by its conflict-point stop line (``merge_stops``).
        engaged = np.isfinite(st.conflict_s[r]) & committed
        pos = np.where(np.isnan(pos) & engaged[:, None], v_off, pos)
        p_off = st.merge_prio[r[:, None], lane_c[None, :]] + sig_c[None, :]
        pos = np.where(np.isnan(pos) & committed[None, :], p_off, pos)
        alive = self.alive
        valid_pair = alive[:, None] & alive[None, :] & (idx[:, None] != idx[None, :])
        ahead = valid_pair & (pos > s[:, None])
        gap_m = np.where(ahead, pos - s[:, None] - 0.5 * (length[:, None] + length[None, :]), _BIG)
        lead = np.argmin(gap_m, axis=1)
        gap = gap_m[idx, lead]
        gap = np.where(gap >= _BIG, np.inf, gap)
        return _Leaders(gap, self.v[lead], front, committed, valid_pair, v_off)

    def signal_stops(
        self, t: int, sig: np.ndarray, front: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(stop targets [N] (inf: none), held by the light [N]) at step t: red, yellow when
        the vehicle decided to stop, or vehicles of another phase still in the box."""
        st, r, v, cfg = self.st, self.r, self.v, self.cfg
        stop_at = np.full(self.n, np.inf)
        sig_hold = np.zeros(self.n, bool)
        if not sig.shape[0]:
            return stop_at, sig_hold
        has_line = st.signal_row[r] >= 0
        line = st.line_s[r]
        before = has_line & (front < line)
        state = np.where(has_line, sig[np.maximum(st.signal_row[r], 0), t], 0)
        need = v**2 / (2.0 * np.maximum(line - front, 0.01))
        latch = np.where(state == int(SignalState.GO), 0, self.latch).astype(np.int8)
        decide = before & (state == int(SignalState.CAUTION)) & (latch == 0)
        self.latch = np.where(decide, np.where(need <= cfg.yellow_decel, 1, 2), latch)
        red = state == int(SignalState.STOP)
        must = (red & ((self.latch != 2) | (need <= cfg.max_decel))) | (
            (state == int(SignalState.CAUTION)) & (self.latch == 1)
        )
        occupied = np.zeros(st.other_phase.shape[1], bool)  # per approach arm
        for lane in (self.lane_c, self.lane_f, self.lane_b):
            arm = st.conn_arm[lane]
            occupied[arm[self.alive & (arm >= 0)]] = True
        must = must | (occupied[None, :] & st.other_phase[r]).any(axis=1)
        sig_hold = before & must
        return np.where(sig_hold, line, stop_at), sig_hold

    def merge_stops(self, stop_at: np.ndarray, lead: _Leaders) -> np.ndarray:
        """Stop targets [N] with yielding vehicles held before their conflict point until
        they accept the gaps ahead of and behind them on the priority lane."""
        st, r, v, cfg, fleet = self.st, self.r, self.v, self.cfg, self.fleet
        yielding = self.alive & np.isfinite(st.conflict_s[r]) & ~lead.committed
        if not yielding.any():
            return stop_at
        length = self.length
        rel = np.where(
            lead.valid_pair & ~np.isnan(lead.v_off), lead.v_off - self.s[:, None], np.nan
        )
        half = 0.5 * (length[:, None] + length[None, :])
        fgap = np.where(rel >= 0, rel - half, np.inf).min(axis=1)
        rgap_m = np.where(rel < 0, -rel - half, np.inf)
        follower = np.argmin(rgap_m, axis=1)
        rgap = rgap_m[self.idx, follower]
        vf = v[follower]
        ok_front = fgap >= cfg.merge_front_gap + 1.0 * v
        ok_rear = rgap >= cfg.merge_rear_gap + 1.5 * vf + 2.0 * np.maximum(vf - v, 0.0)
        c_s = st.conflict_s[r]
        near = c_s - lead.front <= v**2 / (2.0 * fleet.comfort_decel) + 2.0
        self.merge_ok = self.merge_ok | (yielding & near & ok_front & ok_rear)
        wait = yielding & ~self.merge_ok
        return np.where(wait, np.minimum(stop_at, c_s), stop_at)

    def junction_stops(
        self, t: int, stop_at: np.ndarray, sig_hold: np.ndarray, front: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """(stop targets [N], creeping to a full stop [N]) at an unsignalised junction or a
        signalised one with permissive turns: connectors are granted in order of priority
        and arrival, never while a conflicting one is held."""
        st, r, fleet = self.st, self.r, self.fleet
        jr = self.alive & (st.j_kind[r] >= 0)
        j_line = st.j_line[r]
        self.granted |= jr & (front >= j_line)
        # At a signalised junction a vehicle its light holds neither keeps a grant nor
        # yields or is yielded to (the light orders the phases; the rules order a green).
        self.granted &= ~sig_hold
        waiting = jr & ~self.granted & ~sig_hold
        to_line = j_line - front
        is_stop = st.j_kind[r] == STOP
        zone = waiting & is_stop & (to_line < STOP_ZONE_M)
        self.stop_t = np.where(zone & (self.v < STOPPED_SPEED) & (self.stop_t < 0), t, self.stop_t)
        first = self._first_in_queue(waiting, front)
        dwell = (t - self.stop_t) * DT >= fleet.reaction
        ready = first & is_stop & (self.stop_t >= 0) & dwell & (to_line < STOP_ZONE_M)
        major = first & ~is_stop
        ready |= major & (to_line < self.v**2 / (2.0 * fleet.comfort_decel) + DECIDE_MARGIN_M)
        must = self._grant(t, ready, major, waiting, to_line, jr)
        hold = jr & ~self.granted & (is_stop | must)
        target = j_line + np.where(is_stop, fleet.min_gap - 1.0, 0.0)
        stop_at = np.where(hold, np.minimum(stop_at, target), stop_at)
        creep = hold & is_stop & (to_line < STOP_ZONE_M) & (self.v < CREEP_SPEED)
        return stop_at, creep

    def _first_in_queue(self, waiting: np.ndarray, front: np.ndarray) -> np.ndarray:
        """[N] bool, the waiting vehicle nearest the line (largest ``front`` [N]) on each
        inbound lane."""
        first = np.zeros(self.n, bool)
        wi = np.flatnonzero(waiting)
        if wi.size:
            order = wi[np.lexsort((-front[wi], self.st.j_in[self.r[wi]]))]
            lanes_o = self.st.j_in[self.r[order]]
            first[order[np.concatenate([[True], lanes_o[1:] != lanes_o[:-1]])]] = True
        return first

    def _grant(
        self,
        t: int,
        ready: np.ndarray,
        major: np.ndarray,
        waiting: np.ndarray,
        to_line: np.ndarray,
        jr: np.ndarray,
    ) -> np.ndarray:
        """Grant connectors to the ready vehicles (priority rank, then arrival); returns the
        priority-approach vehicles that must brake for the line because they are blocked."""
        st, r, v = self.st, self.r, self.v
        held = jr & self.granted & (self.s - 0.5 * self.length < st.j_exit[r] + GRANT_CLEAR_M)
        rank, conn = st.j_rank[r], st.j_conn[r]
        ttl = np.where(waiting, np.maximum(to_line, 0.0) / np.maximum(v, 0.5), np.inf)
        held_conns = list(conn[held])
        args = (conn, rank, waiting, ttl, self.fleet.gap_time, st)
        cand = np.flatnonzero(ready)
        arrival = np.where(self.stop_t >= 0, self.stop_t, t)
        for i in cand[np.lexsort((cand, arrival[cand], rank[cand]))]:
            if not _junction_blocked(i, *args, held_conns):
                self.granted[i] = True
                held_conns.append(conn[i])
        # Priority approaches flow freely; they only brake for the line when blocked.
        must = np.zeros(self.n, bool)
        for i in np.flatnonzero(major & ~self.granted):
            must[i] = _junction_blocked(i, *args, held_conns)
        return must

    def acceleration(self, lead: _Leaders, stop_at: np.ndarray, creep: np.ndarray) -> np.ndarray:
        """[N] m/s^2: the lowest IDM acceleration of free road (capped in bends), the
        leader and the stop target, bend braking, clipped to the limits."""
        fleet, v, cfg = self.fleet, self.v, self.cfg
        cap_here, a_curve = _curve_accel(self.routes, self.r, self.s, v, cfg.lateral_accel)
        v_des = np.minimum(fleet.desired_speed, cap_here)
        acc = _idm(fleet, v, v_des, lead.gap, lead.v_lead)
        line_gap = np.where(np.isfinite(stop_at), stop_at - lead.front, np.inf)
        acc = np.minimum(acc, _idm(fleet, v, v_des, line_gap, np.zeros(self.n)))
        acc = np.where(a_curve < BEND_BRAKE, np.minimum(acc, a_curve), acc)
        acc = np.clip(acc, -cfg.max_decel, fleet.max_accel)
        # Come to a full stop at a stop sign (v reaches exactly 0).
        return np.where(creep, np.minimum(acc, -v / DT), acc)

    def record(self, t: int) -> None:
        """Store step t's route s, speed and presence."""
        self.out_s[:, t], self.out_v[:, t], self.out_alive[:, t] = self.s, self.v, self.alive

    def move(self, acc: np.ndarray) -> None:
        """One step of ``DT`` at acceleration ``acc`` (speeds stay >= 0); vehicles past the
        end of their route leave the map."""
        alive, v = self.alive, self.v
        v_new = np.maximum(v + acc * DT, 0.0)
        self.s = np.where(alive, self.s + 0.5 * (v + v_new) * DT, self.s)
        self.v = np.where(alive, v_new, v)
        gone = alive & (self.s >= self.routes.length[self.r])
        self.alive = alive & ~gone


def simulate(setup: DriveSetup, cfg: DriverConfig, rng: np.random.Generator) -> DriveLog:
    """Run the driver for ``setup.num_steps`` steps of ``DT`` starting at ``-cfg.warmup_s``.

    Slots ``[0, num_initial)`` start on the map at ``s0``/``v0``; the remaining slots are
    spawned in order at the start of a source lane when it is clear (each step with
    probability ``spawn_prob`` per source lane) and get a route from that lane by weight.

    Args:
        setup: the road, the slots and their start.
        cfg: driver configuration.
        rng: random generator (spawn times and routes).

    Returns:
        The ``DriveLog`` of all N slots (and the crossing pedestrians) over ``num_steps``
        steps.
    """
    net, routes, num_steps = setup.net, setup.routes, setup.num_steps
    traffic = _Traffic(setup, cfg)
    times = -cfg.warmup_s + DT * np.arange(num_steps)
    sig = (
        signal_states(net.signals, times, setup.signal_offset_s)
        if net.signals is not None
        else np.zeros((0, num_steps), np.int8)
    )
    peds = _Pedestrians.start(net, routes, setup.crossing, times, setup.signal_offset_s)
    for t in range(num_steps):
        traffic.locate()
        traffic.spawn(rng)
        lead = traffic.leaders()
        stop_at, sig_hold = traffic.signal_stops(t, sig, lead.front)
        stop_at = traffic.merge_stops(stop_at, lead)
        creep = np.zeros(traffic.n, bool)
        if net.junction is not None:
            stop_at, creep = traffic.junction_stops(t, stop_at, sig_hold, lead.front)
        if peds.num:
            t_v = (traffic.r, traffic.s, traffic.v, traffic.length, traffic.alive)
            stop_at = np.minimum(stop_at, peds.interact(t, *t_v, traffic.fleet))
        acc = traffic.acceleration(lead, stop_at, creep)
        traffic.record(t)
        peds.advance(t)
        traffic.move(acc)
    return DriveLog(
        fleet=dataclasses.replace(setup.fleet, route=traffic.r, size=traffic.size),
        s=traffic.out_s,
        speed=traffic.out_v,
        alive=traffic.out_alive,
        crossing=peds.plan,
        ped_s=peds.out_s,
        ped_speed=peds.out_v,
    )
