"""Parameters of the ``idm`` policy: per object type IDM and tracking values, and the policy's
settings, validated on construction (one ``ValueError`` naming the field).

Sources of the per-type values:

* **Vehicles** (also ``UNSET`` and ``OTHER``): the Intelligent Driver Model of Treiber,
  Hennecke & Helbing (2000, Phys. Rev. E 62, 1805), with the "city traffic" values of Treiber &
  Kesting, *Traffic Flow Dynamics* (2013), table 11.2: T = 1.0 s, s0 = 2 m, delta = 4,
  v0 = 15 m/s (54 km/h; used where neither the history nor a speed limit gives a desired
  speed), but a = 1.5 m/s^2 and b = 2.0 m/s^2 instead of 1.0 and 1.5: chosen on the real
  validation split (``docs/model_card/real_splits.json``; 24 scenes, 8 rollouts), where they
  raised the WOSAC kinematic bucket from 0.322 to 0.355 at the same collision and off-road
  rates. The braking limit is the unicycle's (5 m/s^2, ``constants.MAX_ACCEL``). Pure
  pursuit looks 3 m + 0.3 s x speed ahead (chosen there too: 4 m + 0.6 s cut corners, off-road
  rate 0.138 against 0.124).
* **Cyclists** and **pedestrians**: no published IDM calibration is used; tbsim's choices,
  scaled from the vehicle values: cyclists v0 = 5 m/s (18 km/h), s0 = 1 m; pedestrians
  v0 = 1.34 m/s (the mean free walking speed of Weidmann 1993), T = 0.5 s, s0 = 0.5 m.

Per agent the desired speed and the time headway are drawn around these values
(``IDMConfig.speed_spread``, ``headway_spread``) from the rollout's generator, so that
rollouts of one scene differ; an agent that follows its leader closer at the start than its
headway allows gets a shorter one for a while (``IDMConfig.min_headway``,
``HEADWAY_RELAX_TIME``).
"""

from __future__ import annotations

import dataclasses
import enum
from dataclasses import dataclass

