"""Rollout viewer: one self-contained HTML file (map, signals, agents over time, WOSAC flags).

``build_viewer_data`` gathers what the page shows into JSON-ready builtins; ``write_viewer``
embeds them into ``viewer_template.html`` (hand-written JavaScript on a canvas: no server, no
network, no library). The page offers a time slider, play/pause, a rollout selector, zoom and
pan, and shows an agent's id, type, controller, speed and WOSAC flags when clicked.

Every trajectory lies on the WOSAC time grid: ``current + 1 + 80`` steps of 0.1 s (91 in WOMD);
a longer log is cut there, a shorter one (a history-only scene) shows nothing past its end.
A rollout holds the logged history followed by the simulated future of the sim agents (tracks
valid at the current step, the only ones a submission carries); the log entry holds every track.

Per agent and per future step, the flags are the WOSAC features (``tbsim_env.metrics.wosac``):
collision = distance to the nearest object < 0, off-road = distance to the road edge > 0, both
computed for every sim agent (not only the evaluated ones), and the speed is WOSAC's
central-difference linear speed.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from dataclasses import dataclass, replace
from importlib import resources
from pathlib import Path

import numpy as np
import torch

from tbsim_env.core.constants import (
    DT,
    NUM_FUTURE,
    NUM_TL_STATES,
    SIGNAL_TO_TL_STATE,
    MapFeatureType,
    ObjectType,
    TLState,
)
from tbsim_env.core.errors import TbsimError
from tbsim_env.data.scenario import Scenario
from tbsim_env.metrics.wosac.features import slice_steps
from tbsim_env.metrics.wosac.features_interactive import distance_to_nearest_object
from tbsim_env.metrics.wosac.features_kinematic import linear_speed
from tbsim_env.metrics.wosac.features_map import (
    MapFeatureError,
    distance_to_road_edge,
    road_edge_segments,
)
from tbsim_env.metrics.wosac.rollouts import Rollouts
from tbsim_env.metrics.wosac.trajectories import (
    MetricObjects,
    ObjectTrajectories,
    log_trajectories,
    simulated_trajectories,
)
from tbsim_env.rendering import palette as P
from tbsim_env.rendering.frame import log_groups
from tbsim_env.rendering.palette import AgentGroup
from tbsim_env.rendering.view import view_for

TEMPLATE = "viewer_template.html"
"""The page's HTML/CSS/JavaScript, a package file next to this module."""
DATA_MARK = "/*__TBSIM_VIEWER_DATA__*/null"
"""The template's placeholder replaced by the JSON data."""
CANVAS_SIZE = (720, 960)
"""(H, W) CSS pixels of the page's canvas, and of the initial camera."""
POSITION_DECIMALS = 2
"""Positions are embedded in metres rounded to 1 cm."""
ANGLE_DECIMALS = 3
"""Headings are embedded in radians rounded to 1 mrad."""
MARKS = {"selected": (255, 255, 255), "collision": (255, 40, 40), "offroad": (255, 170, 0)}
"""Viewer-only outline colours (RGB): the selected agent, a collision, off-road (this step)."""


class ViewerError(TbsimError, ValueError):
    """Inputs the viewer cannot show (e.g. rollouts of another scenario)."""


@dataclass(frozen=True)
class ViewerRollout:
    """One set of trajectories the page can show, over the WOSAC time grid of T steps.

    Attributes:
        name: label in the rollout selector.
        x, y: [A, T] float64 box centres, metres, scenario frame (NaN where not shown).
        yaw: [A, T] float64 headings, radians CCW from +x.
        valid: [A, T] bool, where an agent is drawn.
        group: [A] int ``AgentGroup`` (who drives it), -1 for tracks this rollout lacks.
        speed: [A, T] float64 m/s (NaN where unknown: ends of a run, invalid steps).
        collision: [A, T] bool, WOSAC collision indication per step (future steps only).
        offroad: [A, T] bool, WOSAC off-road indication per step (future steps only).
        flagged: [A] bool, agents whose flags were computed (the sim agents; a map without
            road edges flags nobody off-road).
    """

    name: str
    x: np.ndarray
    y: np.ndarray
    yaw: np.ndarray
    valid: np.ndarray
    group: np.ndarray
    speed: np.ndarray
    collision: np.ndarray
    offroad: np.ndarray
    flagged: np.ndarray


