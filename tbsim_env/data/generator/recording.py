"""What real WOMD logs hold beyond the traffic the generator drives: parked vehicles and the
tracker's jitter.

The generator's tracks are exact and its streets have no parked cars. Real logs differ in two
ways that no driving parameter can reproduce (docs/model_card/generator_calibration.md):

* **Parked vehicles.** About 60% of the vehicle steps of the real training scenes belong to
  tracks that never move 2 m. ``parked_vehicles`` fills the parking slots of a lot row behind
  each observed sidewalk (``LOT_OFFSET_M`` beyond its walking line, clear of the standing
  pedestrians) with a share ``Recording.parked_occupancy`` of parked vehicles, each row parked
  either along the street or facing it. WOMD's labels hold parked objects exactly still, so
  they get no jitter.
* **Tracker jitter.** On moving real vehicles the logged box centre scatters around a smooth
  path by about 1.2 cm along the heading and 0.4 cm across it (median track; the residual of
  a 1 s quadratic fit, with no correlation from one step to the next), the heading by about
  1.4 mrad. Central differences turn that into the wide tails of the real acceleration
  histograms. ``jitter`` adds white Gaussian noise of that kind to every moving track, scaled
  per track by a log-normal factor (the real spread between tracks) and, for vehicles and
  cyclists, per step by the speed up to ``JITTER_FULL_SPEED`` (standing vehicles stay exact,
  as in WOMD, where standing pedestrians jitter by about 3 cm and 0.3 rad). The logged
  velocity, the tracker's own estimate that the policies read as speed and acceleration, gets
  its own white noise of the size measured on the real tracks (``speed_jitter``): the histogram
  fit cannot see it (the WOSAC features come from positions).

A ``Recording`` is applied by ``generate_scenario(..., recording=...)`` after the traffic is
simulated, from random streams of its own: the driven traffic is the same with or without it.
``RECORDED`` holds the values fitted by ``scripts/calibrate_generator.py`` on the real training
scenes (the velocity jitter measured there, not fitted). Units: metres, radians, m/s.
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from tbsim_env.core.boxes import box_corners_numpy
from tbsim_env.core.constants import ObjectType
from tbsim_env.data.generator.driver import CAR_SIZE_RANGE, VAN_SIZE_RANGE

LOT_OFFSET_M: float = 6.0
"""The lot row's near side lies this far beyond a sidewalk's walking line, away from the road
(walkers keep within 1 m of the line, standing pedestrians stand 2.5 m beyond it), m."""

LOT_START_M: float = 4.0
"""Rows start this far along their sidewalk's observed part (clear of the junction corner
where two arms' rows meet), m."""

SLOT_PITCH_M: dict[str, float] = {"along": 7.0, "facing": 3.0}
"""Length of one parking slot along the row: parked along the street or facing it, m."""

ROAD_CLEARANCE_M: float = 1.5
"""A parked box keeps at least this far from every road edge; a slot that cannot is left
empty, m."""

PARKED_GAP_M: float = 0.3
"""A parked box keeps at least this far from the other parked boxes (where two rows meet), m."""

JITTER_FULL_SPEED: float = 1.0
"""Speed from which a track gets its full jitter (linearly less below, none standing), m/s."""

JITTER_TRACK_SPREAD: float = 0.7
"""Standard deviation of the log of a track's jitter factor (real tracks: the 90th percentile
of the along-heading scatter is about 2.5 times the median)."""