# ----------------------------------------------------------------- fixed sizes and tolerances
ROUTE_SPACING = 2.5
"""m between the points of a route (uniform in arc length)."""
ROUTE_POINTS = 128
"""Points per route: 317.5 m, more than 80 steps at 30 m/s plus the leader horizon."""
CHORDS = 8
"""Straight pieces the route ahead (the leader horizon) is cut into for the corridor test."""
HORIZON_BASE = 10.0
"""m: the leader horizon of a standing agent; it grows by ``HORIZON_TIME`` per m/s of speed
up to ``IDMConfig.horizon``."""
HORIZON_TIME = 3.0
"""s (see ``HORIZON_BASE``): at 10 m/s a 40 m horizon, where a standing obstacle already
takes half the IDM's acceleration."""
LEADER_PERIOD = 3
"""Default of ``IDMConfig.leader_period``: steps between two leader searches of an agent (0.3
s, a reaction time); in between, the gap to the leader found is carried on at the speeds
then. The stop line that holds the agent (signals, stop signs, crosswalks) is looked up on
the same steps and its arc along the route carried on. A row's agents do both together, on
its steps that are multiples of the period and at its first act; an agent that appears later
waits for the row's next search (at most 0.2 s). A search of a few agents costs about the
tensor operations of a search of all, so two steps in three skip both whole.

On the validation scenes (90% paired intervals): a period of 3 scores as 2 did (meta -0.0003
[-0.0010, +0.0004], collisions +0.0005 [-0.0006, +0.0020]); 4 raised collisions (+0.0034
[+0.0004, +0.0077]); a row's agents at once scored as a third of them each step (meta +0.0002
[-0.0005, +0.0008], collisions +0.0004 [-0.0009, +0.0019]; in ``BatchedTrafficEnv``, of the
1,145 vehicles appearing after the start, as many collide either way); stop lines on the
period as every step (meta +0.0001 [-0.0001, +0.0003], collisions and off-road unchanged)."""
DISC_SLACK = 1.0
"""m added to the leader search's candidate discs (``leaders.candidate_pairs``): the product
form of the disc test rounds, and a superset is harmless (the corridor tests that follow are
exact; the corridor lies > 0.5 m inside each disc)."""
FAR_AWAY = 1.0e6
"""m, the coordinate that stands for an absent agent in the candidate disc test (finite, so
that its products stay finite)."""
CROSSING_HORIZON = 2.0
"""s: a crossing agent's path this far ahead in time (constant velocity) is tested too: the
first time its box enters the corridor."""
CROSSING_SIN = 0.5
"""An agent crosses a route when its heading is more than 30 deg off the route's (sine)."""
YIELD_SLACK = 0.5
"""s: an agent goes before a crossing agent whose box enters its path at time tau only when
it would clear that point (its gap, the crossing box's extent along its route and its own
length, at its speed now, at least 1 m/s) more than this before tau; else it yields."""
HEADWAY_FIT_SPEED = 2.0
"""m/s: agents slower than this at the start keep their drawn time headway (a queue's gaps
say little about a headway)."""
HEADWAY_RELAX_TIME = 4.0
"""s: the time constant with which the headway cut of an agent that follows closely at the
start shrinks back to its drawn headway (exponentially; 2, 4 and 8 s did alike on the real
validation split, each back to the collision rate without the cut, 0.020, where keeping the
cut for good gave 0.021)."""
HEADWAY_FIT_SHARE = 0.25
"""The least share of the maximum acceleration that a leader at the start takes away from an
agent whose headway is fitted to its gap (``IDMPolicy._start_cut``: where the free-road term
leaves less, e.g. an agent at or above its desired speed)."""
MAX_SIGNAL_STOPS = 4
"""Signal-controlled stop lines kept per route (the first along it)."""
MAX_SIGN_STOPS = 2
"""Stop-sign lines kept per route."""
MAX_CROSSWALKS = 4
"""Crosswalks kept per route."""
SCENE_CROSSWALKS = 32
"""Crosswalk polygons kept per scene (the first in map order)."""
CROSSWALK_VERTICES = 8
"""Vertices kept per crosswalk polygon (longer outlines are reduced to their convex hull's
first ones; WOMD crosswalks are quadrilaterals)."""
LINK_TOLERANCE = 0.2
"""m: lane a leads into lane b when a's last point is this near b's first (links inferred
from geometry; linked WOMD lanes share the point exactly)."""
LINK_MAX_TURN = 0.785
"""rad (45 deg): largest heading change between a lane's end and an inferred successor."""
LANE_MATCH_DISTANCE = 1.5
"""m: an agent is on a lane when a lane centre line passes this near."""
LANE_MATCH_COS = 0.7
"""The lane's direction there is within 45 deg of the agent's heading (cosine)."""
STOP_MATCH_DISTANCE = 2.0
"""m: a route passes a stop line when its controlled lane's first point is this near."""
STOP_FOLLOW_DISTANCE = 1.5
"""m: and the controlled lane's points 5 m and 10 m on stay this near the route (which lane
of a fork the stop line controls)."""
SIGN_LANE_RADIUS = 8.0
"""m: without the map's list, a stop sign controls the lanes that start this near it (behind
it, the sign not on their left)."""
STOPPED_SPEED = 0.3
"""m/s: an agent slower than this within ``SIGN_STOP_ZONE`` of a stop-sign line has made its
full stop."""
SIGN_STOP_ZONE = 4.0
"""m: bumper gap to a stop-sign line within which a stop counts."""
MOVING_SPEED = 0.5
"""m/s: an agent faster than this near a stop sign's junction keeps it occupied."""
STILL_HISTORY_SPEED = 0.3
"""m/s: an agent never faster than this over its history stands still (desired speed 0 off
lanes)."""


class Route(str, enum.Enum):
    """Which path an IDM agent follows (see ``policies.idm``)."""

    LOG = "log"
    LANES = "lanes"