def wosac_grid(scenario: Scenario) -> Scenario:
    """The scenario on the WOSAC grid: ``current + 1 + 80`` steps (cut or padded invalid)."""
    return scenario.on_time_grid(scenario.current_index + 1 + NUM_FUTURE)


def sim_agent_objects(scenario: Scenario) -> MetricObjects:
    """Every sim agent (valid at the current step), all of them "evaluated", in track order."""
    idx = scenario.sim_agent_indices()
    return MetricObjects(
        track_index=idx, object_id=scenario.tracks.id[idx].astype(np.int64), num_eval=len(idx)
    )


def _future_flags(scenario: Scenario, traj: ObjectTrajectories) -> tuple[np.ndarray, np.ndarray]:
    """WOSAC collision and off-road indications of every object at every future step.

    Args:
        scenario: the scenario on the WOSAC grid.
        traj: [R, N, T] trajectories, every object evaluated (N == num_eval).

    Returns:
        (collision [R, N, T], offroad [R, N, T]) bool, False before the first future step;
        off-road all False on a map without road edges.
    """
    first = scenario.current_index + 1
    fut = slice_steps(traj, slice(first, None))
    r, n, t = traj.x.shape
    collision = np.zeros((r, n, t), bool)
    offroad = np.zeros((r, n, t), bool)
    collision[..., first:] = (distance_to_nearest_object(fut) < 0.0).numpy()
    try:
        edges = road_edge_segments(scenario)
    except MapFeatureError:
        return collision, offroad
    offroad[..., first:] = (distance_to_road_edge(fut, edges) > 0.0).numpy()
    return collision, offroad


def _empty(num_tracks: int, num_steps: int, fill: float = np.nan) -> np.ndarray:
    return np.full((num_tracks, num_steps), fill, np.float64)


def _speed(traj: ObjectTrajectories) -> np.ndarray:
    """[R, N, T] WOSAC linear speed (m/s), NaN where a neighbouring step is invalid."""
    v = traj.valid
    both = torch.zeros_like(v)
    both[..., 1:-1] = v[..., :-2] & v[..., 2:] & v[..., 1:-1]
    speed = linear_speed(traj.x.double(), traj.y.double(), traj.z.double())
    return torch.where(both, speed, torch.nan).numpy()


@dataclass(frozen=True)
class _Flags:
    """WOSAC indications of objects in metric order: collision, off-road [R, N, T] bool."""

    objects: MetricObjects
    collision: np.ndarray
    offroad: np.ndarray


def _rollout_from(
    name: str,
    scenario: Scenario,
    traj: ObjectTrajectories,
    speed: np.ndarray,
    row: int,
    flags: _Flags,
    groups: np.ndarray,
) -> ViewerRollout:
    """Row ``row`` of ``traj`` (objects in ``flags.objects`` order) spread over all A tracks.

    Args:
        traj: [R, N, T] trajectories of ``flags.objects``.
        speed: [R, N, T] m/s of ``traj``.
    """
    a, t = scenario.tracks.num_tracks, scenario.num_steps
    idx = flags.objects.track_index
    x, y, yaw, spd = _empty(a, t), _empty(a, t), _empty(a, t), _empty(a, t)
    valid = np.zeros((a, t), bool)
    v = traj.valid[row].numpy()
    valid[idx] = v
    x[idx] = np.where(v, traj.x[row].numpy(), np.nan)
    y[idx] = np.where(v, traj.y[row].numpy(), np.nan)
    yaw[idx] = np.where(v, traj.heading[row].numpy(), np.nan)
    spd[idx] = speed[row]
    collision, offroad = np.zeros((a, t), bool), np.zeros((a, t), bool)
    collision[idx], offroad[idx] = flags.collision[row] & v, flags.offroad[row] & v
    flagged = np.zeros(a, bool)
    flagged[idx] = True
    group = np.full(a, -1, np.int64)
    group[idx] = groups[idx]
    return ViewerRollout(name, x, y, yaw, valid, group, spd, collision, offroad, flagged)


