"""Public API of the generator: seeded WOMD-like ``Scenario`` objects from the layouts.

A scene holds the vehicles of the driver (``driver``: cars, vans, trucks and buses, and on
urban layouts a per-scene share of cyclists), pedestrians on the sidewalks (walking along
them with a fluctuating speed, or standing) and, on the junction layouts, pedestrians
crossing on the crosswalks (``crossings``) whom the vehicles yield to. How they move
(speeds, acceleration, headways, walking) is a ``behaviour.Behaviour``, by default the one
calibrated against real scenes (``behaviour.CALIBRATED``); with a ``recording.Recording``
the log also holds parked vehicles and tracker jitter. Cyclists and crossing
pedestrians are drawn from a random stream of their own, so the freeway ``merge`` scenes,
which have neither, were the same as before they were added."""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

from tbsim_env.core.constants import CURRENT_INDEX, DT, NUM_STEPS, ObjectType
from tbsim_env.data.generator.behaviour import CALIBRATED, Behaviour
from tbsim_env.data.generator.crossings import CrossingPlan, plan_crossings
from tbsim_env.data.generator.driver import (
    DriveLog,
    DriverConfig,
    DriveSetup,
    add_cyclists,
    draw_fleet,
    kerb_routes,
    simulate,
)
from tbsim_env.data.generator.recording import Recording, jitter, parked_vehicles
from tbsim_env.data.generator.roads import (
    LAYOUT_BUILDERS,
    STOP,
    RoadNetwork,
    signal_states,
    to_road_map,
)
from tbsim_env.data.generator.routes import RouteTable, build_routes
from tbsim_env.data.scenario import Scenario, Tracks, TrafficSignals, wrap_angle_np

LAYOUTS: tuple[str, ...] = tuple(LAYOUT_BUILDERS)
"""Names of the available layouts."""

_DEFAULT_SCENES: tuple[tuple[str, int], ...] = (
    ("intersection", 0),
    ("merge", 0),
    ("stop_intersection", 0),
    ("t_junction", 0),
    ("intersection", 1),
    ("merge", 1),
    ("stop_intersection", 1),
    ("t_junction", 1),
)


@dataclass(frozen=True)
class LayoutTraffic:
    """Traffic settings of one layout.

    Attributes:
        driver: driver parameter ranges.
        initial_vehicles: range (inclusive) of vehicles placed at the start of the warm-up.
        pedestrians: default number of pedestrians walking along the sidewalks.
        crossing_pedestrians: range (inclusive) of the number of pedestrians who cross on
            the crosswalks (at most one per crosswalk).
        stop_source_boost: traffic entering through stop-controlled lanes is this many times
            the other sources' (initial placement and inflow), so minor roads see action.
    """

    driver: DriverConfig
    initial_vehicles: tuple[int, int]
    pedestrians: int
    crossing_pedestrians: tuple[int, int] = (0, 0)
    stop_source_boost: float = 1.0


CYCLISTS: tuple[float, float] = (0.03, 0.1)
"""Range of the per-scene share of cyclists among the vehicle slots of the urban layouts."""

TRAFFIC = {
    "intersection": LayoutTraffic(
        driver=DriverConfig(desired_speed=(9.0, 14.0), inflow=0.07, cyclist_share=CYCLISTS),
        initial_vehicles=(18, 24),
        pedestrians=4,
        crossing_pedestrians=(1, 3),
    ),
    "merge": LayoutTraffic(
        driver=DriverConfig(desired_speed=(15.0, 20.0), inflow=0.25, warmup_s=6.0),
        initial_vehicles=(14, 18),
        pedestrians=0,
    ),
    "stop_intersection": LayoutTraffic(
        driver=DriverConfig(desired_speed=(8.0, 13.0), inflow=0.05, cyclist_share=CYCLISTS),
        initial_vehicles=(16, 22),
        pedestrians=4,
        crossing_pedestrians=(1, 3),
    ),
    "t_junction": LayoutTraffic(
        driver=DriverConfig(desired_speed=(9.0, 14.0), inflow=0.06, cyclist_share=CYCLISTS),
        initial_vehicles=(14, 20),
        pedestrians=3,
        crossing_pedestrians=(0, 2),
        stop_source_boost=2.5,
    ),
}
TRAFFIC["permissive_intersection"] = TRAFFIC["intersection"]  # same roads, other signals