@dataclass(frozen=True)
class TypeParams:
    """IDM and path-tracking parameters of one object type.

    Attributes:
        max_accel: IDM a, m/s^2 (> 0).
        comfort_decel: IDM b, m/s^2 (> 0).
        time_headway: IDM T, s (>= 0).
        standstill_gap: IDM s0, bumper gap kept at rest, m (>= 0).
        max_decel: hard braking limit, m/s^2 (> 0; the dynamics clip at the type's limit).
        default_speed: desired speed without a better source, m/s (> 0).
        min_lookahead: pure-pursuit lookahead at rest, m (> 0).
        lookahead_time: lookahead added per m/s of speed, s (>= 0).
        exponent: IDM delta (> 0).
    """

    max_accel: float
    comfort_decel: float
    time_headway: float
    standstill_gap: float
    max_decel: float
    default_speed: float
    min_lookahead: float
    lookahead_time: float
    exponent: float = 4.0

    def __post_init__(self) -> None:
        positive = ("max_accel", "comfort_decel", "max_decel", "default_speed", "min_lookahead")
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            strict = f.name in positive or f.name == "exponent"
            ok = value > 0.0 if strict else value >= 0.0
            if not ok or value != value or value == float("inf"):
                bound = "> 0" if strict else ">= 0"
                raise ValueError(f"IDM parameter {f.name} must be finite and {bound}, got {value}")


VEHICLE = TypeParams(
    max_accel=1.5,
    comfort_decel=2.0,
    time_headway=1.0,
    standstill_gap=2.0,
    max_decel=5.0,
    default_speed=15.0,
    min_lookahead=3.0,
    lookahead_time=0.3,
)
CYCLIST = TypeParams(
    max_accel=1.0,
    comfort_decel=1.5,
    time_headway=1.0,
    standstill_gap=1.0,
    max_decel=5.0,
    default_speed=5.0,
    min_lookahead=2.5,
    lookahead_time=0.5,
)
PEDESTRIAN = TypeParams(
    max_accel=1.0,
    comfort_decel=1.5,
    time_headway=0.5,
    standstill_gap=0.5,
    max_decel=3.0,
    default_speed=1.34,
    min_lookahead=1.0,
    lookahead_time=0.5,
)


def _type_params(value: TypeParams | dict, base: TypeParams) -> TypeParams:
    """``value`` as ``TypeParams``: as given, or ``base`` with the fields of a dict replaced."""
    if isinstance(value, TypeParams):
        return value
    if isinstance(value, dict):
        unknown = set(value) - {f.name for f in dataclasses.fields(TypeParams)}
        if unknown:
            raise ValueError(f"unknown IDM parameter(s) {sorted(unknown)}")
        return dataclasses.replace(base, **value)
    raise TypeError(f"IDM type parameters must be TypeParams or a dict, got {value!r}")