def log_rollout(scenario: Scenario) -> ViewerRollout:
    """The logged scene as a viewer rollout: every track, logged validity, SDC highlighted.

    Flags are computed, as WOSAC computes those of the log, among the sim agents only and at
    the future steps where they are logged; other tracks have none (``flagged`` False).
    """
    scenario = wosac_grid(scenario)
    tracks = scenario.tracks
    every = MetricObjects(
        track_index=np.arange(tracks.num_tracks, dtype=np.int64),
        object_id=tracks.id.astype(np.int64),
        num_eval=tracks.num_tracks,
    )
    traj = log_trajectories(scenario, every)
    a, t = tracks.num_tracks, scenario.num_steps
    collision, offroad = np.zeros((1, a, t), bool), np.zeros((1, a, t), bool)
    sim = sim_agent_objects(scenario)
    if sim.num_objects:
        c, o = _future_flags(scenario, log_trajectories(scenario, sim))
        collision[:, sim.track_index], offroad[:, sim.track_index] = c, o
    out = _rollout_from(
        "log", scenario, traj, _speed(traj), 0, _Flags(every, collision, offroad),
        log_groups(scenario),
    )  # fmt: skip
    flagged = np.zeros(a, bool)
    flagged[sim.track_index] = True
    return replace(out, flagged=flagged)


def policy_groups(scenario: Scenario, controller: AgentGroup) -> np.ndarray:
    """[A] ``AgentGroup``: ``controller`` for every track, the SDC as ``SDC`` (as the MP4s)."""
    groups = np.full(scenario.tracks.num_tracks, int(controller), np.int64)
    groups[scenario.sdc_index] = int(AgentGroup.SDC)
    return groups


def simulated_rollouts(
    scenario: Scenario,
    rollouts: Rollouts,
    *,
    controller: AgentGroup = AgentGroup.POLICY,
    label: str = "rollout",
) -> list[ViewerRollout]:
    """One viewer rollout per simulated future: logged history, then the rollout's future.

    Args:
        scenario: the scenario the rollouts were simulated on (any log length).
        rollouts: R futures of at least every sim agent, S = 80 steps.
        controller: colour group of the simulated agents (the SDC keeps ``SDC``).
        label: selector labels are ``"<label> <r>"``.

    Raises:
        ViewerError: rollouts of another scenario, of another length, or missing sim agents.
    """
    scenario = wosac_grid(scenario)
    mismatch = rollouts.mismatch(scenario, NUM_FUTURE)
    if mismatch:
        raise ViewerError(mismatch)
    objects = sim_agent_objects(scenario)
    log = log_trajectories(scenario, objects)
    sim = simulated_trajectories(log, objects, rollouts.to("cpu"), scenario.current_index)
    flags = _Flags(objects, *_future_flags(scenario, sim))
    speed = _speed(sim)
    groups = policy_groups(scenario, controller)
    return [
        _rollout_from(f"{label} {r}", scenario, sim, speed, r, flags, groups)
        for r in range(rollouts.num_rollouts)
    ]


def submission_rollouts(scenario: Scenario, path: str | Path) -> list[ViewerRollout]:
    """The rollouts a submission file holds for ``scenario``, checked as the server checks.

    Raises:
        ViewerError: the file has no entry for the scenario.
        SubmissionError: an unreadable file or rollouts that fail the server's checks.
    """
    from tbsim_env.metrics.wosac.submission import (
        read_submission,
        rollouts_from_proto,
        validate_scenario_rollouts,
    )

    sub = read_submission(path)
    for entry in sub.scenario_rollouts:
        if entry.scenario_id == scenario.scenario_id:
            validate_scenario_rollouts(entry, scenario, num_rollouts=len(entry.joint_scenes))
            return simulated_rollouts(scenario, rollouts_from_proto(entry))
    raise ViewerError(
        f"{Path(path)}: no rollouts of scenario {scenario.scenario_id} "
        f"(it holds {len(sub.scenario_rollouts)} scenarios)"
    )


