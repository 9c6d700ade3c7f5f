"""Turn ``Scenario`` objects into a batched initial ``SimState`` (padding, frame shift, tensors)."""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
import shapely
import torch

from tbsim_env.core import constants as C
from tbsim_env.data.preprocess.scene import scene_origin
from tbsim_env.data.scenario import Scenario
from tbsim_env.sim.dynamics import signed_speed
from tbsim_env.sim.edge_grid import build_edge_grid
from tbsim_env.sim.state import AgentInfo, LogTrajectory, RoadEdges, SignalLog, SimState

CYCLIC_TOLERANCE_SQ = 1.0
"""A road edge whose ends are closer than 1 m (squared 1 m^2) is closed (WOSAC convention)."""


def _agent_sizes(scenario: Scenario, step: int) -> np.ndarray:
    """[A, 3] sizes at ``step`` where valid, else the last valid size, else 0."""
    t = scenario.tracks
    n_t = t.num_steps
    idx = np.arange(n_t)
    # Last valid step at or before `step`, else the first valid step after it.
    before = np.where(t.valid & (idx <= step), idx, -1).max(axis=1)
    after = np.where(t.valid, idx, n_t).min(axis=1)
    pick = np.where(before >= 0, before, np.minimum(after, n_t - 1))
    return t.size[np.arange(t.num_tracks), pick].astype(np.float32)


def _simplified(polyline: np.ndarray) -> np.ndarray:
    """[n', 2] the polyline [n, 2] simplified to within ``EDGE_SIMPLIFY_TOLERANCE`` m
    (Douglas-Peucker; ends kept): WOMD samples edges every 0.5 m, mostly along straight or
    gently curved lines, so this keeps about one point in ten."""
    if len(polyline) < 3:
        return polyline
    line = shapely.LineString(polyline)
    out = shapely.simplify(line, C.EDGE_SIMPLIFY_TOLERANCE, preserve_topology=False)
    coords = np.asarray(out.coords, np.float64)[:, :2]
    return coords if len(coords) >= 2 else polyline[[0, -1]]


def _road_edge_segments(scenario: Scenario, origin: np.ndarray) -> tuple[np.ndarray, ...]:
    """Flattened road-edge segments with previous/next links (numpy, unpadded), from the
    simplified polylines (``_simplified``)."""
    m = scenario.road_map
    starts, ends, prevs, nexts = [], [], [], []
    offset = 0
    for k in m.indices_of(C.MapFeatureType.ROAD_EDGE):
        raw = m.polylines[k][:, :2] - origin
        if len(raw) < 2:
            continue
        cyclic = float(((raw[0] - raw[-1]) ** 2).sum()) < CYCLIC_TOLERANCE_SQ
        pl = _simplified(raw)
        n = len(pl) - 1
        local = np.arange(n)
        prev = np.where(local > 0, local - 1, n - 1 if cyclic else 0)
        nxt = np.where(local < n - 1, local + 1, 0 if cyclic else n - 1)
        starts.append(pl[:-1])
        ends.append(pl[1:])
        prevs.append(prev + offset)
        nexts.append(nxt + offset)
        offset += n
    if not starts:
        z = np.zeros((0, 2))
        return z, z, np.zeros(0, np.int64), np.zeros(0, np.int64)
    return (
        np.concatenate(starts),
        np.concatenate(ends),
        np.concatenate(prevs).astype(np.int64),
        np.concatenate(nexts).astype(np.int64),
    )


def _check_time_grid(scenarios: Sequence[Scenario], start_step: int) -> int:
    """The common log length T of the scenarios (every one holds ``start_step``)."""
    if not scenarios:
        raise ValueError("build_sim_state needs at least one scenario")
    if start_step < 0:
        raise ValueError(f"start_step {start_step} is negative")
    n_t = scenarios[0].num_steps
    for sc in scenarios:
        if sc.num_steps != n_t:
            raise ValueError(
                f"scenario {sc.scenario_id!r} has {sc.num_steps} steps, "
                f"but {scenarios[0].scenario_id!r} has {n_t}; a batch needs one time grid "
                "(Scenario.on_time_grid)"
            )
        sc.require_log_until(start_step, f"a simulation that starts at step {start_step}")
    return n_t


def _padded_tracks(
    scenarios: Sequence[Scenario], origins: np.ndarray, n_t: int, start_step: int
) -> dict[str, np.ndarray]:
    """Every scenario's tracks padded to the largest track count N (numpy, [B, N, ...]):
    the log (pose in the origin's frame, velocity, z, valid) and the agent attributes."""
    b, n = len(scenarios), max(sc.tracks.num_tracks for sc in scenarios)
    out = {
        "pose": np.zeros((b, n, n_t, 3), np.float32),
        "vel": np.zeros((b, n, n_t, 2), np.float32),
        "z": np.zeros((b, n, n_t), np.float32),
        "valid": np.zeros((b, n, n_t), bool),
        "track_id": np.full((b, n), -1, np.int64),
        "track_index": np.full((b, n), -1, np.int64),
        "object_type": np.zeros((b, n), np.int64),
        "size": np.zeros((b, n, 3), np.float32),
        "role": np.zeros((b, n, 3), bool),
        "mask": np.zeros((b, n), bool),
    }
    for i, sc in enumerate(scenarios):
        t, a = sc.tracks, sc.tracks.num_tracks
        v = t.valid
        out["pose"][i, :a, :, 0] = np.where(v, t.xyz[..., 0] - origins[i, 0], 0.0)
        out["pose"][i, :a, :, 1] = np.where(v, t.xyz[..., 1] - origins[i, 1], 0.0)
        out["pose"][i, :a, :, 2] = np.where(v, t.heading, 0.0)
        out["vel"][i, :a] = np.where(v[..., None], t.velocity, 0.0)
        out["z"][i, :a] = np.where(v, t.xyz[..., 2], 0.0)
        out["valid"][i, :a] = v
        out["track_id"][i, :a] = t.id
        out["track_index"][i, :a] = np.arange(a)
        out["object_type"][i, :a] = t.object_type
        out["size"][i, :a] = _agent_sizes(sc, start_step)
        out["role"][i, :a] = sc.role_mask()
        out["mask"][i, :a] = True
    return out