@dataclass(frozen=True)
class IDMConfig:
    """Settings of the ``idm`` policy.

    Attributes:
        route: ``Route.LOG`` (the agent's logged path, then the lane graph) or ``Route.LANES``
            (a lane-graph path; fork branches chosen by the logged future where there is one).
            Scenes without a logged future use lanes whatever this says.
        vehicle, cyclist, pedestrian: per-type parameters (a dict replaces fields of the
            defaults).
        speed_spread: each agent's desired speed is scaled by a factor drawn uniformly from
            [1 - spread, 1 + spread] (in [0, 1)). 0.5 from a sweep on the real validation
            split (meta-metric 0.750 at 0.05, 0.756 at 0.2, 0.761 at 0.5, 0.765 at 0.8: wider
            draws cover more of the logged futures); 0.5 keeps desired speeds within 1.5x
            of the history's either way.
        headway_spread: likewise for its time headway (in [0, 1)).
        lateral_accel: m/s^2 (> 0), the speed in a bend of the path is capped at
            sqrt(lateral_accel / curvature), approached with comfortable braking.
        horizon: m (> 0), how far ahead along the path leaders are looked for at most (less
            at low speed: ``HORIZON_BASE`` + ``HORIZON_TIME`` x speed).
        lateral_margin: m (>= 0) added on each side of the agent's width to its corridor.
        min_gap: m (> 0), smaller gaps (and overlaps) count as this one.
        stop_gap: m (>= 0), the gap kept to a stop line (red light, stop sign, crosswalk).
        junction_radius: m (> 0), a stop sign's junction is clear when no other agent moves
            within this distance of the stop line.
        cruise_speed: m/s (>= 0): an agent at least this fast at the start keeps its highest
            history speed as its desired speed; a slower one on a lane (queued, starting off)
            wants the lane's speed limit (``plan.desired_speeds``).
        min_headway: s (>= 0): an agent that follows a leader closer at the start than its time
            headway allows has its headway lowered, to no less than this, the cut then
            shrinking back (``HEADWAY_RELAX_TIME``; ``IDMPolicy._start_cut``): real
            drivers keep 0.5-1 s where the IDM's 1 s would brake them at once. 0.3 on the
            real validation split (57 scenes, 32 rollouts): minADE 3.29 -> 3.20 m, the
            meta-metric the same (0.763); 0.5 s and 0.2 s (tried without the relaxation) did
            no better.
        pedestrian_gaps: pedestrians keep IDM gaps to other pedestrians. Off by default:
            people walk in groups, shoulder to shoulder, and WOMD's pedestrian boxes overlap
            there (logged pedestrians "collide" with each other in many real scenes); a
            pedestrian still keeps its gap to vehicles and cyclists, and they to it.
        leader_period: steps (an integer >= 1) between two leader searches of an agent
            (``LEADER_PERIOD``); 1 searches every step (the ``idm`` planner: one agent, no
            cost to save).
    """

    route: Route | str = Route.LOG
    vehicle: TypeParams | dict = VEHICLE
    cyclist: TypeParams | dict = CYCLIST
    pedestrian: TypeParams | dict = PEDESTRIAN
    speed_spread: float = 0.5
    headway_spread: float = 0.2
    lateral_accel: float = 2.5
    horizon: float = 50.0
    lateral_margin: float = 0.3
    min_gap: float = 0.1
    stop_gap: float = 1.0
    junction_radius: float = 12.0
    cruise_speed: float = 8.0
    min_headway: float = 0.3
    pedestrian_gaps: bool = False
    leader_period: int = LEADER_PERIOD

    def __post_init__(self) -> None:
        try:
            route = Route(self.route)
        except ValueError:
            raise ValueError(f"IDM route must be 'log' or 'lanes', got {self.route!r}") from None
        object.__setattr__(self, "route", route)
        object.__setattr__(self, "vehicle", _type_params(self.vehicle, VEHICLE))
        object.__setattr__(self, "cyclist", _type_params(self.cyclist, CYCLIST))
        object.__setattr__(self, "pedestrian", _type_params(self.pedestrian, PEDESTRIAN))
        checks = {
            "speed_spread": 0.0 <= self.speed_spread < 1.0,
            "headway_spread": 0.0 <= self.headway_spread < 1.0,
            "lateral_accel": self.lateral_accel > 0.0,
            "horizon": self.horizon > 0.0,
            "lateral_margin": self.lateral_margin >= 0.0,
            "min_gap": self.min_gap > 0.0,
            "stop_gap": self.stop_gap >= 0.0,
            "junction_radius": self.junction_radius > 0.0,
            "cruise_speed": self.cruise_speed >= 0.0,
            "min_headway": self.min_headway >= 0.0,
            "leader_period": float(self.leader_period).is_integer() and self.leader_period >= 1,
        }
        for name, ok in checks.items():
            value = getattr(self, name)
            if not ok or value != value or value == float("inf"):
                raise ValueError(f"IDM setting {name} is out of range: {value}")
        object.__setattr__(self, "leader_period", int(self.leader_period))


__all__ = [
    "CYCLIST",
    "PEDESTRIAN",
    "VEHICLE",
    "IDMConfig",
    "Route",
    "TypeParams",
]