def policy_rollouts(
    scenario: Scenario,
    policy: str,
    *,
    num_rollouts: int,
    seed: int = 0,
    checkpoint: str | None = None,
) -> list[ViewerRollout]:
    """Rollouts of a WOSAC policy by name, with the seed ``tbsim export-wosac`` would use."""
    from tbsim_env.evaluation import check_logged_future, make_rollout_fn, scenario_seed

    if policy == "log_replay":
        check_logged_future([scenario], "log replay")
    fn = make_rollout_fn(policy, checkpoint=checkpoint)
    rollouts = fn(scenario, num_rollouts, scenario_seed(seed, scenario.scenario_id))
    controller = AgentGroup.LOG_REPLAY if policy == "log_replay" else AgentGroup.POLICY
    return simulated_rollouts(scenario, rollouts, controller=controller, label=policy)


# ----------------------------------------------------------------------------- JSON
def _rounded(values: np.ndarray, decimals: int) -> list:
    """Nested lists of ``values`` rounded, NaN and infinities as None (JSON null)."""
    arr = np.round(np.asarray(values, np.float64), decimals)
    if np.isfinite(arr).all():
        return arr.tolist()
    return np.where(np.isfinite(arr), arr, None).tolist()


def _xy(points: np.ndarray) -> list:
    """[n, 2] metres as [[x, y], ...] rounded to 1 cm."""
    return _rounded(np.asarray(points)[:, :2], POSITION_DECIMALS)


def _rgb(color: Sequence[int]) -> list[int]:
    return [int(c) for c in color]


def palette_json() -> dict:
    """The renderer's colours and sizes the page draws with (``palette.py``, one definition)."""
    return {
        "groups": {
            str(int(g)): {"label": P.GROUP_LABELS[g], "color": _rgb(P.GROUP_COLORS[g])}
            for g in AgentGroup
        },
        "signals": [_rgb(P.TL_COLORS[TLState(s)]) for s in range(NUM_TL_STATES)],
        "signal_names": [TLState(s).name.lower() for s in range(NUM_TL_STATES)],
        "background": _rgb(P.BACKGROUND),
        "lane": _rgb(P.LANE_CENTER),
        "bike_lane": _rgb(P.BIKE_LANE_CENTER),
        "edge_boundary": _rgb(P.ROAD_EDGE_BOUNDARY),
        "edge_median": _rgb(P.ROAD_EDGE_MEDIAN),
        "crosswalk": _rgb(P.CROSSWALK),
        "speed_bump": _rgb(P.SPEED_BUMP),
        "driveway": _rgb(P.DRIVEWAY),
        "stop_sign": _rgb(P.STOP_SIGN),
        "stop_sign_outline": _rgb(P.STOP_SIGN_OUTLINE),
        "agent_outline": _rgb(P.AGENT_OUTLINE),
        "heading_tick": _rgb(P.HEADING_TICK),
        "signal_outline": _rgb(P.SIGNAL_OUTLINE),
        "sizes_m": {
            "lane": P.LANE_CENTER_WIDTH_M,
            "road_line": P.ROAD_LINE_WIDTH_M,
            "road_edge": P.ROAD_EDGE_WIDTH_M,
            "dash": P.DASH_M,
            "gap": P.GAP_M,
            "stop_sign": P.STOP_SIGN_RADIUS_M,
            "signal": P.SIGNAL_RADIUS_M,
            "pedestrian": P.PEDESTRIAN_MIN_RADIUS_M,
            "heading_tick": P.HEADING_TICK_WIDTH_M,
        },
        "min_px": {
            "lane": P.LANE_CENTER_MIN_PX,
            "road_line": P.ROAD_LINE_MIN_PX,
            "road_edge": P.ROAD_EDGE_MIN_PX,
            "stop_sign": P.STOP_SIGN_MIN_PX,
            "signal": P.SIGNAL_MIN_PX,
            "agent": P.AGENT_MIN_PX,
            "heading_tick": P.HEADING_TICK_MIN_PX,
        },
    }