def _padded_signals(
    scenarios: Sequence[Scenario], origins: np.ndarray, n_t: int, device: torch.device
) -> SignalLog:
    """Every scenario's signals padded to the largest signal count (at least 1)."""
    b, s = len(scenarios), max(max(sc.signals.num_signals for sc in scenarios), 1)
    lane = np.full((b, s), -1, np.int64)
    state = np.zeros((b, s, n_t), np.int64)
    valid = np.zeros((b, s, n_t), bool)
    stop = np.zeros((b, s, 2), np.float32)
    to_tl = np.asarray(C.SIGNAL_TO_TL_STATE, np.int64)
    for i, sc in enumerate(scenarios):
        sig, k = sc.signals, sc.signals.num_signals
        lane[i, :k] = sig.lane_id
        state[i, :k] = np.where(sig.valid, to_tl[np.clip(sig.state, 0, 8)], 0)
        valid[i, :k] = sig.valid
        stop[i, :k] = sig.stop_point[:, :2] - origins[i]
    tt = functools.partial(_tensor, device=device)
    return SignalLog(lane_id=tt(lane), state=tt(state), valid=tt(valid), stop_point=tt(stop))


def _padded_edges(edges: list[tuple[np.ndarray, ...]], device: torch.device) -> RoadEdges:
    """Every scenario's road-edge segments padded to the largest count (at least 1), with
    their grid."""
    b, e = len(edges), max(max(len(x[0]) for x in edges), 1)
    start = np.zeros((b, e, 2), np.float32)
    end = np.zeros((b, e, 2), np.float32)
    valid = np.zeros((b, e), bool)
    prev = np.tile(np.arange(e), (b, 1))
    nxt = np.tile(np.arange(e), (b, 1))
    for i, (st, en, pr, nx) in enumerate(edges):
        ne = len(st)
        start[i, :ne], end[i, :ne], valid[i, :ne] = st, en, True
        prev[i, :ne], nxt[i, :ne] = pr, nx
    tt = functools.partial(_tensor, device=device)
    return RoadEdges(
        start=tt(start),
        end=tt(end),
        valid=tt(valid),
        prev_index=tt(prev),
        next_index=tt(nxt),
        grid=build_edge_grid(
            [(x[0], x[1]) for x in edges], device, links=[(x[2], x[3]) for x in edges]
        ),
    )


def _tensor(x: np.ndarray, device: torch.device) -> torch.Tensor:
    return torch.from_numpy(x).to(device)


def _log_trajectory(tracks: dict[str, np.ndarray], device: torch.device) -> LogTrajectory:
    """The ``LogTrajectory`` of ``_padded_tracks``' arrays (speed signed along the heading)."""
    pose, vel = _tensor(tracks["pose"], device), _tensor(tracks["vel"], device)
    valid = _tensor(tracks["valid"], device)
    return LogTrajectory.of_tables(
        pose=pose,
        speed=signed_speed(vel, pose[..., 2]) * valid,
        velocity=vel,
        z=_tensor(tracks["z"], device),
        valid=valid,
    )


def build_sim_state(
    scenarios: Sequence[Scenario],
    *,
    start_step: int = C.CURRENT_INDEX,
    device: str | torch.device = "cpu",
) -> SimState:
    """Batch scenarios into the initial state at ``start_step``, every agent replayed from the log.

    Agent slots follow the track order of each scenario; smaller scenarios are padded.
    All scenarios must share the same time grid (``Scenario.on_time_grid``), whose length is
    the log's length T of the state; steps past a scenario's log have no valid state there.

    Args:
        scenarios: B scenarios.
        start_step: log step the state starts at (the WOMD current step by default).
        device: torch device.

    Returns:
        A ``SimState`` with ``controlled`` all False.

    Raises:
        MissingFutureError: a scenario's log does not hold ``start_step``.
    """
    n_t = _check_time_grid(scenarios, start_step)
    dev = torch.device(device)
    origins = np.stack([scene_origin(sc) for sc in scenarios]).astype(np.float64)
    edges = [_road_edge_segments(sc, origins[i]) for i, sc in enumerate(scenarios)]
    tracks = _padded_tracks(scenarios, origins, n_t, start_step)
    log = _log_trajectory(tracks, dev)
    b, n = tracks["mask"].shape
    fields = ("track_id", "track_index", "object_type", "size", "role", "mask")
    agents = AgentInfo(**{k: _tensor(tracks[k], dev) for k in fields})
    return SimState(
        step=torch.full((b,), start_step, dtype=torch.int64, device=dev),
        pose=log.pose.value[:, :, start_step].clone(),
        speed=log.speed.value[:, :, start_step].clone(),
        valid=log.valid.value[:, :, start_step].clone(),
        controlled=torch.zeros((b, n), dtype=torch.bool, device=dev),
        agents=agents,
        log=log,
        signals=_padded_signals(scenarios, origins, n_t, dev),
        road_edges=_padded_edges(edges, dev),
        origin=_tensor(origins, dev),
    )