FRAME_OFFSET_RANGE_M: tuple[float, float] = (1000.0, 5000.0)
"""Range of |x| and |y| of the generated scene's world origin (metres). The layouts are built
around (0, 0), but a track's invalid steps hold the placeholder (0, 0, 0) as in WOMD, and
anything that reads the log blindly (log replay in WOSAC scoring) would park departed agents on
the junction. Real WOMD scenes lie far from (0, 0), so the generated ones are moved there too."""


MAP_MARGIN_M: float = 60.0
"""The roads run this far past the observed area ([-E, E]^2 with E the layout's default extent);
objects are valid (observed) only inside it. As in WOMD, where the map reaches beyond the
tracks, a simulated agent that is faster than its log or takes another exit still finds road
ahead instead of a map end: with the roads ending at the border, policies learn to stop there
and the followers run into them."""


def _rng(layout: str, seed: int) -> np.random.Generator:
    return np.random.default_rng([int(seed), zlib.crc32(layout.encode())])


def _vru_rng(layout: str, seed: int) -> np.random.Generator:
    """Stream of the vulnerable road users added after the first release (cyclists, crossing
    pedestrians): its own, so that scenes without them keep every other draw."""
    return np.random.default_rng([int(seed), zlib.crc32(layout.encode()), 2])


def _ped_rng(layout: str, seed: int) -> np.random.Generator:
    """Stream of the sidewalk pedestrians' calibrated behaviour (standing, speed fluctuation,
    sway): its own, so that without it every other draw is as before."""
    return np.random.default_rng([int(seed), zlib.crc32(layout.encode()), 3])


def _rec_rng(layout: str, seed: int) -> np.random.Generator:
    """Stream of the recording (parked vehicles, tracker jitter): its own, so that the driven
    traffic is the same with or without it."""
    return np.random.default_rng([int(seed), zlib.crc32(layout.encode()), 4])


def frame_offset(layout: str, seed: int) -> tuple[float, float]:
    """Seeded world offset of a scene (its own stream, so the traffic draws are unchanged)."""
    rng = np.random.default_rng([int(seed), zlib.crc32(layout.encode()), 1])
    mag = rng.uniform(*FRAME_OFFSET_RANGE_M, size=2)
    sign = rng.choice([-1.0, 1.0], size=2)
    return float(mag[0] * sign[0]), float(mag[1] * sign[1])


def _route_weights(routes: RouteTable) -> np.ndarray:
    """[R] weights: every source lane equally likely, its routes equally likely."""
    counts = {int(src): int((routes.source == src).sum()) for src in np.unique(routes.source)}
    n_src = len(counts)
    return np.asarray([1.0 / (n_src * counts[int(src)]) for src in routes.source])


def _place_initial(
    net: RoadNetwork,
    routes: RouteTable,
    route: np.ndarray,
    n: int,
    rng: np.random.Generator,
    length: np.ndarray | None = None,
) -> np.ndarray:
    """Route coordinates [n] for the first n slots, spread out (>= 14 m between centres of
    cars, 10 m plus half of both lengths for longer vehicles).

    Vehicles are not placed inside the intersection box nor past a merge point, nor within
    35 m of an unsignalised junction's stop line (so that they can stop there). A slot that
    finds no free spot after a few tries is put at the start of its route (where the driver
    holds it back behind the others, as the warm-up sorts it out).

    Args:
        length: [>= n] vehicle lengths in metres (None: all 4.6 m).
    """
    conn = np.zeros(len(net.lanes) + 1, bool)
    for ln in net.lanes:
        conn[ln.id] = ln.is_connector or bool(ln.entry and len(ln.entry) > 1)
    guard = np.zeros(len(net.lanes) + 1)
    if net.junction is not None:
        guard[list(net.junction.lane_ids)] = 35.0
    length = np.full(n, 4.6) if length is None else np.asarray(length, float)
    placed_xy = np.zeros((0, 2))
    placed_len = np.zeros(0)
    s_out = np.zeros(n)
    for k in range(n):
        r = route[k : k + 1]
        for _ in range(30):
            s = rng.uniform(5.0, routes.length[r] - 10.0)
            lane, lane_s = routes.locate(r, s)
            xy, _ = routes.interpolate(r, s)
            if conn[lane[0]]:
                continue
            if lane_s[0] + 0.5 * length[k] > routes.lane_length[lane[0]] - guard[lane[0]]:
                continue
            need = np.maximum(14.0, 10.0 + 0.5 * (placed_len + length[k]))
            if placed_xy.size and np.any(np.linalg.norm(placed_xy - xy, axis=1) < need):
                continue
            s_out[k] = s[0]
            placed_xy = np.concatenate([placed_xy, xy])
            placed_len = np.append(placed_len, length[k])
            break
        else:
            s_out[k] = -1.0
    return s_out