def map_json(scenario: Scenario) -> dict:
    """The road map as polylines in metres: lanes, road-line strokes, road edges, polygons.

    Road lines are one entry per painted stroke (double lines as two polylines offset by
    ``DOUBLE_LINE_GAP_M`` each side), with their colour and whether dashed.
    """
    from tbsim_env.core.constants import LaneType, RoadEdgeType
    from tbsim_env.rendering.map_layer import offset_polyline, road_line_style

    rm = scenario.road_map
    out: dict[str, list] = {
        k: []
        for k in ("lanes", "road_lines", "road_edges", "crosswalks", "speed_bumps", "driveways")
    }
    out["stop_signs"] = []
    polygon_key = {
        MapFeatureType.CROSSWALK: "crosswalks",
        MapFeatureType.SPEED_BUMP: "speed_bumps",
        MapFeatureType.DRIVEWAY: "driveways",
    }
    for k, pts in enumerate(rm.polylines):
        kind, sub = MapFeatureType(int(rm.feature_type[k])), int(rm.subtype[k])
        if kind == MapFeatureType.STOP_SIGN:
            out["stop_signs"].append(_xy(pts[:1])[0])
        elif pts.shape[0] < 2:
            continue
        elif kind == MapFeatureType.LANE:
            out["lanes"].append({"pts": _xy(pts), "bike": sub == LaneType.BIKE_LANE})
        elif kind == MapFeatureType.ROAD_EDGE:
            out["road_edges"].append({"pts": _xy(pts), "median": sub == RoadEdgeType.MEDIAN})
        elif kind == MapFeatureType.ROAD_LINE:
            color, strokes = road_line_style(sub)
            for side, dashed in strokes:
                line = offset_polyline(pts[:, :2], side * P.DOUBLE_LINE_GAP_M) if side else pts
                out["road_lines"].append(
                    {"pts": _xy(line), "color": _rgb(color), "dashed": bool(dashed)}
                )
        else:
            out[polygon_key[kind]].append(_xy(pts))
    return out


def signals_json(scenario: Scenario) -> dict:
    """Signal stop points and their ``TLState`` per step (``[S][T]``, -1 where no state)."""
    sig = wosac_grid(scenario).signals
    tl = np.asarray(SIGNAL_TO_TL_STATE, np.int64)[sig.state.astype(np.int64)]
    state = np.where(sig.valid, tl, -1)
    return {
        "lane_id": [int(i) for i in sig.lane_id],
        "xy": _xy(sig.stop_point) if sig.num_signals else [],
        "state": state.tolist(),
    }


def agents_json(scenario: Scenario) -> list[dict]:
    """Per track: id, type, box size (at the current step, else the first valid one), roles."""
    t = scenario.tracks
    cur = scenario.current_index
    role = scenario.role_mask()  # [A, 3]: sdc, interest, predict
    out = []
    for a in range(t.num_tracks):
        valid = np.flatnonzero(t.valid[a])
        k = cur if t.valid[a, cur] or valid.size == 0 else int(valid[0])
        out.append(
            {
                "id": int(t.id[a]),
                "type": ObjectType(int(t.object_type[a])).name.lower(),
                "length": round(float(t.size[a, k, 0]), POSITION_DECIMALS),
                "width": round(float(t.size[a, k, 1]), POSITION_DECIMALS),
                "sdc": bool(a == scenario.sdc_index),
                "sim_agent": bool(t.valid[a, cur]),
                "to_predict": bool(role[a, 2]),
            }
        )
    return out


