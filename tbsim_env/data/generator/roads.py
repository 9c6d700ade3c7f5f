"""Road layouts of the procedural generator: lane graph, road lines, edges, crosswalks, signals.

All geometry is 2-D in metres (z = 0 when written to a ``RoadMap``), traffic drives on the
right. Lane ids are 1..L in lane order; the other map features get the following ids.
Layouts are fixed (the seed only changes traffic and signal timing).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tbsim_env.core.constants import (
    LaneType,
    MapFeatureType,
    RoadEdgeType,
    RoadLineType,
    SignalState,
)
from tbsim_env.data.generator.geometry import bezier, circle_arc, line, offset, resample
from tbsim_env.data.scenario import RoadMap

LANE_WIDTH = 3.5
"""Lane width in metres."""


@dataclass(frozen=True)
class Lane:
    """One lane centre line of the generated map.

    Attributes:
        id: map feature id (1-based, unique).
        points: [n, 2] float64 centre line in metres, ~0.5 m spacing, in driving direction.
        entry: ids of predecessor lanes.
        exit: ids of successor lanes.
        left: ids of left neighbour lanes.
        right: ids of right neighbour lanes.
        approach: intersection arm the lane enters from (inbound and connector lanes), else -1.
        is_connector: True for lanes inside the intersection box.
    """

    id: int
    points: np.ndarray
    entry: tuple[int, ...]
    exit: tuple[int, ...]
    left: tuple[int, ...]
    right: tuple[int, ...]
    approach: int
    is_connector: bool


@dataclass(frozen=True)
class Merge:
    """A lane that must yield where it merges into a priority lane (same successor lane).

    Attributes:
        priority_lane: id of the lane with right of way.
        yield_lane: id of the merging lane.
        conflict_s: arc length (m) along the yield lane from which vehicles on the two lanes
            could touch; a yielding vehicle must not pass it without an accepted gap.
    """

    priority_lane: int
    yield_lane: int
    conflict_s: float


PRIORITY = 0
"""``JunctionControl.kind`` of an approach with right of way (no sign, no full stop)."""
STOP = 1
"""``JunctionControl.kind`` of a stop-sign approach (full stop at the line, then yield)."""


@dataclass(frozen=True)
class JunctionControl:
    """Right-of-way rules of a junction: an unsignalised one, or the permissive turns of a
    signalised one (there only vehicles whose light lets them go take part).

    Every controlled lane ends at a stop line where its connector lanes begin. A vehicle
    crosses the line only once it has been granted its connector, which the driver does when
    no conflicting connector is held (see ``connector_conflicts``) and, for a lower rank, no
    higher-ranked vehicle is approaching within the driver's accepted time gap.

    Attributes:
        lane_ids: ids of the controlled inbound lanes, [J].
        kind: ``PRIORITY`` or ``STOP`` per controlled lane, [J].
        rank: priority rank of each connector lane id (dict lane id -> rank): 0 = major
            through/right turn, 1 = major left turn (yields to oncoming rank 0), 2 = minor
            road / stop sign (yields to ranks 0 and 1). Equal ranks go first come first
            served.
    """

    lane_ids: tuple[int, ...]
    kind: tuple[int, ...]
    rank: dict[int, int]


@dataclass(frozen=True)
class StopSign:
    """A stop sign: its position [2] (metres, at the kerb by the stop line) and lane ids."""

    position: np.ndarray
    lanes: tuple[int, ...]


PERMISSIVE_GREEN_S = 18.0
"""Green time of each of the two phases of ``build_permissive_intersection``, seconds."""


@dataclass(frozen=True)
class SignalPlan:
    """Fixed-time signal plan: each phase gets green, then yellow, then an all-red clearance.

    Attributes:
        lane_ids: ids of the controlled (inbound) lanes, [S].
        phase: phase index of each controlled lane, [S].
        num_phases: phases per cycle, served in index order.
        green_s: green time of a phase in seconds.
        yellow_s: yellow time in seconds.
        all_red_s: all-red clearance after each yellow, in seconds.
    """

    lane_ids: tuple[int, ...]
    phase: tuple[int, ...]
    num_phases: int
    green_s: float
    yellow_s: float
    all_red_s: float

    @property
    def phase_s(self) -> float:
        """Duration of one phase (green + yellow + all-red) in seconds."""
        return self.green_s + self.yellow_s + self.all_red_s

    @property
    def cycle_s(self) -> float:
        """Duration of one full cycle in seconds."""
        return self.phase_s * self.num_phases


def signal_states(plan: SignalPlan, times: np.ndarray, offset_s: float) -> np.ndarray:
    """Signal state of every controlled lane at the given times.

    Args:
        plan: the signal plan.
        times: [T] seconds (any real values; the plan is periodic).
        offset_s: phase offset in seconds, added to ``times``.

    Returns:
        [S, T] int8 ``SignalState`` values (GO, CAUTION or STOP).
    """
    t = np.mod(np.asarray(times, float) + offset_s, plan.cycle_s)
    start = np.asarray(plan.phase, float)[:, None] * plan.phase_s
    local = np.mod(t[None, :] - start, plan.cycle_s)
    state = np.full(local.shape, int(SignalState.STOP), np.int8)
    state[local < plan.green_s + plan.yellow_s] = int(SignalState.CAUTION)
    state[local < plan.green_s] = int(SignalState.GO)
    return state


@dataclass(frozen=True)
class Crossing:
    """Where pedestrians cross one junction arm: its crosswalk and the walking lines to it.

    Coordinates are relative to the crosswalk centre: ``along`` points along the arm away
    from the junction, ``axis`` across the road (the crosswalk's long side). A crossing
    pedestrian comes in on a walking line ``walk`` metres to one side of the arm's axis,
    bends at ``bend`` toward the kerb point (``kerb`` to that side, off the road), crosses
    to the kerb point on the other side and leaves on the other walking line.

    Attributes:
        arm: the junction arm (polar angle arm * pi / 2) the crosswalk lies on.
        centre: [2] crosswalk centre, metres.
        along: [2] unit vector along the arm, away from the junction.
        axis: [2] unit vector across the road.
        kerb: distance from the centre line of the arm to the kerb (waiting) points, m.
        walk: distance from the centre line of the arm to the walking lines, m (beyond the
            sidewalk walkers' paths).
        bend: ``along`` coordinate where the walking lines bend toward the kerb, m.
        reach: ``along`` coordinate of the map border, m.
        offset: range of the ``along`` coordinate of the crossing line on the crosswalk, m
            (the outer half, so that pedestrians at the kerb points of two neighbouring
            arms stay apart).
    """

    arm: int
    centre: np.ndarray
    along: np.ndarray
    axis: np.ndarray
    kerb: float
    walk: float
    bend: float
    reach: float
    offset: tuple[float, float]


@dataclass(frozen=True)
class RoadNetwork:
    """A complete generated road layout.

    Attributes:
        layout: layout name.
        lane_type: ``LaneType`` of every lane.
        speed_limit_mph: speed limit of every lane.
        lanes: lane centre lines with the lane graph; ``lanes[k].id == k + 1``.
        road_lines: polylines [n, 2] of painted lines.
        road_line_types: ``RoadLineType`` per road line.
        road_edges: polylines [n, 2], oriented with the road on their left.
        crosswalks: polygons [4, 2].
        sidewalks: pedestrian walking paths [n, 2] (off-road).
        signals: the signal plan, or None for an unsignalised layout.
        merges: lanes that must yield to another lane.
        half_extent: the map covers [-half_extent, half_extent]^2; objects leave beyond it.
        junction: right-of-way rules of an unsignalised junction, or None.
        stop_signs: stop signs (written as ``MapFeatureType.STOP_SIGN``).
        crossings: pedestrian crossings, one per crosswalk (same order).
    """

    layout: str
    lane_type: LaneType
    speed_limit_mph: float
    lanes: tuple[Lane, ...]
    road_lines: tuple[np.ndarray, ...]
    road_line_types: tuple[RoadLineType, ...]
    road_edges: tuple[np.ndarray, ...]
    crosswalks: tuple[np.ndarray, ...]
    sidewalks: tuple[np.ndarray, ...]
    signals: SignalPlan | None
    merges: tuple[Merge, ...]
    half_extent: float
    junction: JunctionControl | None = None
    stop_signs: tuple[StopSign, ...] = ()
    crossings: tuple[Crossing, ...] = ()

    def lane(self, lane_id: int) -> Lane:
        """The lane with this id."""
        return self.lanes[lane_id - 1]

    @property
    def source_lanes(self) -> tuple[int, ...]:
        """Ids of lanes without predecessors (where traffic enters the map)."""
        return tuple(ln.id for ln in self.lanes if not ln.entry)


def _link(
    points: list[np.ndarray],
    exits: dict[int, list[int]],
    left: dict[int, list[int]],
    right: dict[int, list[int]],
    approach: list[int],
    connector: list[bool],
) -> tuple[Lane, ...]:
    """Freeze 0-based lane lists into ``Lane`` objects with 1-based ids and symmetric entries."""
    entries: dict[int, list[int]] = {k: [] for k in range(len(points))}
    for k, outs in exits.items():
        for o in outs:
            entries[o].append(k)
    return tuple(
        Lane(
            id=k + 1,
            points=points[k],
            entry=tuple(e + 1 for e in entries[k]),
            exit=tuple(e + 1 for e in exits.get(k, [])),
            left=tuple(e + 1 for e in left.get(k, [])),
            right=tuple(e + 1 for e in right.get(k, [])),
            approach=approach[k],
            is_connector=connector[k],
        )
        for k in range(len(points))
    )


JUNCTION_LANES = 2
"""Lanes per direction on every junction arm."""
STOP_LINE_M = 14.0
"""Distance from the junction centre to the stop lines (and the kerb corners), metres."""
CROSSWALK_M = (8.5, 12.0)
"""Crosswalk extent along each arm from the junction centre, metres."""
SIDEWALK_KERB_M = 2.5
"""Sidewalk walking line beyond the road edge, metres."""
SIDEWALK_START_M = 3.0
"""Sidewalks start this far past the stop line, metres."""
SPLIT_PHASES = dict(green_s=9.0, yellow_s=3.5, all_red_s=2.5)
"""Timing of the split-phase signals (one arm at a time), seconds."""
PERMISSIVE_PHASES = dict(green_s=PERMISSIVE_GREEN_S, yellow_s=3.5, all_red_s=2.0)
"""Timing of the two-phase signals with permissive left turns, seconds."""
SPEED_LIMIT_MPH = {"signal": 35.0, "stop": 30.0}
"""Lane speed limits of signalised and stop-controlled junctions."""


def _axes(k: int) -> tuple[np.ndarray, np.ndarray]:
    """(along, right-hand normal) unit vectors of arm k (polar angle k * pi / 2)."""
    th = k * np.pi / 2
    return np.array([np.cos(th), np.sin(th)]), np.array([-np.sin(th), np.cos(th)])


@dataclass(frozen=True)
class _JunctionLanes:
    """The lane graph of a junction (0-based lane indices inside).

    Attributes:
        lanes: the frozen lanes.
        inbound: arm -> its inbound lane indices, inner lane first.
        exits: lane index -> successor lane indices.
        turn: connector index -> -1 right, 0 through, 1 left.
    """

    lanes: tuple[Lane, ...]
    inbound: dict[int, list[int]]
    exits: dict[int, list[int]]
    turn: dict[int, int]


def _junction_lanes(arms: tuple[int, ...], arm_length: float) -> _JunctionLanes:
    """Inbound and outbound lanes of every arm and the connectors across the box (through
    from both lanes, left turn from the inner lane, right turn from the outer lane, where the
    target arm exists)."""
    w, n_lanes = LANE_WIDTH, JUNCTION_LANES
    points: list[np.ndarray] = []
    approach: list[int] = []
    connector: list[bool] = []
    exits: dict[int, list[int]] = {}
    left: dict[int, list[int]] = {}
    right: dict[int, list[int]] = {}
    turn: dict[int, int] = {}

    def add(pts: np.ndarray, arm: int, is_conn: bool) -> int:
        points.append(pts)
        approach.append(arm)
        connector.append(is_conn)
        return len(points) - 1

    inbound = {k: [0] * n_lanes for k in arms}
    outbound = {k: [0] * n_lanes for k in arms}
    for k in arms:
        u, r = _axes(k)
        for i in range(n_lanes):
            lat = (i + 0.5) * w
            inbound[k][i] = add(line(arm_length * u + lat * r, STOP_LINE_M * u + lat * r), k, False)
            outbound[k][i] = add(
                line(STOP_LINE_M * u - lat * r, arm_length * u - lat * r), -1, False
            )
        for lanes in (inbound[k], outbound[k]):
            for i in range(n_lanes - 1):
                right[lanes[i]] = [lanes[i + 1]]
                left[lanes[i + 1]] = [lanes[i]]
    for k in arms:
        th_in = k * np.pi / 2 + np.pi
        moves = [(i, (k + 2) % 4, i, 0) for i in range(n_lanes)]
        moves += [(0, (k + 3) % 4, 0, 1), (n_lanes - 1, (k + 1) % 4, n_lanes - 1, -1)]
        for i, k_out, j, kind in moves:
            if k_out not in arms:
                continue
            a, b = points[inbound[k][i]][-1], points[outbound[k_out][j]][0]
            conn = add(bezier(a, th_in, b, k_out * np.pi / 2), k, True)
            turn[conn] = kind
            exits.setdefault(inbound[k][i], []).append(conn)
            exits[conn] = [outbound[k_out][j]]
    lanes = _link(points, exits, left, right, approach, connector)
    return _JunctionLanes(lanes=lanes, inbound=inbound, exits=exits, turn=turn)


def _arm_markings(k: int, arm_length: float) -> tuple[list, list, list]:
    """(road lines, their types, sidewalks) along arm k: the double yellow centre line, the
    broken white lane lines, and a walking line beyond each road edge."""
    u, r = _axes(k)
    half = JUNCTION_LANES * LANE_WIDTH
    lines, types, sidewalks = [line(STOP_LINE_M * u, arm_length * u)], [], []
    types.append(RoadLineType.SOLID_DOUBLE_YELLOW)
    for side in (1.0, -1.0):
        for i in range(1, JUNCTION_LANES):
            lat = side * i * LANE_WIDTH * r
            lines.append(line(STOP_LINE_M * u + lat, arm_length * u + lat))
            types.append(RoadLineType.BROKEN_SINGLE_WHITE)
        walk = side * (half + SIDEWALK_KERB_M) * r
        sidewalks.append(line((STOP_LINE_M + SIDEWALK_START_M) * u + walk, arm_length * u + walk))
    return lines, types, sidewalks


def _arm_crossing(k: int, arm_length: float) -> tuple[np.ndarray, Crossing]:
    """The crosswalk polygon [4, 2] across arm k and the pedestrians' crossing on it."""
    u, r = _axes(k)
    half = JUNCTION_LANES * LANE_WIDTH
    c0, c1 = CROSSWALK_M
    polygon = np.stack([c0 * u - half * r, c1 * u - half * r, c1 * u + half * r, c0 * u + half * r])
    mid = 0.5 * (c0 + c1)
    crossing = Crossing(
        arm=k,
        centre=mid * u,
        along=u,
        axis=r,
        kerb=half + 2.3,
        walk=half + 4.3,
        bend=STOP_LINE_M + 2.0 - mid,
        reach=arm_length - mid,
        offset=(0.15, 0.25 * (c1 - c0)),
    )
    return polygon, crossing


def _kerb(k: int, arms: tuple[int, ...], arm_length: float) -> np.ndarray:
    """The road edge between arm k and arm k+1 (road on its left): along arm k, round the
    corner, out along arm k+1; or straight on to arm k+2 when arm k+1 is missing."""
    u, _ = _axes(k)
    b, _ = _axes(k + 1)
    half, stop = JUNCTION_LANES * LANE_WIDTH, STOP_LINE_M
    if (k + 1) % 4 not in arms:
        return line(arm_length * u + half * b, -arm_length * u + half * b)
    a0 = np.arctan2(-b[1], -b[0])
    arc = circle_arc(stop * u + stop * b, stop - half, a0, a0 - np.pi / 2)
    return np.concatenate(
        [
            line(arm_length * u + half * b, stop * u + half * b)[:-1],
            arc,
            line(half * u + stop * b, half * u + arm_length * b)[1:],
        ]
    )


def _junction_control(
    control: str, arms: tuple[int, ...], graph: _JunctionLanes
) -> tuple[SignalPlan | None, JunctionControl | None, tuple[StopSign, ...]]:
    """(signal plan, right-of-way rules, stop signs) of the junction's control scheme."""
    n_lanes = JUNCTION_LANES
    inbound_ids = tuple(graph.inbound[k][i] + 1 for k in arms for i in range(n_lanes))
    if control == "signal":
        phase = tuple(p for p, _ in enumerate(arms) for _ in range(n_lanes))
        plan = SignalPlan(inbound_ids, phase, num_phases=len(arms), **SPLIT_PHASES)
        return plan, None, ()
    if control == "signal_permissive":
        phase = tuple(k % 2 for k in arms for _ in range(n_lanes))
        plan = SignalPlan(inbound_ids, phase, num_phases=2, **PERMISSIVE_PHASES)
        # Every approach has right of way on its green; left turns rank below the oncoming
        # through and right turns they cross.
        rank = {c + 1: 1 if graph.turn[c] == 1 else 0 for c in graph.turn}
        priority = (PRIORITY,) * len(inbound_ids)
        return plan, JunctionControl(lane_ids=inbound_ids, kind=priority, rank=rank), ()
    if control not in ("all_stop", "minor_stop"):
        raise ValueError(f"unknown junction control {control!r}")
    kinds: list[int] = []
    rank: dict[int, int] = {}
    signs: list[StopSign] = []
    half = n_lanes * LANE_WIDTH
    for k in arms:
        minor = control == "all_stop" or (k + 2) % 4 not in arms
        kinds += [STOP if minor else PRIORITY] * n_lanes
        if minor:
            u, r = _axes(k)
            pos = (STOP_LINE_M + 1.0) * u + (half + 1.0) * r
            signs.append(StopSign(pos, tuple(graph.inbound[k][i] + 1 for i in range(n_lanes))))
        for i in range(n_lanes):
            for c in graph.exits[graph.inbound[k][i]]:
                rank[c + 1] = 2 if minor else (1 if graph.turn[c] == 1 else 0)
    junction = JunctionControl(lane_ids=inbound_ids, kind=tuple(kinds), rank=rank)
    return None, junction, tuple(signs)


def _build_junction(
    layout: str, arms: tuple[int, ...], control: str, arm_length: float
) -> RoadNetwork:
    """Junction of 2-lane-per-direction roads on the given arms (shared by the 4-way layouts
    and the T-junction).

    Arm k points along polar angle k*pi/2 (east, north, west, south). Inbound lanes end at the
    stop line ``STOP_LINE_M`` from the centre; connector lanes (``_junction_lanes``) cross the
    box.

    Args:
        layout: layout name.
        arms: the present arms, a subset of (0, 1, 2, 3) in increasing order; a missing arm
            must have both neighbours present.
        control: "signal" (split phasing, one arm at a time), "signal_permissive" (two
            phases, opposite arms together; left turns yield to oncoming through and
            right-turning traffic on the green), "all_stop" (stop sign on every arm) or
            "minor_stop" (stop sign on arms whose opposite arm is missing; the through road
            has priority and its left turns yield to oncoming traffic).
        arm_length: distance from the centre to the map border along each arm, metres.
    """
    graph = _junction_lanes(arms, arm_length)
    plan, junction, stop_signs = _junction_control(control, arms, graph)
    road_lines, line_types, sidewalks, crosswalks, crossings = [], [], [], [], []
    for k in arms:
        lines, types, walks = _arm_markings(k, arm_length)
        road_lines += lines
        line_types += types
        sidewalks += walks
        polygon, crossing = _arm_crossing(k, arm_length)
        crosswalks.append(polygon)
        crossings.append(crossing)
    return RoadNetwork(
        layout=layout,
        lane_type=LaneType.SURFACE_STREET,
        speed_limit_mph=SPEED_LIMIT_MPH["signal" if control.startswith("signal") else "stop"],
        lanes=graph.lanes,
        road_lines=tuple(road_lines),
        road_line_types=tuple(line_types),
        road_edges=tuple(_kerb(k, arms, arm_length) for k in arms),
        crosswalks=tuple(crosswalks),
        sidewalks=tuple(sidewalks),
        signals=plan,
        merges=(),
        half_extent=arm_length,
        junction=junction,
        stop_signs=stop_signs,
        crossings=tuple(crossings),
    )


def build_intersection(arm_length: float = 100.0) -> RoadNetwork:
    """Signalised 4-way intersection of two roads with 2 lanes per direction.

    Signals use split phasing (one arm at a time), so turning movements of different arms
    never run together. See ``_build_junction`` for the geometry.

    Args:
        arm_length: distance from the centre to the map border along each arm, metres.
    """
    return _build_junction("intersection", (0, 1, 2, 3), "signal", arm_length)


def build_permissive_intersection(arm_length: float = 100.0) -> RoadNetwork:
    """Signalised 4-way intersection with two-phase signals and permissive left turns.

    Opposite arms share a green; a left-turning vehicle waits at its line, at a green light,
    for a gap in the oncoming through and right-turning traffic (the driver's accepted
    time gap), and the vehicles queued behind it in the inner lane wait with it. Turning
    vehicles also yield to pedestrians crossing on the walk phase. Same geometry as
    ``build_intersection``.

    Args:
        arm_length: distance from the centre to the map border along each arm, metres.
    """
    return _build_junction("permissive_intersection", (0, 1, 2, 3), "signal_permissive", arm_length)


def build_stop_intersection(arm_length: float = 100.0) -> RoadNetwork:
    """All-way stop-controlled 4-way intersection (stop sign on every arm).

    Vehicles stop fully at the line, then cross first come first served when no conflicting
    movement holds the box.

    Args:
        arm_length: distance from the centre to the map border along each arm, metres.
    """
    return _build_junction("stop_intersection", (0, 1, 2, 3), "all_stop", arm_length)


def build_t_junction(arm_length: float = 100.0) -> RoadNetwork:
    """T-junction: an east-west major road and a minor road from the south with a stop sign.

    The minor road turns left (across both major directions) or right; it stops and then
    yields to major traffic. Major left turns into the minor road yield to oncoming traffic.

    Args:
        arm_length: distance from the centre to the map border along each arm, metres.
    """
    return _build_junction("t_junction", (0, 2, 3), "minor_stop", arm_length)


def connector_conflicts(net: RoadNetwork, clearance: float = 3.0) -> np.ndarray:
    """Which connector lanes may not be used at the same time.

    Two connectors conflict when their centre lines come closer than ``clearance`` (wide
    enough for two of the widest vehicles side by side) and they do not start on the same
    inbound lane (vehicles there are ordered by car following).

    Args:
        net: road network.
        clearance: smallest centre-line distance of two connectors used together, metres.

    Returns:
        [L + 1, L + 1] bool, indexed by lane id (row and column 0 unused).
    """
    from shapely.geometry import LineString

    n = len(net.lanes) + 1
    out = np.zeros((n, n), bool)
    conns = [ln for ln in net.lanes if ln.is_connector]
    geoms = {ln.id: LineString(ln.points) for ln in conns}
    for a in conns:
        for b in conns:
            if a.id >= b.id or set(a.entry) & set(b.entry):
                continue
            if geoms[a.id].distance(geoms[b.id]) < clearance:
                out[a.id, b.id] = out[b.id, a.id] = True
    return out


def _ease(t: np.ndarray) -> np.ndarray:
    """Cosine ease from 0 to 1 on t in [0, 1] (zero slope at both ends)."""
    return 0.5 - 0.5 * np.cos(np.pi * np.clip(t, 0.0, 1.0))


def build_merge(half_length: float = 120.0) -> RoadNetwork:
    """Two-lane one-way freeway carriageway with an on-ramp merging into the right lane.

    The ramp comes in from the lower left, runs beside the right lane as an acceleration lane
    (x in [-40, 0]), then tapers into it over 60 m and ends at x = 60, where the right main
    lane is split so that both the ramp and the upstream right lane exit into the same lane.

    Args:
        half_length: the carriageway runs from -half_length to +half_length along x, metres.
    """
    w = LANE_WIDTH
    x_par, x_taper, x_merge = -40.0, 0.0, 60.0
    y_inner, y_outer, y_ramp0 = 0.0, -w, -25.0
    xs = np.linspace(-half_length, x_merge, 4000)
    approach_t = (xs + half_length) / (x_par + half_length)
    y = y_ramp0 + (y_outer - w - y_ramp0) * _ease(approach_t)
    y = y + w * _ease((xs - x_taper) / (x_merge - x_taper))
    ramp_dense = np.stack([xs, y], axis=1)
    ramp = resample(ramp_dense)

    points = [
        line([-half_length, y_inner], [half_length, y_inner]),
        line([-half_length, y_outer], [x_merge, y_outer]),
        line([x_merge, y_outer], [half_length, y_outer]),
        ramp,
    ]
    inner, up, down, rmp = 0, 1, 2, 3
    exits = {up: [down], rmp: [down]}
    left = {up: [inner], down: [inner], rmp: [up]}
    right = {inner: [up, down], up: [rmp]}
    lanes = _link(points, exits, left, right, [-1] * 4, [False] * 4)
    touching = np.abs(ramp[:, 1] - y_outer) < 2.6
    seg = np.linalg.norm(np.diff(ramp, axis=0), axis=1)
    conflict_s = float(np.concatenate([[0.0], np.cumsum(seg)])[np.argmax(touching)])

    half_w = 0.5 * w
    top = line([half_length, y_inner + half_w], [-half_length, y_inner + half_w])
    gore_pts = ramp_dense[ramp_dense[:, 0] <= x_par]
    gore = np.concatenate(
        [
            line([-half_length, y_outer - half_w], [x_par, y_outer - half_w])[:-1],
            resample(offset(gore_pts, half_w)[::-1]),
        ]
    )
    bottom = np.concatenate(
        [
            resample(offset(ramp_dense, -half_w)),
            line([x_merge, y_outer - half_w], [half_length, y_outer - half_w])[1:],
        ]
    )
    road_lines = (
        line([-half_length, y_inner - half_w], [half_length, y_inner - half_w]),
        line([x_par, y_outer - half_w], [x_taper, y_outer - half_w]),
    )
    return RoadNetwork(
        layout="merge",
        lane_type=LaneType.FREEWAY,
        speed_limit_mph=45.0,
        lanes=lanes,
        road_lines=road_lines,
        road_line_types=(RoadLineType.BROKEN_SINGLE_WHITE, RoadLineType.BROKEN_SINGLE_WHITE),
        road_edges=(top, gore, bottom),
        crosswalks=(),
        sidewalks=(),
        signals=None,
        merges=(Merge(priority_lane=up + 1, yield_lane=rmp + 1, conflict_s=conflict_s),),
        half_extent=half_length,
    )


def to_road_map(net: RoadNetwork) -> RoadMap:
    """Convert a generated network into the WOMD-like ``RoadMap`` (z = 0 everywhere).

    Lanes keep their ids (1..L); road lines, road edges and crosswalks follow in that order.
    """
    polylines: list[np.ndarray] = []
    ftype: list[int] = []
    subtype: list[int] = []
    speed: list[float] = []
    entry: list[np.ndarray] = []
    exit_: list[np.ndarray] = []
    lefts: list[np.ndarray] = []
    rights: list[np.ndarray] = []

    def ids(x: tuple[int, ...]) -> np.ndarray:
        return np.asarray(x, np.int64)

    def add(pts: np.ndarray, kind: MapFeatureType, sub: int, lane: Lane | None = None) -> None:
        polylines.append(np.concatenate([pts, np.zeros((len(pts), 1))], axis=1))
        ftype.append(int(kind))
        subtype.append(sub)
        speed.append(net.speed_limit_mph if lane is not None else 0.0)
        entry.append(ids(lane.entry) if lane else ids(()))
        exit_.append(ids(lane.exit) if lane else ids(()))
        lefts.append(ids(lane.left) if lane else ids(()))
        rights.append(ids(lane.right) if lane else ids(()))

    for ln in net.lanes:
        add(ln.points, MapFeatureType.LANE, int(net.lane_type), ln)
    for pts, kind in zip(net.road_lines, net.road_line_types):
        add(pts, MapFeatureType.ROAD_LINE, int(kind))
    for pts in net.road_edges:
        add(pts, MapFeatureType.ROAD_EDGE, int(RoadEdgeType.BOUNDARY))
    for pts in net.crosswalks:
        add(pts, MapFeatureType.CROSSWALK, 0)
    controlled = [ids(()) for _ in polylines]
    for sign in net.stop_signs:
        add(sign.position[None, :], MapFeatureType.STOP_SIGN, 0)
        controlled.append(ids(sign.lanes))
    n = len(polylines)
    return RoadMap(
        id=np.arange(1, n + 1, dtype=np.int64),
        feature_type=np.asarray(ftype, np.int8),
        subtype=np.asarray(subtype, np.int8),
        polylines=tuple(polylines),
        speed_limit_mph=np.asarray(speed, np.float32),
        entry_lanes=tuple(entry),
        exit_lanes=tuple(exit_),
        left_neighbors=tuple(lefts),
        right_neighbors=tuple(rights),
        controlled_lanes=tuple(controlled),
    )


LAYOUT_BUILDERS = {
    "intersection": build_intersection,
    "merge": build_merge,
    "stop_intersection": build_stop_intersection,
    "t_junction": build_t_junction,
    "permissive_intersection": build_permissive_intersection,
}
"""Layout name -> builder of its ``RoadNetwork``."""