def _vehicle_tracks(
    routes: RouteTable, log: DriveLog, window: slice
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Vehicles seen in the logged window: (slot [V], xy [V,T,2], heading, velocity, valid)."""
    alive = log.alive[:, window]
    keep = np.flatnonzero(alive.any(axis=1))
    s, speed, valid = log.s[keep, window], log.speed[keep, window], alive[keep]
    route = np.broadcast_to(log.fleet.route[keep, None], s.shape)
    xy, heading = routes.interpolate(route, s)
    heading = wrap_angle_np(heading)
    vel = speed[..., None] * np.stack([np.cos(heading), np.sin(heading)], axis=-1)
    return keep, xy, heading, vel, valid


def _clip_to_box(a: np.ndarray, b: np.ndarray, half: float) -> tuple[np.ndarray, np.ndarray]:
    """The part of segment a-b [2] inside [-half, half]^2 (a, b if none is)."""
    import shapely

    part = shapely.clip_by_rect(shapely.LineString([a, b]), -half, -half, half, half)
    if part.is_empty:
        return a, b
    xy = np.asarray(part.coords)
    return xy[0], xy[-1]


STANDING_OFFSET_M: float = 2.5
"""Standing pedestrians stand this far beyond their sidewalk's walking line, away from the road
(walkers keep 0.6 m to their right of it and sway at most ``MAX_SWAY_M``), m."""

MAX_SWAY_M: float = 0.4
"""Largest sideways offset of a swaying walker from its lane of the sidewalk, m."""

WALK_SPEED_LIMITS: tuple[float, float] = (0.3, 2.5)
"""A walker's fluctuating speed stays in this range, m/s."""


def _ou(rng: np.random.Generator, n: int, sigma: float, tau: float) -> np.ndarray:
    """[n] stationary Ornstein-Uhlenbeck process on the DT grid (std ``sigma``, time constant
    ``tau`` in s), 0 when sigma is 0 (nothing drawn then)."""
    if sigma <= 0.0:
        return np.zeros(n)
    a = float(np.exp(-DT / tau))
    eps = rng.standard_normal(n)
    out = np.empty(n)
    out[0] = sigma * eps[0]
    for k in range(1, n):
        out[k] = a * out[k - 1] + np.sqrt(1.0 - a * a) * sigma * eps[k]
    return out


@dataclass(frozen=True)
class _Walk:
    """The observed part of one sidewalk walking line.

    Attributes:
        a: [2] start point, m; d: [2] unit direction from a; total: length, m.
        outward: [2] unit normal pointing away from the road.
    """

    a: np.ndarray
    d: np.ndarray
    total: float
    outward: np.ndarray

    @classmethod
    def of(cls, line: np.ndarray, observed: float) -> _Walk:
        a, b = _clip_to_box(line[0], line[-1], observed)
        total = float(np.linalg.norm(b - a))
        d = (b - a) / total
        normal = np.array([-d[1], d[0]])
        # The layouts' roads run through the origin: away from it is away from the road.
        outward = normal if normal @ (0.5 * (a + b)) >= 0.0 else -normal
        return cls(a=a, d=d, total=total, outward=outward)


def _walker(
    walk: _Walk, start: float, sign: float, speed: float, rng: np.random.Generator, b: Behaviour
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """One sidewalk walker keeping 0.6 m to its right of the line: (xy [T, 2], heading [T],
    velocity [T, 2], along [T] m from the line's start). With ``b.walkers_wander`` its speed
    fluctuates and it sways sideways (``_ou`` draws from rng), heading along its motion."""
    t = DT * np.arange(NUM_STEPS)
    direction = walk.d * sign
    side = np.array([-direction[1], direction[0]]) * -0.6  # keep to the right
    if not b.walkers_wander:
        along = start + sign * speed * t
        xy = walk.a + along[:, None] * walk.d + side
        heading = np.full(NUM_STEPS, np.arctan2(direction[1], direction[0]))
        return xy, heading, np.broadcast_to(speed * direction, (NUM_STEPS, 2)), along
    tau = b.ped_wander_tau
    v = np.clip(speed + _ou(rng, NUM_STEPS, b.ped_speed_sigma, tau), *WALK_SPEED_LIMITS)
    sway = np.clip(_ou(rng, NUM_STEPS, b.ped_sway_sigma, tau), -MAX_SWAY_M, MAX_SWAY_M)
    along = start + sign * np.concatenate([[0.0], np.cumsum(v[:-1]) * DT])
    xy = walk.a + along[:, None] * walk.d + side + sway[:, None] * walk.outward
    vel = np.gradient(xy, DT, axis=0)
    return xy, np.arctan2(vel[:, 1], vel[:, 0]), vel, along


def _pedestrians(
    net: RoadNetwork,
    n: int,
    rng: np.random.Generator,
    observed: float,
    behaviour: Behaviour,
    ped_rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Pedestrians on the observed part ([-observed, observed]^2) of the sidewalks: walkers
    (``_walker``) and, a ``behaviour.ped_standing_share`` of them, pedestrians standing still
    ``STANDING_OFFSET_M`` beyond the walking line facing a random way. Returns (size [P, 3],
    xy [P, T, 2], heading [P, T], velocity [P, T, 2], valid [P, T]) over the logged steps;
    walkers become invalid past the line's ends.

    Draws of the layout stream ``rng`` are the same whatever the behaviour; standing and
    wandering draw from ``ped_rng`` only.
    """
    size = np.zeros((n, 3))
    xy = np.zeros((n, NUM_STEPS, 2))
    heading = np.zeros((n, NUM_STEPS))
    vel = np.zeros((n, NUM_STEPS, 2))
    valid = np.zeros((n, NUM_STEPS), bool)
    if n == 0 or not net.sidewalks:
        return size[:0], xy[:0], heading[:0], vel[:0], valid[:0]
    for k in range(n):
        walk = _Walk.of(net.sidewalks[rng.integers(len(net.sidewalks))], observed)
        sign = 1.0 if rng.random() < 0.5 else -1.0
        # Slot along the walk so that pedestrians on the same walk do not overlap.
        start = (k + rng.uniform(0.1, 0.9)) / n * walk.total
        speed = rng.uniform(*behaviour.ped_speed)
        if behaviour.ped_standing_share > 0.0 and ped_rng.random() < behaviour.ped_standing_share:
            spot = walk.a + start * walk.d + STANDING_OFFSET_M * walk.outward
            xy[k] = spot
            heading[k] = ped_rng.uniform(-np.pi, np.pi)
            valid[k] = True
        else:
            xy[k], heading[k], vel[k], along = _walker(walk, start, sign, speed, ped_rng, behaviour)
            valid[k] = (along >= 0.0) & (along <= walk.total)
        size[k] = [rng.uniform(0.6, 0.9), rng.uniform(0.6, 0.9), rng.uniform(1.6, 1.9)]
    heading = wrap_angle_np(heading)
    return size, xy, heading, vel, valid


@dataclass(frozen=True)
class _Road:
    """A layout's road network and what its traffic draws from."""

    net: RoadNetwork
    routes: RouteTable
    weights: np.ndarray  # [R] route weights (stop-sign sources boosted)
    boost: np.ndarray  # [sources] spawn boost per source lane
    observed: float  # m, half extent of the observed area


def _road(layout: str, traffic: LayoutTraffic) -> _Road:
    """The layout's network (grown by ``MAP_MARGIN_M`` beyond the observed area), its routes
    and their weights."""
    observed = LAYOUT_BUILDERS[layout]().half_extent
    net = LAYOUT_BUILDERS[layout](observed + MAP_MARGIN_M)
    routes = build_routes(net)
    weights = _route_weights(routes)
    sources = np.unique(routes.source)
    boost = np.ones(sources.size)
    if net.junction is not None:
        stops = [lid for lid, k in zip(net.junction.lane_ids, net.junction.kind) if k == STOP]
        boost = np.where(np.isin(sources, stops), traffic.stop_source_boost, 1.0)
        weights = weights * boost[np.searchsorted(sources, routes.source)]
    return _Road(net, routes, weights, boost, observed)


def _drive(
    road: _Road, n_init: int, cfg: DriverConfig, rngs: tuple[np.random.Generator, ...], crossing_fn
) -> tuple[DriveLog, float, CrossingPlan]:
    """(the driven log over the warm-up and the episode, the signal offset s, the crossing
    plan): the fleet drawn, placed and simulated (``rngs`` = traffic, vulnerable users)."""
    rng, vru = rngs
    net, routes, weights = road.net, road.routes, road.weights
    total_steps = int(round(cfg.warmup_s / DT)) + NUM_STEPS
    n_src = int(np.unique(routes.source).size)
    capacity = n_init + int(3 * cfg.inflow * n_src * total_steps * DT) + 4
    fleet = draw_fleet(routes, weights, capacity, cfg, rng)
    fleet = add_cyclists(fleet, weights, kerb_routes(net, routes), cfg, vru)
    s0 = _place_initial(net, routes, fleet.route, n_init, rng, fleet.size[:, 0])
    v0 = fleet.desired_speed * rng.uniform(0.6, 0.9, capacity)
    placed = np.concatenate([s0 >= 0.0, np.zeros(capacity - n_init, bool)])
    # Slots that found no spot are moved to the end and spawned later instead.
    order = np.concatenate([np.flatnonzero(placed), np.flatnonzero(~placed)])
    fleet = type(fleet)(**{k: getattr(fleet, k)[order] for k in fleet.__dataclass_fields__})
    s0 = np.concatenate([s0, np.zeros(capacity - n_init)])[order]
    offset_s = float(rng.uniform(0.0, net.signals.cycle_s)) if net.signals else 0.0
    crossing = crossing_fn(offset_s)
    setup = DriveSetup(
        net=net,
        routes=routes,
        fleet=fleet,
        s0=s0,
        v0=v0[order],
        num_initial=int(placed.sum()),
        spawn_prob=road.boost * cfg.inflow * DT,
        route_weights=weights,
        num_steps=total_steps,
        signal_offset_s=offset_s,
        crossing=crossing,
    )
    log = simulate(setup, cfg, rng)
    return log, offset_s, crossing


def _check_request(
    layout: str, num_vehicles: int | None, num_pedestrians: int | None, num_crossing: int | None
) -> None:
    """Raise ``ValueError`` for an unknown layout or negative counts (``generate_scenario``)."""
    if layout not in LAYOUT_BUILDERS:
        raise ValueError(f"unknown layout {layout!r}; valid layouts are {', '.join(LAYOUTS)}")
    if (
        (num_vehicles is not None and num_vehicles < 1)
        or (num_pedestrians is not None and num_pedestrians < 0)
        or (num_crossing is not None and num_crossing < 0)
    ):
        raise ValueError("num_vehicles must be >= 1, num_pedestrians and num_crossing >= 0")


def generate_scenario(
    layout: str = "intersection",
    seed: int = 0,
    *,
    num_vehicles: int | None = None,
    num_pedestrians: int | None = None,
    num_crossing: int | None = None,
    behaviour: Behaviour = CALIBRATED,
    recording: Recording | None = None,
) -> Scenario:
    """Generate one WOMD-like scenario (91 steps at 10 Hz, current index 10).

    Deterministic: the same (layout, seed, counts) gives identical arrays.

    Args:
        layout: one of ``LAYOUTS``.
        seed: random seed (traffic, driver parameters, signal phase offset, track ids,
            cyclists and crossing pedestrians).
        num_vehicles: vehicles placed on the map at the start of the warm-up (more enter
            during the run through the map borders); None draws a layout default.
        num_pedestrians: pedestrians on the sidewalks (none on layouts without sidewalks, e.g.
            the merge); None uses the layout default.
        num_crossing: pedestrians who cross on the crosswalks (at most one per crosswalk,
            none on layouts without); None draws a layout default.
        behaviour: how the agents move (speeds, acceleration, headways, walking); the
            calibrated one by default, ``behaviour.UNCALIBRATED`` gives the scenes of the
            generator before its calibration.
        recording: parked vehicles and tracker jitter as real logs have them
            (``recording.RECORDED``, fitted to the real training scenes); None (default) for
            exact tracks and no parked vehicles. The driven traffic is the same either way.

    Returns:
        A validated ``Scenario``: vehicles and cyclists, then sidewalk and crossing
        pedestrians, the SDC (a vehicle, never a cyclist) last; tracks_to_predict are
        vehicles only.

    Raises:
        ValueError: unknown layout or negative counts.
    """
    _check_request(layout, num_vehicles, num_pedestrians, num_crossing)
    traffic = TRAFFIC[layout]
    cfg = behaviour.driver(traffic.driver)
    rng = _rng(layout, seed)
    road = _road(layout, traffic)
    lo, hi = traffic.initial_vehicles
    n_init = int(rng.integers(lo, hi + 1)) if num_vehicles is None else int(num_vehicles)
    n_init = int(round(n_init * road.net.half_extent / road.observed))  # same density
    vru = _vru_rng(layout, seed)

    def crossing_fn(offset_s: float) -> CrossingPlan:
        lo, hi = traffic.crossing_pedestrians
        n = num_crossing
        if n is None:
            n = int(vru.integers(lo, hi + 1)) if hi > 0 else 0
        return plan_crossings(road.net, n, vru, cfg.warmup_s, offset_s, behaviour.crossing_speed)

    log, offset_s, crossing = _drive(road, n_init, cfg, (rng, vru), crossing_fn)
    n_ped = traffic.pedestrians if num_pedestrians is None else num_pedestrians
    walkers = _pedestrians(road.net, n_ped, rng, road.observed, behaviour, _ped_rng(layout, seed))
    tracks = _tracks(road, log, crossing, walkers, rng, cfg)
    predict = _tracks_to_predict(tracks, tracks.object_type.astype(np.int64), tracks.valid)
    if recording is not None:
        tracks = _record(tracks, road, recording, _rec_rng(layout, seed))
    return _scenario(layout, seed, road, tracks, predict, offset_s)


def _scenario(
    layout: str, seed: int, road: _Road, tracks: Tracks, predict: np.ndarray, offset_s: float
) -> Scenario:
    """The validated ``Scenario`` of a generated log (SDC last), moved by ``frame_offset``."""
    return (
        Scenario(
            scenario_id=f"gen-{layout}-{seed:04d}",
            timestamps=DT * np.arange(NUM_STEPS, dtype=np.float64),
            current_index=CURRENT_INDEX,
            tracks=tracks,
            road_map=to_road_map(road.net),
            signals=_signals(road.net, offset_s),
            sdc_index=tracks.num_tracks - 1,
            tracks_to_predict=predict,
            predict_difficulty=np.ones(predict.size, np.int8),
            objects_of_interest=np.zeros(0, np.int64),
            source=f"<generated {layout} seed {seed}>",
        )
        .transformed(shift=frame_offset(layout, seed))
        .validate()
    )


def _tracks(
    road: _Road,
    log: DriveLog,
    crossing: CrossingPlan,
    walkers: tuple[np.ndarray, ...],
    rng: np.random.Generator,
    cfg: DriverConfig,
) -> Tracks:
    """The ``Tracks`` of the episode window: vehicles and cyclists, then
    sidewalk and crossing pedestrians, objects never in the observed area dropped, the SDC
    last; track ids drawn from ``rng``."""
    warm = int(round(cfg.warmup_s / DT))
    window = slice(warm, warm + NUM_STEPS)
    slot, vxy, vhead, vvel, vvalid = _vehicle_tracks(road.routes, log, window)
    psize, pxy, phead, pvel, pvalid = walkers
    cxy, chead, cvel = crossing.poses(log.ped_s[:, window], log.ped_speed[:, window])
    n_ped = len(psize) + crossing.num
    psize = np.concatenate([psize, crossing.size])
    pxy, phead = np.concatenate([pxy, cxy]), np.concatenate([phead, wrap_angle_np(chead)])
    pvel = np.concatenate([pvel, cvel])
    pvalid = np.concatenate([pvalid, np.ones(chead.shape, bool)])
    n_veh = slot.size
    vsize = np.broadcast_to(log.fleet.size[slot, None, :], (n_veh, NUM_STEPS, 3))
    size = np.concatenate([vsize, np.broadcast_to(psize[:, None, :], (n_ped, NUM_STEPS, 3))])
    xy = np.concatenate([vxy, pxy])
    heading = np.concatenate([vhead, phead])
    vel = np.concatenate([vvel, pvel])
    valid = np.concatenate([vvalid, pvalid]) & (np.abs(xy) <= road.observed).all(axis=-1)
    vtype = np.where(log.fleet.cyclist[slot], int(ObjectType.CYCLIST), int(ObjectType.VEHICLE))
    otype = np.concatenate([vtype, np.full(n_ped, int(ObjectType.PEDESTRIAN))])
    seen = valid.any(axis=1)  # objects that never enter the observed area are not tracks
    n_veh, n_ped = int(seen[:n_veh].sum()), int(seen[n_veh:].sum())
    size, xy, heading, vel, valid, otype = (a[seen] for a in (size, xy, heading, vel, valid, otype))
    xyz = np.concatenate([xy, 0.5 * size[..., 2:3]], axis=-1)
    motor = otype[:n_veh] == int(ObjectType.VEHICLE)
    sdc = _choose_sdc(xy[:n_veh], valid[:n_veh] & motor[:, None])
    order = np.concatenate([np.delete(np.arange(n_veh + n_ped), sdc), [sdc]])
    xyz, heading, vel, size, valid, otype = (
        a[order] for a in (xyz, heading, vel, size, valid, otype)
    )
    mask3 = valid[..., None]
    tracks = Tracks(
        id=(1 + rng.permutation(10 * len(order))[: len(order)]).astype(np.int64),
        object_type=otype.astype(np.int8),
        xyz=np.where(mask3, xyz, 0.0).astype(np.float64),
        heading=np.where(valid, heading, 0.0).astype(np.float32),
        velocity=np.where(mask3, vel, 0.0).astype(np.float32),
        size=np.where(mask3, size, 0.0).astype(np.float32),
        valid=valid,
    )
    return tracks


def _record(tracks: Tracks, road: _Road, rec: Recording, rng: np.random.Generator) -> Tracks:
    """``tracks`` with the tracker's jitter on moving objects and the parked vehicles of the lot
    rows inserted before the SDC (which stays last; earlier indices keep their objects)."""
    speed = np.linalg.norm(tracks.velocity, axis=-1).astype(np.float64)
    head = tracks.heading.astype(np.float64)
    dxy, dhead, dvel = jitter(head, speed, tracks.object_type, rec, rng)
    valid = tracks.valid
    xyz = tracks.xyz.copy()
    xyz[..., :2] += np.where(valid[..., None], dxy, 0.0)
    # Headings without jitter stay as they are (re-wrapping a float32 -pi would flip it).
    heading = np.where(valid & (dhead != 0.0), wrap_angle_np(head + dhead), tracks.heading)
    walks = [_Walk.of(line, road.observed) for line in road.net.sidewalks]
    size, xy, yaw = parked_vehicles(
        [(w.a, w.d, w.total, w.outward) for w in walks],
        road.net.road_edges,
        rec.parked_occupancy,
        rng,
    )
    keep = (np.abs(xy) <= road.observed).all(axis=-1)
    size, xy, yaw = size[keep], xy[keep], yaw[keep]
    k = len(size)
    ids = tracks.id.max() + 1 + rng.permutation(10 * max(k, 1))[:k]
    parked = {
        "id": ids.astype(np.int64),
        "object_type": np.full(k, int(ObjectType.VEHICLE), np.int8),
        "xyz": np.broadcast_to(
            np.concatenate([xy, 0.5 * size[:, 2:3]], axis=-1)[:, None], (k, NUM_STEPS, 3)
        ),
        "heading": np.broadcast_to(yaw[:, None], (k, NUM_STEPS)),
        "velocity": np.zeros((k, NUM_STEPS, 2)),
        "size": np.broadcast_to(size[:, None], (k, NUM_STEPS, 3)),
        "valid": np.ones((k, NUM_STEPS), bool),
    }
    moved = {
        "id": tracks.id,
        "object_type": tracks.object_type,
        "xyz": xyz,
        "heading": heading,
        "velocity": tracks.velocity + np.where(valid[..., None], dvel, 0.0),
        "size": tracks.size,
        "valid": tracks.valid,
    }
    dtypes = {n: getattr(tracks, n).dtype for n in moved}
    return Tracks(
        **{
            n: np.concatenate([a[:-1], parked[n], a[-1:]]).astype(dtypes[n])
            for n, a in moved.items()
        }
    )


SDC_MIN_TRAVEL_M: float = 10.0
"""The SDC is chosen among vehicles that drive at least this far in the log when there are any
(an ego car that waits out the whole log at a red light makes a dull default episode)."""


def _choose_sdc(xy: np.ndarray, valid: np.ndarray) -> int:
    """Index of the vehicle to be the SDC: valid at the current step, preferably one that drives
    ``SDC_MIN_TRAVEL_M`` or more in the log, then valid longest, then closest to the map
    centre at the current step.

    Args:
        xy: [V, T, 2] vehicle positions m; valid: [V, T] bool.
    """
    cur = valid[:, CURRENT_INDEX]
    if not cur.any():
        raise ValueError("no vehicle is valid at the current step; use more vehicles")
    both = valid[:, 1:] & valid[:, :-1]
    travel = (np.linalg.norm(np.diff(xy, axis=1), axis=-1) * both).sum(axis=1)
    moving = cur & (travel >= SDC_MIN_TRAVEL_M)
    ok = moving if moving.any() else cur
    dist = np.linalg.norm(xy[:, CURRENT_INDEX], axis=-1)
    score = np.where(ok, valid.sum(axis=1) * 1000.0 - dist, -np.inf)
    return int(np.argmax(score))


def _tracks_to_predict(tracks: Tracks, otype: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Up to 4 vehicle indices (not the SDC) nearest to the SDC at the current step that are
    valid then and for at least half of the future steps."""
    sdc = tracks.num_tracks - 1
    cur = CURRENT_INDEX
    ok = (otype == int(ObjectType.VEHICLE)) & valid[:, cur]
    ok &= valid[:, cur + 1 :].mean(axis=1) >= 0.5
    ok[sdc] = False
    d = np.linalg.norm(tracks.xyz[:, cur, :2] - tracks.xyz[sdc, cur, :2], axis=-1)
    cand = np.flatnonzero(ok)
    return np.sort(cand[np.argsort(d[cand], kind="stable")[:4]]).astype(np.int64)


def _signals(net: RoadNetwork, offset_s: float) -> TrafficSignals:
    """Lane states of the logged window, stop point at the end of each controlled lane."""
    if net.signals is None:
        return TrafficSignals.empty(NUM_STEPS)
    times = DT * np.arange(NUM_STEPS)
    state = signal_states(net.signals, times, offset_s)
    stop = np.asarray([np.append(net.lane(lid).points[-1], 0.0) for lid in net.signals.lane_ids])
    return TrafficSignals(
        lane_id=np.asarray(net.signals.lane_ids, np.int64),
        state=state,
        valid=np.ones(state.shape, bool),
        stop_point=stop,
    )


def training_mix(seed: int, layouts: tuple[str, ...] | None = None) -> Scenario:
    """One scene of the training mix: layouts taken round robin by seed.

    ``training_mix(seed)`` is ``generate_scenario(layouts[seed % len(layouts)], seed)``, the
    same scene a cache built as ``"generated:<layouts>:A-B"`` holds for that seed.

    Args:
        seed: scene seed (>= 0).
        layouts: layouts to cycle through; None uses every layout in ``LAYOUTS``.
    """
    names = LAYOUTS if layouts is None else tuple(layouts)
    if not names:
        raise ValueError("layouts must not be empty")
    return generate_scenario(names[int(seed) % len(names)], seed)


def default_scenarios(n: int = 4) -> list[Scenario]:
    """The embedded default scenes: a fixed list alternating layouts and seeds.

    Args:
        n: how many (1 .. 8).
    """
    if not 1 <= n <= len(_DEFAULT_SCENES):
        raise ValueError(f"n must be in [1, {len(_DEFAULT_SCENES)}], got {n}")
    return [generate_scenario(layout, seed) for layout, seed in _DEFAULT_SCENES[:n]]