def rollout_json(rollout: ViewerRollout) -> dict:
    """One rollout: ``[A][T]`` poses and speeds (null where not shown), flag steps per agent."""
    hide = ~rollout.valid
    return {
        "name": rollout.name,
        "group": [int(g) for g in rollout.group],
        "x": _rounded(np.where(hide, np.nan, rollout.x), POSITION_DECIMALS),
        "y": _rounded(np.where(hide, np.nan, rollout.y), POSITION_DECIMALS),
        "yaw": _rounded(np.where(hide, np.nan, rollout.yaw), ANGLE_DECIMALS),
        "speed": _rounded(np.where(hide, np.nan, rollout.speed), POSITION_DECIMALS),
        "collision": [np.flatnonzero(row).tolist() for row in rollout.collision],
        "offroad": [np.flatnonzero(row).tolist() for row in rollout.offroad],
        "flagged": [bool(f) for f in rollout.flagged],
    }


def build_viewer_data(
    scenario: Scenario, rollouts: Sequence[ViewerRollout], title: str = ""
) -> dict:
    """Everything the page shows, as JSON-ready builtins (see ``rollout_json`` for a rollout).

    Args:
        scenario: the scenario (any log length; shown on the WOSAC grid).
        rollouts: what the selector offers, first one shown first.
        title: a line shown above the canvas (e.g. the policy or the submission file).

    Raises:
        ViewerError: no rollout, or a rollout of another shape than the scenario's grid.
    """
    grid = wosac_grid(scenario)
    shape = (grid.tracks.num_tracks, grid.num_steps)
    if not rollouts:
        raise ViewerError(f"scenario {scenario.scenario_id}: nothing to show (no rollout)")
    for r in rollouts:
        if r.x.shape != shape:
            raise ViewerError(f"rollout {r.name!r} has shape {r.x.shape}, expected {shape}")
    h, w = CANVAS_SIZE
    view = view_for(grid, size=(h, w))
    return {
        "format": 1,
        "scenario_id": scenario.scenario_id,
        "source": scenario.source,
        "title": title,
        "dt": DT,
        "current_step": grid.current_index,
        "num_steps": grid.num_steps,
        "view": {
            "cx": view.center[0],
            "cy": view.center[1],
            "mpp": view.meters_per_pixel,
            "width": w,
            "height": h,
        },
        "palette": palette_json(),
        "marks": {k: _rgb(v) for k, v in MARKS.items()},
        "map": map_json(grid),
        "signals": signals_json(grid),
        "agents": agents_json(grid),
        "rollouts": [rollout_json(r) for r in rollouts],
    }


def viewer_html(data: dict) -> str:
    """The page with ``data`` embedded (``</`` escaped so no string can end the script)."""
    template = resources.files("tbsim_env.rendering").joinpath(TEMPLATE).read_text("utf-8")
    if DATA_MARK not in template:
        raise ViewerError(f"{TEMPLATE} lacks the data placeholder {DATA_MARK!r}")
    payload = json.dumps(data, separators=(",", ":"), allow_nan=False).replace("</", "<\\/")
    return template.replace(DATA_MARK, payload)


def write_viewer(
    path: str | Path, scenario: Scenario, rollouts: Sequence[ViewerRollout], title: str = ""
) -> int:
    """Write the self-contained viewer page of ``scenario``; returns its size in bytes."""
    html = viewer_html(build_viewer_data(scenario, rollouts, title))
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(html, encoding="utf-8")
    return len(html.encode("utf-8"))


def embedded_data(html: str) -> dict:
    """The JSON data a page written by ``write_viewer`` embeds (for tests and tools)."""
    start = html.index("const TBSIM_DATA = ") + len("const TBSIM_DATA = ")
    end = html.index(";\n", start)
    return json.loads(html[start:end])


__all__ = [
    "ViewerError",
    "ViewerRollout",
    "build_viewer_data",
    "embedded_data",
    "log_rollout",
    "policy_groups",
    "policy_rollouts",
    "simulated_rollouts",
    "submission_rollouts",
    "viewer_html",
    "write_viewer",
]
