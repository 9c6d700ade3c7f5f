"""The ``idm`` policy (issue 40): behaviour on small hand-made scenes (free road, a stopped
leader, a red light turning green, a stop sign, a crosswalk with and without a pedestrian, a
cut-in by a controlled agent, a fork), every real format of the shared data, road keeping on
the real samples, refused parameters, frame invariance, and lane links inferred from geometry
against the protos' own."""

from __future__ import annotations

import dataclasses
import glob
import warnings

import numpy as np
import pytest
import torch

from policies import make_policy, make_rollout_fn
from policies.idm import IDMConfig, IDMPolicy
from policies.idm.lanes import infer_successors, lane_graph, match_lanes
from policies.idm.params import (
    HEADWAY_RELAX_TIME,
    LANE_MATCH_COS,
    LANE_MATCH_DISTANCE,
    LEADER_PERIOD,
)
from policies.idm.routes import LOG_POINT_SPACING, thin
from tbsim_env.cli import app as cli
from tbsim_env.core.config import EnvConfig, TerminationConfig
from tbsim_env.core.constants import DT, MapFeatureType, ObjectType, SignalState
from tbsim_env.data.generator import generate_scenario
from tbsim_env.data.loader import load_scenarios
from tbsim_env.data.scenario import RoadMap, Scenario, Tracks, TrafficSignals, wrap_angle_np
from tbsim_env.env import BatchedTrafficEnv, TrafficEnv
from tbsim_env.metrics.wosac.rollouts import log_replay_rollouts
from tbsim_env.metrics.wosac.scoring import simulated_road_departure
from tbsim_env.metrics.wosac.simulate import simulate_rollouts
from tbsim_env.sim import core
from tbsim_env.sim.build import build_sim_state
from tbsim_env.sim.collision import pairwise_overlap

pytestmark = pytest.mark.usefixtures("torch_one_thread")

STEPS, NOW = 91, 10
CAR = (4.5, 2.0)
MPH_10_MPS = 10.0 / 0.44704


# ----------------------------------------------------------------------------- scenes
def line(*corners: tuple[float, float], spacing: float = 0.5) -> np.ndarray:
    """[n, 2] a polyline through the corners, points ``spacing`` apart."""
    pts = [np.array(corners[0], float)]
    for a, b in zip(corners[:-1], corners[1:]):
        a, b = np.array(a, float), np.array(b, float)
        k = max(int(np.ceil(np.linalg.norm(b - a) / spacing)), 1)
        pts += [a + (b - a) * (i / k) for i in range(1, k + 1)]
    return np.stack(pts)


def arc(centre: tuple[float, float], radius: float, a0: float, a1: float) -> np.ndarray:
    """[n, 2] points of a circular arc from angle ``a0`` to ``a1`` (rad), ~0.5 m apart."""
    k = max(int(abs(a1 - a0) * radius / 0.5), 2)
    t = np.linspace(a0, a1, k + 1)
    return np.stack([centre[0] + radius * np.cos(t), centre[1] + radius * np.sin(t)], -1)


def road_map(lanes: dict, signs: tuple = (), crosswalks: tuple = ()) -> RoadMap:
    """A map of lanes {id: (polyline [n, 2], exit ids)} (10 m/s limits), stop signs
    ((id, xy, controlled lane ids), ...), crosswalks ((id, outline [n, 2]), ...) and road
    edges 6 m beside the lanes' box."""
    ids, kinds, polys, exits, ctrl = [], [], [], [], []
    for k, (poly, out) in lanes.items():
        ids.append(k), kinds.append(MapFeatureType.LANE), polys.append(poly)
        exits.append(np.array(out, np.int64)), ctrl.append(np.zeros(0, np.int64))
    for k, xy, controlled in signs:
        ids.append(k), kinds.append(MapFeatureType.STOP_SIGN), polys.append(np.array([xy], float))
        exits.append(np.zeros(0, np.int64)), ctrl.append(np.array(controlled, np.int64))
    for k, outline in crosswalks:
        ids.append(k), kinds.append(MapFeatureType.CROSSWALK), polys.append(np.asarray(outline))
        exits.append(np.zeros(0, np.int64)), ctrl.append(np.zeros(0, np.int64))
    allxy = np.concatenate([p for p in polys])
    lo, hi = allxy.min(0) - 6.0, allxy.max(0) + 6.0
    box = [(lo[0], lo[1]), (hi[0], lo[1]), (hi[0], hi[1]), (lo[0], hi[1]), (lo[0], lo[1])]
    ids.append(9000), kinds.append(MapFeatureType.ROAD_EDGE), polys.append(line(*box, spacing=5))
    exits.append(np.zeros(0, np.int64)), ctrl.append(np.zeros(0, np.int64))
    f = len(ids)
    entries = [
        np.array([i for i, (_, out) in lanes.items() if k in out], np.int64)
        if kind == MapFeatureType.LANE
        else np.zeros(0, np.int64)
        for k, kind in zip(ids, kinds)
    ]
    empty = tuple(np.zeros(0, np.int64) for _ in range(f))
    return RoadMap(
        id=np.array(ids, np.int64),
        feature_type=np.array(kinds, np.int8),
        subtype=np.zeros(f, np.int8),
        polylines=tuple(np.concatenate([p, np.zeros((len(p), 1))], 1) for p in polys),
        speed_limit_mph=np.where(np.array(kinds) == MapFeatureType.LANE, MPH_10_MPS, 0.0).astype(
            np.float32
        ),
        entry_lanes=tuple(entries),
        exit_lanes=tuple(exits),
        left_neighbors=empty,
        right_neighbors=empty,
        controlled_lanes=tuple(ctrl),
    )


