"""Helpers of the bad-value tests: real scenes as editable protobufs / JSON documents, cut down
to a few tracks, and the whole pipeline (load -> TrafficEnv -> BatchedTrafficEnv -> WOSAC
export and scoring) run on a file, checking that it either refuses the file with a
``TbsimError`` naming it or gives only finite outputs."""

from __future__ import annotations

import dataclasses
import math
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import torch

from policies import make_policy
from tbsim_env.core.errors import TbsimError
from tbsim_env.data import load_scenarios
from tbsim_env.data.protos import scenario_pb2
from tbsim_env.data.tfrecord import iter_records, write_records
from tbsim_env.env import BatchedTrafficEnv, TrafficEnv
from tbsim_env.metrics.wosac import score_scenario
from tbsim_env.metrics.wosac.simulate import simulate_rollouts
from tbsim_env.metrics.wosac.submission import rollouts_to_proto, validate_scenario_rollouts

OBJECT_STATE_FLOATS = (
    "center_x",
    "center_y",
    "center_z",
    "length",
    "width",
    "height",
    "heading",
    "velocity_x",
    "velocity_y",
)
"""Numeric fields of ``ObjectState``."""


def read_proto(path: Path) -> scenario_pb2.Scenario:
    """The ``Scenario`` message of the first record of a TFRecord file."""
    ((_, _, payload),) = list(iter_records(path))[:1]
    return scenario_pb2.Scenario.FromString(payload)


def write_proto(path: Path, msg: scenario_pb2.Scenario) -> Path:
    """``msg`` as a one-record TFRecord file at ``path``."""
    write_records(path, [msg.SerializeToString()])
    return path


def small_proto(msg: scenario_pb2.Scenario, tracks: int = 8, radius: float = 40.0):
    """A copy of ``msg`` cut down to the SDC, the tracks to predict and the other tracks valid
    at the current step nearest to the SDC (``tracks`` in all), and the map features with a
    point within ``radius`` m of the SDC: real data, small enough for hundreds of fuzz cases."""
    now, sdc = msg.current_time_index, msg.sdc_track_index
    centre = msg.tracks[sdc].states[now]
    keep = {sdc, *(r.track_index for r in msg.tracks_to_predict)}

    def dist(k: int) -> float:
        s = msg.tracks[k].states[now]
        return math.hypot(s.center_x - centre.center_x, s.center_y - centre.center_y)

    others = [k for k in range(len(msg.tracks)) if msg.tracks[k].states[now].valid]
    for k in sorted(others, key=dist):
        if len(keep) >= tracks:
            break
        keep.add(k)
    order = sorted(keep)
    new_index = {k: i for i, k in enumerate(order)}
    out = scenario_pb2.Scenario()
    out.CopyFrom(msg)
    del out.tracks[:]
    out.tracks.extend(msg.tracks[k] for k in order)
    out.sdc_track_index = new_index[sdc]
    del out.tracks_to_predict[:]
    for r in msg.tracks_to_predict:
        out.tracks_to_predict.add(track_index=new_index[r.track_index], difficulty=r.difficulty)
    del out.objects_of_interest[:]
    near = []
    for f in msg.map_features:
        member = f.WhichOneof("feature_data")
        data = getattr(f, member) if member else None
        pts = []
        if member == "stop_sign":
            pts = [data.position]
        elif member in ("crosswalk", "speed_bump", "driveway"):
            pts = data.polygon
        elif member is not None:
            pts = data.polyline
        if any(math.hypot(p.x - centre.center_x, p.y - centre.center_y) < radius for p in pts):
            near.append(f)
    del out.map_features[:]
    out.map_features.extend(near)
    return out


def finite(tree: Any) -> bool:
    """Every number of a nested dict / list / tuple of arrays, tensors and scalars is finite
    (strings, booleans and None are skipped)."""
    if isinstance(tree, dict):
        return all(finite(v) for v in tree.values())
    if isinstance(tree, (list, tuple)):
        return all(finite(v) for v in tree)
    if isinstance(tree, torch.Tensor):
        return not tree.is_floating_point() or bool(torch.isfinite(tree).all())
    if isinstance(tree, np.ndarray):
        return tree.dtype.kind != "f" or bool(np.isfinite(tree).all())
    if isinstance(tree, float):
        return math.isfinite(tree)
    return True


def run_pipeline(path: Path, *, steps: int = 3, rollouts: int = 2, score: bool = True) -> str:
    """Load ``path`` and run it through both environments and the WOSAC export and scoring
    (constant-velocity NPCs and rollouts, random actions within the limits).

    Returns:
        "ok" when every output was finite, "refused" when a ``TbsimError`` naming ``path``
        stopped it. Anything else (another exception, a non-finite output, an error that does
        not name the file) fails the calling test.
    """
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            _pipeline(path, steps, rollouts, score)
    except TbsimError as err:
        assert str(path) in str(err), f"error does not name {path}: {err}"
        assert "\n" not in str(err), f"error is not one line: {err!r}"
        return "refused"
    return "ok"


def _pipeline(path: Path, steps: int, rollouts: int, score: bool) -> None:
    scenarios = load_scenarios(path)
    gen = np.random.default_rng(0)
    env = TrafficEnv(scenarios, controlled="all", npc_policy="constant_velocity")
    obs, infos = env.reset(seed=0)
    assert finite(obs) and finite(infos), "TrafficEnv.reset gave a non-finite value"
    for _ in range(steps):
        if not env.agents:
            break
        act = {a: env.action_space(a).sample() for a in env.agents}
        out = env.step(act)
        assert finite(out), "TrafficEnv.step gave a non-finite value"
    benv = BatchedTrafficEnv(scenarios, 2, controlled="sdc", npc_policy="constant_velocity", seed=0)
    obs, infos = benv.reset()
    assert finite(obs) and finite(infos), "BatchedTrafficEnv.reset gave a non-finite value"
    high = torch.from_numpy(benv.action_high)
    for _ in range(steps):
        u = torch.from_numpy(gen.uniform(-1, 1, (2, benv.num_agents, 2)).astype(np.float32))
        out = benv.step(u * high)
        assert finite(out), "BatchedTrafficEnv.step gave a non-finite value"
    policy = make_policy("constant_velocity")
    for sc in scenarios:
        r = simulate_rollouts(sc, policy, num_rollouts=rollouts, seed=0)
        validate_scenario_rollouts(rollouts_to_proto(r), sc, num_rollouts=rollouts)
        if score and sc.has_future:
            scores = score_scenario(sc, r)
            values = {f.name: getattr(scores, f.name) for f in dataclasses.fields(scores)}
            assert finite(values), f"scores are not finite: {values}"