@dataclass(frozen=True)
class Recording:
    """Parked vehicles and tracker jitter added to a generated log.

    Attributes:
        parked_occupancy: share of the lot rows' parking slots that hold a parked vehicle,
            in [0, 1].
        jitter_along: standard deviation of the white noise on a moving vehicle's or cyclist's
            box centre along its heading, m.
        jitter_lateral: the same across its heading, m.
        jitter_heading: standard deviation of the white noise on its heading, rad.
        ped_jitter: standard deviation of the white noise on a pedestrian's position, each axis,
            m.
        ped_jitter_heading: the same on a standing pedestrian's heading, rad (a tracker cannot
            tell which way a standing person faces: about 0.3 rad on real standing tracks).
        ped_walking_jitter_heading: the same on a pedestrian walking at ``JITTER_FULL_SPEED``
            or faster (the heading follows the motion), rad; linear in between.
        speed_jitter: standard deviation of the white noise on a moving vehicle's or cyclist's
            logged velocity along its heading, m/s (the tracker's velocity, which the policies
            read, is far noisier than its positions: real moving vehicles' logged speed
            scatters by 0.16 m/s around a 1 s quadratic fit, median track).
        ped_speed_jitter: the same on a pedestrian's velocity, each axis, m/s.
    """

    parked_occupancy: float
    jitter_along: float
    jitter_lateral: float
    jitter_heading: float
    ped_jitter: float
    ped_jitter_heading: float
    ped_walking_jitter_heading: float
    speed_jitter: float
    ped_speed_jitter: float

    def __post_init__(self) -> None:
        for f in fields(self):
            if not getattr(self, f.name) >= 0.0:
                raise ValueError(f"Recording.{f.name} must be >= 0, got {getattr(self, f.name)}")
        if self.parked_occupancy > 1.0:
            raise ValueError(
                f"Recording.parked_occupancy must be <= 1, got {self.parked_occupancy}"
            )


# Fitted by scripts/calibrate_generator.py on the real "train" scenes of
# docs/model_card/real_splits.json (docs/model_card/generator_calibration.md); rerun the
# script to refit, it rewrites this block.
# BEGIN RECORDED
RECORDED = Recording(
    parked_occupancy=0.125,
    jitter_along=0.02513,
    jitter_lateral=0.01,
    jitter_heading=0.003,
    ped_jitter=0.00419,
    ped_jitter_heading=0.27,
    ped_walking_jitter_heading=0.00675,
    speed_jitter=0.19,
    ped_speed_jitter=0.125,
)
# END RECORDED
"""The recording fitted to the real training scenes (use with ``behaviour.CALIBRATED``)."""

TRACKER = Recording(
    parked_occupancy=0.0,
    jitter_along=0.0115,
    jitter_lateral=0.0044,
    jitter_heading=0.00137,
    ped_jitter=0.0063,
    ped_jitter_heading=0.045,
    ped_walking_jitter_heading=0.005,
    speed_jitter=0.19,
    ped_speed_jitter=0.125,
)
"""The tracker's white jitter on the real train tracks, no parked vehicles: per track the robust
standard deviation (1.4826 x median absolute deviation) of the second differences of its box
centre (along and across the heading) and heading over 0.1 s steps, divided by sqrt(6) (what
white noise gives), then the median over tracks: vehicles moving at 3 m/s or more (1,481
tracks), pedestrians walking at 1 m/s or more (392: their positions, heading) and standing
below 0.2 m/s (82: heading); standing vehicles measure exactly 0
(``scripts/diagnose_kinematics.py tracker``). The vehicles' values agree with the 1 s
quadratic-fit residuals the generator's fit starts from; a standing pedestrian's heading
scatters by 0.27 rad about its mean (``RECORDED``) but changes by only this much from step to
step. What a simulated trajectory lacks to look like a WOMD log
(``policies.trafficbots.wosac.record_rollouts``, docs/model_card/kinematics.md); the velocity
jitter is ``RECORDED``'s (the WOSAC features do not read it)."""


def _car_sizes(rng: np.random.Generator, n: int) -> np.ndarray:
    """[n, 3] (length, width, height) of parked cars and vans, m (the driver's car and van
    ranges)."""
    van = rng.random(n) < 0.15
    sizes = [
        np.where(van, rng.uniform(*v, n), rng.uniform(*c, n))
        for v, c in zip(VAN_SIZE_RANGE, CAR_SIZE_RANGE)
    ]
    return np.stack(sizes, axis=1)