def along(path: np.ndarray, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Positions [T, 2] and headings [T] at arc lengths ``s`` [T] of a polyline."""
    cum = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))])
    xy = np.stack([np.interp(s, cum, path[:, 0]), np.interp(s, cum, path[:, 1])], -1)
    seg = np.clip(np.searchsorted(cum, s, side="right") - 1, 0, len(path) - 2)
    d = path[seg + 1] - path[seg]
    return xy, np.arctan2(d[:, 1], d[:, 0])


def scene(
    agents: list[tuple], lanes: dict, signs: tuple = (), signals=None, crosswalks: tuple = ()
) -> Scenario:
    """A validated scene of agents (path [n, 2], arc along it at the current step m, speed
    m/s) moving at constant speed along their paths over all 91 steps; track ids 100 + row."""
    s = [a[1] + a[2] * DT * (np.arange(STEPS) - NOW) for a in agents]
    poses = [along(a[0], si) for a, si in zip(agents, s)]
    heading = np.stack([p[1] for p in poses])
    unit = np.stack([np.cos(heading), np.sin(heading)], -1)  # [N, T, 2]
    velocity = np.array([a[2] for a in agents], float)[:, None, None] * unit
    n = len(agents)
    tracks = Tracks(
        id=np.arange(100, 100 + n, dtype=np.int64),
        object_type=np.full(n, int(ObjectType.VEHICLE), np.int8),
        xyz=np.concatenate([np.stack([p[0] for p in poses]), np.zeros((n, STEPS, 1))], -1),
        heading=wrap_angle_np(heading).astype(np.float32),
        velocity=velocity.astype(np.float32),
        size=np.broadcast_to(np.array([*CAR, 1.6], np.float32), (n, STEPS, 3)).copy(),
        valid=np.ones((n, STEPS), bool),
    )
    return Scenario(
        scenario_id="idm-test",
        timestamps=np.arange(STEPS) * DT,
        current_index=NOW,
        tracks=tracks,
        road_map=road_map(lanes, signs, crosswalks),
        signals=signals if signals is not None else TrafficSignals.empty(STEPS),
        sdc_index=0,
        tracks_to_predict=np.zeros(0, np.int64),
        predict_difficulty=np.zeros(0, np.int8),
        objects_of_interest=np.zeros(0, np.int64),
    ).validate()


def drive(sc: Scenario, steps: int, policy=None, replayed=(), external=None) -> dict:
    """Run ``policy`` (default: IDM, no per-agent spread) on every agent of ``sc`` but the
    ``replayed`` rows (they follow the log) and those ``external(t, state)`` returns actions
    for ({row: action [2]}). Returns pose [S, N, 3] (scenario frame), speed [S, N], action
    [S, N, 2]."""
    policy = policy or IDMPolicy(speed_spread=0.0, headway_spread=0.0)
    state = build_sim_state([sc], start_step=NOW)
    controlled = state.valid.clone()
    controlled[0, list(replayed)] = False
    state = state.replace(controlled=controlled)
    gen = torch.Generator().manual_seed(0)
    ps = policy.initial_state(state, [sc], gen)
    out = {"pose": [state.pose[0]], "speed": [state.speed[0]], "action": []}
    with torch.inference_mode():
        for t in range(steps):
            action, ps = policy.act(state, ps, gen)
            for row, act in (external(t, state) if external else {}).items():
                action[0, row] = torch.as_tensor(act, dtype=action.dtype)
            state = core.step(state, action)
            out["pose"].append(state.pose[0]), out["speed"].append(state.speed[0])
            out["action"].append(action[0])
    out = {k: torch.stack(v).double().numpy() for k, v in out.items()}
    out["pose"][..., :2] += state.origin[0].numpy()
    return out


def overlaps(pose: np.ndarray) -> np.ndarray:
    """[S] bool: two of the cars overlap at each step."""
    p = torch.from_numpy(pose)
    size = torch.tensor(CAR).expand(p.shape[1], 2)
    hit = pairwise_overlap(p, size.expand(p.shape[0], -1, -1), p, size.expand(p.shape[0], -1, -1))
    hit = hit & ~torch.eye(p.shape[1], dtype=torch.bool)
    return hit.flatten(1).any(-1).numpy()


STRAIGHT = {1: (line((-150.0, 0.0), (400.0, 0.0)), [])}
APPROACH = line((-150.0, 0.0), (0.0, 0.0))
JUNCTION = {
    1: (APPROACH, [2]),
    2: (line((0.0, 0.0), (30.0, 0.0)), [3]),
    3: (line((30.0, 0.0), (300.0, 0.0)), []),
}
EAST = line((-150.0, 0.0), (300.0, 0.0))


# ----------------------------------------------------------------------------- behaviour
def test_free_road_reaches_the_desired_speed_without_overshoot():
    sc = scene([(EAST, 0.0, 5.0)], STRAIGHT)  # lane limit 10 m/s, history 5 m/s
    speed = drive(sc, 250)["speed"][:, 0]
    assert speed.max() <= 10.0 + 0.5
    assert abs(speed[-1] - 10.0) < 0.5


def test_a_log_that_ends_off_the_lane_centre_joins_its_lane_without_a_kink():
    # The logged path runs 0.4 m beside the lane's centre line; past the log's end the route
    # follows the lane. Joined directly, the 0.4 m step is a bend whose curvature caps the
    # speed near 6 m/s, and a fast car brakes for it from the start.
    beside = line((-150.0, 0.4), (400.0, 0.4))
    sc = scene([(beside, 0.0, 25.0)], STRAIGHT)
    plan = IDMPolicy(speed_spread=0.0, headway_spread=0.0).plan(sc, NOW, 0, None)
    assert plan.speed_cap[0].min() >= 25.0
    points = plan.routes.points[0]
    assert (
        abs(points[0, 1] - 0.4) < 1e-6 and abs(points[-1, 1]) < 1e-6
    )  # from the log onto the lane
    speed = drive(sc, STEPS - 1 - NOW)["speed"][:, 0]
    assert np.abs(speed - 25.0).max() < 0.5


def test_centimetres_of_jitter_in_a_straight_log_do_not_cap_a_fast_cars_speed():
    x = np.arange(-150.0, 400.0, 3.0)  # a position every 0.1 s at 30 m/s
    jittery = np.stack([x, 0.03 * (-1.0) ** np.arange(len(x))], -1)
    sc = scene([(jittery, 0.0, 30.0)], STRAIGHT)
    plan = IDMPolicy(speed_spread=0.0, headway_spread=0.0).plan(sc, NOW, 0, None)
    assert plan.speed_cap[0].min() >= 30.0
    bend = scene(
        [
            (
                np.concatenate(
                    [line((-40.0, 0.0), (0.0, 0.0)), arc((0.0, 20.0), 20.0, -np.pi / 2, 0.0)]
                ),
                0.0,
                10.0,
            )
        ],
        STRAIGHT,
    )
    cap = IDMPolicy(speed_spread=0.0, headway_spread=0.0).plan(bend, NOW, 0, None).speed_cap[0]
    assert cap.min() == pytest.approx(np.sqrt(IDMConfig().lateral_accel * 20.0), rel=0.15)


def test_a_car_that_follows_closely_at_the_start_keeps_its_gap_instead_of_braking():
    # 15 m/s, 10.5 m behind a leader at 15 m/s (0.7 s): the IDM's 1 s headway would have it
    # brake hard at once; its headway is lowered to what the gap allows (0.3 s at least),
    # and the cut shrinks back with time constant HEADWAY_RELAX_TIME.
    sc = scene([(EAST, 0.0, 15.0), (EAST, 15.0, 15.0)], STRAIGHT)
    fitted = IDMPolicy(speed_spread=0.0, headway_spread=0.0)
    kept = IDMPolicy(speed_spread=0.0, headway_spread=0.0, min_headway=1.0)
    state = build_sim_state([sc], start_step=NOW)
    ps = fitted.initial_state(state, [sc], torch.Generator())
    assert torch.isnan(ps.headway_cut[0, 0])  # fixed by the first leader search
    _, ps = fitted.act(state, ps, torch.Generator())
    relax = np.exp(-0.1 / HEADWAY_RELAX_TIME)  # a step's shrink, after the act
    expected = (IDMConfig().vehicle.time_headway - 0.3) * relax
    assert ps.headway_cut[0].tolist() == pytest.approx([expected, 0], rel=1e-5)
    cut = ps.headway_cut[0, 0].item()
    for _ in range(40):  # 4 s
        _, ps = fitted.act(state, ps, torch.Generator())
    assert ps.headway_cut[0, 0].item() == pytest.approx(
        cut * np.exp(-4.0 / HEADWAY_RELAX_TIME), rel=1e-4
    )
    first = drive(sc, 1, policy=fitted)["action"][0, 0, 0]
    assert -1.0 < first < 0.0  # mild: the free-road term is spent at the desired speed
    assert drive(sc, 1, policy=kept)["action"][0, 0, 0] < -3.0
    out = drive(sc, STEPS - 1 - NOW, policy=fitted)
    assert out["speed"][:, 0].min() > 12.0 and not overlaps(out["pose"]).any()


def test_stops_behind_a_stopped_leader_at_the_standstill_gap():
    sc = scene([(EAST, 0.0, 10.0), (EAST, 70.0, 0.0)], STRAIGHT)
    out = drive(sc, 250)
    gap = out["pose"][-1, 1, 0] - out["pose"][-1, 0, 0] - CAR[0]
    assert abs(gap - IDMConfig().vehicle.standstill_gap) <= 0.5
    assert out["speed"][-1, 0] < 0.1 and not overlaps(out["pose"]).any()
    assert abs(out["pose"][-1, 1, 0] - (-80.0)) < 1e-3  # the standing car stays (arc 70)


def test_stops_at_a_red_light_and_goes_on_green():
    state = np.where(np.arange(STEPS) < 85, int(SignalState.STOP), int(SignalState.GO))
    signals = TrafficSignals(
        lane_id=np.array([2], np.int64),
        state=state[None].astype(np.int8),
        valid=np.ones((1, STEPS), bool),
        stop_point=np.zeros((1, 3)),
    )
    sc = scene([(EAST, 120.0, 8.0)], JUNCTION, signals=signals)  # 30 m before the line
    out = drive(sc, 110)  # index k: the state at step 10 + k (the last signal state holds)
    front = out["pose"][:, 0, 0] + 0.5 * CAR[0]
    red = slice(0, 85 - NOW + 1)
    assert front[red].max() < 0.0 and front[red][-1] > -4.0  # stopped just before the line
    assert out["speed"][red][-1, 0] < 0.5
    assert front[-1] > 1.0  # through on green


def test_stops_fully_at_a_stop_sign_then_goes():
    sc = scene([(EAST, 100.0, 8.0)], JUNCTION, signs=((500, (-1.0, -3.0), [2]),))
    out = drive(sc, 130)  # past the log's end (step 90): the search cadence goes on
    front, speed = out["pose"][:, 0, 0] + 0.5 * CAR[0], out["speed"][:, 0]
    at_line = (front > -3.0) & (front < 0.0)
    assert (speed[at_line] < 0.5).any()  # a full stop at the line
    first_past = int(np.argmax(front > 0.0))
    assert front[-1] > 5.0 and (speed[:first_past] < 0.5).any()


def test_brakes_for_a_controlled_agent_cutting_in():
    lanes = {1: (line((-150.0, 0.0), (400.0, 0.0)), []), 2: (line((-150.0, 3.5), (400.0, 3.5)), [])}
    left = line((-150.0, 3.5), (400.0, 3.5))
    sc = scene([(EAST, 0.0, 10.0), (left, 15.0, 7.0)], lanes)  # the cutter starts 15 m ahead

    def cut_in(t: int, state) -> dict:
        yaw_rate = -0.5 if 5 <= t < 15 else 0.5 if 15 <= t < 25 else 0.0
        return {1: (0.0, yaw_rate)}

    out = drive(sc, 60, external=cut_in)
    assert abs(out["pose"][-1, 1, 1]) < 0.5  # the cut-in happened (now in the follower's lane)
    assert out["action"][:, 0, 0].min() < -1.0  # the follower braked for it
    assert not overlaps(out["pose"]).any()


def test_yields_to_fast_crossing_traffic_between_sample_times():
    """A slow car 8 m before a crossing, a log-replayed car at 18 m/s 30 m away on the
    crossing road: the slow car yields (the fast car's boxes 1 s and 2 s ahead lie on either
    side of the corridor; its path between them does not)."""
    north = line((0.0, -150.0), (0.0, 150.0))
    lanes = {1: (EAST, []), 2: (north, [])}
    sc = scene([(EAST, 142.0, 3.0), (north, 120.0, 18.0)], lanes)
    out = drive(sc, 60, replayed=(1,))
    assert out["action"][:20, 0, 0].min() < -0.5  # it brakes for the crossing car
    assert not overlaps(out["pose"]).any()
    assert out["pose"][-1, 0, 0] > 5.0  # and crosses once it has passed


def test_a_slow_car_near_a_crossing_waits_until_it_can_clear_it():
    """A car creeping at 1 m/s, its front 0.5 m from where a log-replayed car at 12 m/s will
    pass in about 1.4 s: reaching the crossing first is not clearing it; it waits, then
    crosses."""
    north = line((0.0, -150.0), (0.0, 150.0))
    lanes = {1: (EAST, []), 2: (north, [])}
    sc = scene([(EAST, 146.25, 1.0), (north, 130.0, 12.0)], lanes)
    out = drive(sc, 60, replayed=(1,))
    assert not overlaps(out["pose"]).any()
    assert out["pose"][-1, 0, 0] > 3.0  # it crossed once the other had passed


def test_crosswalk_occupancy_is_the_point_in_polygon_test_of_every_walker():
    """Against shapely on random walkers around concave, convex and padding polygons: a
    walker inside a crosswalk's bounding box but outside its outline leaves it free."""
    from shapely.geometry import Point, Polygon

    from policies.idm.yielding import crosswalks_occupied

    rng = np.random.default_rng(0)
    ell = [(0, 0), (6, 0), (6, 2), (2, 2), (2, 6), (0, 6), (0, 0), (0, 0)]  # an L, concave
    quad = [(10, 10), (14, 11), (13, 15), (9, 14), (9, 14), (9, 14), (9, 14), (9, 14)]
    polygons = torch.zeros(2, 3, 8, 2)  # the last polygon of each row is padding
    polygons[0, 0], polygons[0, 1] = torch.tensor(ell), torch.tensor(quad)
    polygons[1, 0], polygons[1, 1] = torch.tensor(quad) - 5.0, torch.tensor(ell) + 3.0
    xy = torch.from_numpy(rng.uniform(-2.0, 16.0, (2, 200, 2))).float()
    xy[0, 0] = torch.tensor([4.0, 4.0])  # in the L's bounding box, outside the L
    shapes = [[Polygon(polygons[b, w].tolist()) for w in range(2)] for b in range(2)]
    # Every walker lies > 1 mm from every outline: float32 rounding cannot move it across.
    assert (
        min(
            p.exterior.distance(Point(*q))
            for b in range(2)
            for p in shapes[b]
            for q in xy[b].tolist()
        )
        > 1e-3
    )
    inside = 0
    for b, n in np.ndindex(2, 200):  # one walker at a time: its own crosswalks only
        got = crosswalks_occupied(polygons, (torch.tensor([b]), torch.tensor([n])), xy)
        want = [shapes[b][w].contains(Point(*xy[b, n].tolist())) for w in range(2)]
        assert got[b, :2].tolist() == want and not got[b, 2] and not got[1 - b].any()
        inside += sum(want)
    assert inside > 20
    everyone = crosswalks_occupied(polygons, torch.ones(2, 200).nonzero(as_tuple=True), xy)
    assert everyone[:, :2].all() and not everyone[:, 2].any()


@pytest.mark.parametrize("on_it", [True, False])
def test_stops_before_a_crosswalk_with_a_pedestrian_on_it_and_passes_an_empty_one(on_it):
    """A car at 10 m/s, 40 m before a crosswalk across its lane; a pedestrian stands on the
    crosswalk beside the car's corridor (never its leader), or 3 m beyond the crosswalk's
    end: the car stops before the crosswalk, or drives over it."""
    walk = np.array([[30.0, -6.0], [34.0, -6.0], [34.0, 6.0], [30.0, 6.0], [30.0, -6.0]])
    stand = line((32.0, 5.0 if on_it else 9.0), (32.0, 12.0))
    ped = int(ObjectType.PEDESTRIAN)
    sc = scene(
        [(STRAIGHT[1][0], 140.0 - 2.25, 10.0), (stand, 0.0, 0.0)],
        STRAIGHT,
        crosswalks=((500, walk),),
    )
    t = sc.tracks
    sizes = t.size.copy()
    sizes[1] = [0.6, 0.6, 1.7]
    t = dataclasses.replace(t, object_type=np.array([int(ObjectType.VEHICLE), ped], np.int8))
    sc = dataclasses.replace(sc, tracks=dataclasses.replace(t, size=sizes)).validate()
    out = drive(sc, 80)
    front = out["pose"][:, 0, 0] + 0.5 * CAR[0]
    if on_it:
        assert front.max() < 30.0  # never onto the crosswalk
        assert out["speed"][-1, 0] < 0.5 and front[-1] > 26.0  # stopped close to it
    else:
        assert out["pose"][-1, 0, 0] > 40.0


def _with_types(sc: Scenario, kinds: list[int]) -> Scenario:
    t = dataclasses.replace(sc.tracks, object_type=np.array(kinds, np.int8))
    t = dataclasses.replace(
        t, size=np.broadcast_to(np.float32([0.6, 0.6, 1.7]), t.size.shape).copy()
    )
    return dataclasses.replace(sc, tracks=t).validate()


@pytest.mark.parametrize("gaps", [False, True])
def test_pedestrians_in_a_group_keep_no_gaps_unless_asked(gaps):
    """Two pedestrians 0.7 m apart, the rear one faster: by default it walks on through the
    group (WOMD's groups overlap); with ``pedestrian_gaps`` it slows behind the other."""
    walk = {1: (EAST, [])}
    ped = int(ObjectType.PEDESTRIAN)
    sc = _with_types(scene([(EAST, 150.0, 1.8), (EAST, 150.7, 1.0)], walk), [ped, ped])
    policy = IDMPolicy(speed_spread=0.0, headway_spread=0.0, pedestrian_gaps=gaps)
    speed = drive(sc, 30, policy=policy)["speed"][:, 0]
    assert (speed.min() < 1.2) if gaps else (speed.min() > 1.7)


def _fork(turn: bool) -> Scenario:
    a = line((-150.0, 0.0), (0.0, 0.0))
    b = line((0.0, 0.0), (150.0, 0.0))
    c = arc((0.0, 20.0), 20.0, -np.pi / 2, 0.0)
    d = line((20.0, 20.0), (20.0, 150.0))
    lanes = {1: (a, [2, 3]), 2: (b, []), 3: (c, [4]), 4: (d, [])}
    path = np.concatenate([a, (c if turn else b)[1:], d[1:] if turn else np.zeros((0, 2))])
    return scene([(path, 120.0, 8.0)], lanes)


@pytest.mark.parametrize("turn", [True, False])
def test_a_fork_follows_the_branch_of_the_logged_future(turn):
    sc = _fork(turn)
    route = IDMPolicy(route="lanes").plan(sc, NOW).routes.points[0]
    taken = (20.0, 40.0) if turn else (60.0, 0.0)  # on the turn's exit lane / straight on
    assert np.hypot(*(route - taken).T).min() < 1.5  # route points are 2.5 m apart
    out = drive(sc, 80, policy=IDMPolicy(route="lanes", speed_spread=0.0))
    end = out["pose"][-1, 0, :2]
    assert (end[0] > 15.0 and end[1] > 10.0) if turn else (end[0] > 20.0 and abs(end[1]) < 1.0)


def test_bad_parameters_are_refused_with_one_clear_error():
    with pytest.raises(ValueError, match="time_headway must be finite and >= 0, got -1"):
        IDMPolicy(vehicle={"time_headway": -1.0})
    with pytest.raises(ValueError, match="max_decel must be finite and > 0, got 0"):
        make_policy("idm", pedestrian={"max_decel": 0.0})
    with pytest.raises(ValueError, match="route must be 'log' or 'lanes'"):
        make_policy("idm", route="wander")
    with pytest.raises(ValueError, match="unknown IDM setting"):
        IDMPolicy(headway=1.0)
    with pytest.raises(ValueError, match="speed_spread"):
        IDMConfig(speed_spread=1.5)
    with pytest.raises(ValueError, match="min_headway is out of range: -0.1"):
        IDMConfig(min_headway=-0.1)
    for period in (0, 1.5, float("inf"), float("nan")):
        with pytest.raises(ValueError, match="leader_period is out of range"):
            IDMConfig(leader_period=period)
    assert IDMConfig(leader_period=2.0).leader_period == 2


# ----------------------------------------------------------------------------- real data
REAL_FORMATS = (
    "waymo-open-dataset/motion_data_one_scenario.tfrecord",
    "waymo-open-dataset/motion_data_one_example.tfrecord",
    "scenarionet/sd_waymo_v1.2_eb4b91b10ca94ff2.pkl",
    "gpudrive/tfrecord-00000-of-01000_222.json",
    "nocturne/tfrecord-00754-of-01000_171.json",
    "gpudrive_history/gpudrive_early/tfrecord-00002-of-00150_9c52d259d258d6a3.json",
    "gpudrive_codec/tfrecord-00004-of-00150_308.json.gz",
)
"""One scene of every real format and JSON dialect of the shared data."""


def _load(path) -> Scenario:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_scenarios(path)[0]


@pytest.mark.parametrize("name", REAL_FORMATS)
def test_an_episode_with_idm_npcs_runs_on_every_real_format(womd_dir, name):
    never = EnvConfig(termination=TerminationConfig(collision=False, goal=False))
    env = TrafficEnv([_load(womd_dir / name)], npc_policy="idm", config=never)
    env.reset(seed=0)
    npc = env.episode.setup.npc[0]
    moved = torch.zeros_like(npc)
    steps = 0
    while env.agents:
        env.step(env.expert_actions())
        moved |= env.sim_state.speed[0].abs() > 1.0
        steps += 1
    assert steps == env.episode_steps and (moved & npc).any()


def test_no_idm_vehicle_leaves_the_road_on_the_real_samples(womd_dir):
    """Vehicles on the road at the current step stay on it in every rollout (route "log"),
    except where their own log leaves it."""
    files = [*sorted(glob.glob(str(womd_dir / "waymo-open-dataset" / "*.tfrecord")))]
    for folder in ("gpudrive", "nocturne", "scenarionet"):
        files += sorted(glob.glob(str(womd_dir / folder / "*")))
    policy = IDMPolicy()
    checked = 0
    for path in files:
        sc = _load(path).motion_window()
        vehicles = (sc.tracks.object_type == int(ObjectType.VEHICLE)) & sc.sim_agent_mask()
        rows = np.flatnonzero(vehicles)
        sc = sc.replace(tracks_to_predict=rows, predict_difficulty=np.zeros(len(rows), np.int8))
        left = simulated_road_departure(sc, simulate_rollouts(sc, policy, num_rollouts=1))
        if left.any():
            left &= ~simulated_road_departure(sc, log_replay_rollouts(sc, num_rollouts=1))
        assert not left.any(), (path, sc.tracks.id[rows][left[0]])
        checked += len(rows)
    assert len(files) == 10 and checked > 350


def test_lane_links_inferred_from_geometry_are_the_protos_own(womd_dir):
    for name in (
        "waymo-open-dataset/motion_data_one_scenario.tfrecord",
        "waymo-open-dataset/womd_scenario_input.tfrecord",
        "scenarionet/sd_waymo_v1.2_eb4b91b10ca94ff2.pkl",
    ):
        graph = lane_graph(_load(womd_dir / name).road_map)
        assert not graph.links_inferred
        proto = {(a, int(b)) for a, out in enumerate(graph.successors) for b in out}
        inferred = {
            (a, int(b)) for a, out in enumerate(infer_successors(graph.polylines)) for b in out
        }
        assert len(proto) > 80 and inferred == proto, name
    gpudrive = lane_graph(_load(womd_dir / REAL_FORMATS[3]).road_map)
    assert gpudrive.links_inferred and sum(len(s) for s in gpudrive.successors) > 20


@pytest.mark.float_sensitive  # an exact comparison of float geometry
def test_lane_matching_through_the_grid_equals_testing_every_segment(one_scenario_path):
    """``match_lanes`` reads only the segments listed in a position's grid cell: the lanes
    and arcs it finds are those of a test against every segment of the map."""
    graph = lane_graph(_load(one_scenario_path).road_map)
    rng = np.random.default_rng(0)
    e = rng.integers(0, len(graph.seg_start), 1500)
    xy = graph.seg_start[e] + rng.random((1500, 1)) * graph.seg_vec[e]
    xy += rng.normal(0.0, 1.5, (1500, 2))  # on, beside and beyond the match distance
    yaw = np.arctan2(graph.seg_vec[e, 1], graph.seg_vec[e, 0]) + rng.normal(0.0, 0.6, 1500)
    lane, arc = match_lanes(graph, xy, yaw)
    # Every segment: projection, distance, heading within 45 degrees, the first nearest.
    vec, start = graph.seg_vec[None], graph.seg_start[None]
    len2 = (vec**2).sum(-1)
    t = np.clip(((xy[:, None] - start) * vec).sum(-1) / len2, 0.0, 1.0)
    dist = np.linalg.norm(xy[:, None] - start - t[..., None] * vec, axis=-1)
    heading = np.stack([np.cos(yaw), np.sin(yaw)], -1)
    cos = (heading[:, None] * vec).sum(-1) / np.sqrt(len2)
    dist = np.where(cos >= LANE_MATCH_COS, dist, np.inf)
    best = dist.argmin(1)
    rows = np.arange(len(xy))
    ok = dist[rows, best] <= LANE_MATCH_DISTANCE
    assert 400 < ok.sum() < len(xy)  # both outcomes are exercised
    np.testing.assert_array_equal(lane, np.where(ok, graph.seg_lane[best], -1))
    want = graph.seg_arc[best] + t[rows, best] * np.sqrt(len2[0, best])
    np.testing.assert_allclose(arc[ok], want[ok], atol=1e-9)


@pytest.mark.float_sensitive  # an exact comparison of float geometry
def test_thinning_keeps_each_logged_position_far_enough_from_the_last_kept_one():
    rng = np.random.default_rng(3)
    steps = rng.normal(0.0, 0.6, (400, 2)) * (rng.random((400, 1)) < 0.6)  # stands, creeps
    xy = np.cumsum(steps, 0)
    keep = [0]  # the rule, one position at a time
    for k in range(1, len(xy)):
        if np.hypot(*(xy[k] - xy[keep[-1]])) >= LOG_POINT_SPACING:
            keep.append(k)
    assert 50 < len(keep) < 350
    np.testing.assert_array_equal(thin(xy), xy[keep])
    np.testing.assert_array_equal(thin(xy[:1]), xy[:1])
    assert thin(xy[:0]).shape == (0, 2)


YAW, SHIFT = 1.1, (3000.0, -1500.0)


@pytest.mark.parametrize("route", ["log", "lanes"])
def test_rollouts_do_not_depend_on_the_world_frame(one_scenario_path, route):
    real = route == "log"  # a real scene, and a generated one with signals and symmetric lanes
    for sc in [_load(one_scenario_path) if real else generate_scenario("intersection", 10002)]:
        a = simulate_rollouts(sc, IDMPolicy(route=route), num_rollouts=2, seed=0)
        b = simulate_rollouts(
            sc.transformed(YAW, SHIFT), IDMPolicy(route=route), num_rollouts=2, seed=0
        )
        c, s = np.cos(-YAW), np.sin(-YAW)
        dx, dy = b.x.double().numpy() - SHIFT[0], b.y.double().numpy() - SHIFT[1]
        x, y = c * dx - s * dy, s * dx + c * dy
        assert np.hypot(x - a.x.numpy(), y - a.y.numpy()).max() < 0.01
        x0, y0 = a.x.numpy(), a.y.numpy()
        moved = np.hypot(x0[..., -1] - x0[..., 0], y0[..., -1] - y0[..., 0])
        assert (moved > 5.0).mean() > 0.25


def test_rollouts_differ_and_repeat_with_the_seed(one_scenario_path):
    sc = _load(one_scenario_path)
    fn = make_rollout_fn("idm")
    a, b = fn(sc, 4, 0), fn(sc, 4, 0)
    assert torch.equal(a.x, b.x)
    spread = (a.x[:, :, -1] - a.x[:, :, -1].mean(0)).abs().amax(0)
    assert (spread > 0.5).sum() >= 5  # per-agent desired speeds and headways differ


def test_a_rows_agents_search_for_leaders_together_on_its_period(one_scenario_path, monkeypatch):
    """Leaders and stand lines are looked up at a row's first act and on its steps that are
    multiples of ``leader_period``, for all its agents at once; agents appearing in between
    (the real sample has several) wait for the next one, so the other steps look up nothing."""
    import policies.idm.policy as idm_policy

    find, lines, now = idm_policy.find_leaders, idm_policy.signal_distance, [0]
    searched: list[tuple[int, int]] = []  # (step, agents searching)
    looked: list[int] = []  # steps of stand-line lookups

    def spy(agents, followers, *args):
        searched.append((now[0], followers[1].numel()))
        return find(agents, followers, *args)

    def spy_lines(*args):
        looked.append(now[0])
        return lines(*args)

    monkeypatch.setattr(idm_policy, "find_leaders", spy)
    monkeypatch.setattr(idm_policy, "signal_distance", spy_lines)
    env = BatchedTrafficEnv([_load(one_scenario_path)], 2, npc_policy="idm", seed=0)
    env.reset()
    zeros = torch.zeros(2, env.num_agents, 2)
    first = int(env.sim_state.step[0])
    searched.clear()  # the start-headway fit at reset searches every agent once
    appeared = 0
    for _ in range(12):
        now[0] = int(env.sim_state.step[0])
        before = env.sim_state.valid
        env.step(zeros)
        appeared += int((env.sim_state.valid & ~before).sum())
    steps = [t for t, _ in searched]
    assert steps[0] == first and all(t % LEADER_PERIOD == 0 for t in steps[1:])
    assert len(steps) == 1 + sum(t % LEADER_PERIOD == 0 for t in range(first + 1, first + 12))
    assert appeared > 0 and min(k for _, k in searched) > 50  # whole rows, never a few
    assert looked == steps


def test_candidate_disc_test_keeps_every_near_pair_far_from_the_origin():
    """The leader search's product-form disc test (``leaders._near_discs``) keeps every pair
    the direct test |c - p| < r + reach keeps, and none beyond the radius plus ``DISC_SLACK``,
    in a world 5 km from the origin, with absent columns (+inf) and rows that ask nothing."""
    from policies.idm.leaders import _near_discs
    from policies.idm.params import DISC_SLACK

    g = torch.Generator().manual_seed(0)
    b, ci, cj = 6, 20, 50
    shift = torch.tensor([5000.0, -4000.0])
    p = torch.rand(b, cj, 2, generator=g) * 300.0 + shift
    c = torch.rand(b, ci, 2, generator=g) * 300.0 + shift
    r = torch.rand(b, ci, generator=g) * 40.0
    reach = torch.rand(b, cj, generator=g) * 20.0
    p[:, -5:] = float("inf")  # absent agents
    r[-1] = float("-inf")  # a row that asks nothing
    got = _near_discs((p[..., 0], p[..., 1], reach), (c[..., 0], c[..., 1], r))
    d = torch.cdist(c.double(), torch.nan_to_num(p.double(), posinf=1e9))
    limit = (r.double().unsqueeze(2) + reach.double().unsqueeze(1)).clamp_min(0.0)
    inside, beyond = d < limit - 1e-3, d > limit + DISC_SLACK + 0.05  # float32 rounding
    assert inside.sum() > 100 and beyond.sum() > 1000
    assert got[inside].all() and not got[beyond].any()
    assert not got[-1].any() and not got[..., -5:].any()


def test_quarter_chords_give_the_gaps_of_every_chord():
    """``pair_gaps`` tests only the chords of the corridor quarters each agent's path comes
    near: on random bent corridors and agents (standing, slow, fast, reversing, crossing) it
    gives the gaps, lead speeds and crossing gaps of testing all ``CHORDS`` chords of every
    pair, and no pair it leaves out has a finite gap or crossing in any chord."""
    from policies.idm.leaders import Agents, Corridor, _chord_gaps, pair_gaps, slot_table
    from policies.idm.params import CHORDS, CROSSING_HORIZON, MOVING_SPEED

    g = torch.Generator().manual_seed(0)
    n_lanes, n_agents = 40, 120
    turn = (torch.rand(n_lanes, CHORDS, generator=g) - 0.5) * 1.2  # rad per chord
    heading = torch.rand(n_lanes, 1, generator=g) * 6.283 + turn.cumsum(1)
    length = 2.0 + torch.rand(n_lanes, CHORDS, generator=g) * 6.0
    direction = torch.stack([heading.cos(), heading.sin()], -1)
    start = (torch.rand(n_lanes, 1, 2, generator=g) - 0.5) * 60.0
    steps = direction * length.unsqueeze(-1)
    origin = start + torch.cat([torch.zeros(n_lanes, 1, 2), steps.cumsum(1)[:, :-1]], 1)
    offset = torch.cat([torch.zeros(n_lanes, 1), length.cumsum(1)[:, :-1]], 1)
    lanes = Corridor(origin, direction, length, offset)
    pose = torch.cat(
        [
            (torch.rand(1, n_agents, 2, generator=g) - 0.5) * 100.0,
            torch.rand(1, n_agents, 1, generator=g) * 6.283,
        ],
        -1,
    )
    speed = torch.rand(1, n_agents, generator=g) * 20.0 - 4.0
    speed[0, :20] = 0.0
    size = torch.stack(
        [
            3.0 + 3.0 * torch.rand(1, n_agents, generator=g),
            1.5 + torch.rand(1, n_agents, generator=g),
        ],
        -1,
    )
    agents = Agents(pose, speed, size)
    own = torch.stack(
        [
            4.5 * torch.ones(n_lanes),
            1.3 * torch.ones(n_lanes),
            10.0 * torch.rand(n_lanes, generator=g),
        ],
        0,
    )  # [3, L]
    li = torch.arange(n_lanes).repeat_interleave(n_agents)
    fj = torch.arange(n_agents).repeat(n_lanes)
    slots = slot_table(agents)
    k, gap, lead, ghost = pair_gaps((li, fj), slots, lanes, own)
    columns = [*origin.unbind(-1), *direction.unbind(-1), length, offset]
    chords = torch.stack(columns, 0)[:, li].transpose(1, 2)  # [6, CHORDS, Q]: every chord
    other = slots[:, fj]  # [7, Q]
    moving = other[4].abs() > MOVING_SPEED
    horizon = torch.where(moving, CROSSING_HORIZON, 0.0)
    all_gap, all_lead, all_ghost = _chord_gaps(chords, other, own[:, li], horizon)
    found = torch.isfinite(all_gap) | torch.isfinite(all_ghost)
    assert found.sum() > 50 and torch.isfinite(all_ghost).sum() > 10
    left_out = torch.ones(li.shape[0], dtype=torch.bool)
    left_out[k] = False
    assert not found[left_out].any()
    assert torch.equal(gap, all_gap[k]) and torch.equal(ghost, all_ghost[k])
    finite = torch.isfinite(gap)
    assert torch.equal(lead[finite], all_lead[k][finite])


# ----------------------------------------------------------------------------- entry points
def test_batched_env_cli_and_planner_use(one_scenario_path, tmp_path):
    sc = _load(one_scenario_path)
    venv = BatchedTrafficEnv([sc], 3, npc_policy="idm_lanes", seed=0)
    venv.reset()
    zeros = torch.zeros(3, venv.num_agents, 2)
    for _ in range(82):  # past the first autoreset (80-step episodes)
        venv.step(zeros)
    assert venv.npc_policy.config.route.value == "lanes"
    args = ["evaluate", "--data", str(one_scenario_path), "--policy", "idm", "--rollouts", "2"]
    assert cli.main(args) == 0
    view = tmp_path / "view.html"
    args = ["view", str(one_scenario_path), "--policy", "idm", "--rollouts", "1"]
    assert cli.main([*args, "--out", str(view)]) == 0 and view.stat().st_size > 10_000


def test_planning_one_track_routes_it_alone():
    """``plan(tracks=[k])`` (the planner's: one agent) routes track k alone, with the route
    and stop lines the full plan gives it where no branch is drawn."""
    sc = _fork(turn=True)
    policy = IDMPolicy(route="lanes")
    full, one = policy.plan(sc, NOW), policy.plan(sc, NOW, tracks=[0])
    assert one.routes.valid.tolist() == [True] and full.routes.valid.tolist() == [True]
    np.testing.assert_array_equal(one.routes.points, full.routes.points)
    two = scene(
        [(EAST, 100.0, 8.0), (EAST, 60.0, 8.0)], JUNCTION, signs=((500, (-1.0, -3.0), [2]),)
    )
    full, one = policy.plan(two, NOW), policy.plan(two, NOW, tracks=[1])
    assert one.routes.valid.tolist() == [False, True]
    assert np.isinf(one.events.sign_arc[0]).all() and np.isfinite(one.events.sign_arc[1, 0])
    np.testing.assert_array_equal(one.events.sign_arc[1], full.events.sign_arc[1])