def parked_vehicles(
    walks: list[tuple[np.ndarray, np.ndarray, float, np.ndarray]],
    road_edges: tuple[np.ndarray, ...],
    occupancy: float,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Vehicles parked in a lot row behind each sidewalk.

    Args:
        walks: per observed sidewalk, (start [2], unit direction [2], length m, unit normal
            away from the road [2]).
        road_edges: the map's road-edge polylines [n, 2].
        occupancy: share of slots filled, in [0, 1].
        rng: the recording's stream.

    Returns:
        (size [K, 3] m, centre [K, 2] m, heading [K] rad) of the K parked vehicles.
    """
    import shapely

    edges = shapely.MultiLineString([e for e in road_edges]) if road_edges else None
    boxes: list[shapely.Polygon] = []
    out_size, out_xy, out_head = [], [], []
    for a, d, total, outward in walks:
        kind = "along" if rng.random() < 0.5 else "facing"
        pitch = SLOT_PITCH_M[kind]
        n = int((total - LOT_START_M) // pitch)
        if n <= 0:
            continue
        taken = rng.random(n) < occupancy
        size = _car_sizes(rng, n)
        flip = rng.random(n) < 0.5
        yaw_noise = rng.normal(0.0, 0.05, n)
        for k in np.flatnonzero(taken):
            length, width = size[k, 0], size[k, 1]
            depth = width if kind == "along" else length
            base = d if kind == "along" else outward
            centre = (
                a + (LOT_START_M + (k + 0.5) * pitch) * d + (LOT_OFFSET_M + depth / 2) * outward
            )
            heading = float(np.arctan2(base[1], base[0]) + (np.pi if flip[k] else 0.0))
            heading += float(yaw_noise[k])
            poly = shapely.Polygon(box_corners_numpy(centre, np.float64(heading), length, width))
            if edges is not None and poly.distance(edges) < ROAD_CLEARANCE_M:
                continue
            if any(poly.distance(b) < PARKED_GAP_M for b in boxes):
                continue
            boxes.append(poly)
            out_size.append(size[k])
            out_xy.append(centre)
            out_head.append(np.arctan2(np.sin(heading), np.cos(heading)))
    if not out_size:
        return np.zeros((0, 3)), np.zeros((0, 2)), np.zeros(0)
    return np.asarray(out_size), np.asarray(out_xy), np.asarray(out_head)


def jitter(
    heading: np.ndarray,
    speed: np.ndarray,
    object_type: np.ndarray,
    rec: Recording,
    rng: np.random.Generator,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tracker jitter of logged poses and velocities (see the module docstring).

    Args:
        heading: [A, T] exact headings, rad (the jitter's along / across directions).
        speed: [A, T] speed of the exact track, m/s (scales the jitter of vehicles and cyclists
            per step; pedestrians jitter standing too, as the real ones do).
        object_type: [A] ``ObjectType``.
        rec: the noise levels.
        rng: the recording's stream.

    Returns:
        (offset [A, T, 2] m, heading offset [A, T] rad, velocity offset [A, T, 2] m/s) to add to
        the box centres, headings and velocities; exactly 0 where a track gets no jitter.
    """
    n, t = heading.shape
    ped = object_type == int(ObjectType.PEDESTRIAN)
    along = np.where(ped, rec.ped_jitter, rec.jitter_along)[:, None]
    lateral = np.where(ped, rec.ped_jitter, rec.jitter_lateral)[:, None]
    moving = np.clip(speed / JITTER_FULL_SPEED, 0.0, 1.0)
    ped_head = rec.ped_jitter_heading + moving * (
        rec.ped_walking_jitter_heading - rec.ped_jitter_heading
    )
    head = np.where(ped[:, None], ped_head, rec.jitter_heading * moving)
    scale = np.exp(rng.normal(0.0, JITTER_TRACK_SPREAD, n))[:, None]
    eps = rng.standard_normal((5, n, t)) * scale
    pos = np.where(ped[:, None], 1.0, moving)
    c, s = np.cos(heading), np.sin(heading)

    def rotate(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.stack([c * u - s * v, s * u + c * v], axis=-1)

    offset = rotate(eps[0] * along * pos, eps[1] * lateral * pos)
    v_along = np.where(ped, rec.ped_speed_jitter, rec.speed_jitter)[:, None] * pos
    v_across = np.where(ped, rec.ped_speed_jitter, 0.0)[:, None]
    return offset, eps[2] * head, rotate(eps[3] * v_along, eps[4] * v_across)
