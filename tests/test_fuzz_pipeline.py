"""Seeded fuzz of the whole pipeline with bad values inside valid files.

Real scenes (the two shared Scenario protos cut down to a few tracks, and a GPUDrive JSON scene)
get one or two edits that keep the file well-formed: a numeric field set to NaN, inf, +-1e30,
0, a negative or huge number; an integer field out of its range; a field removed or of the
wrong type; the scene cut short; no track valid at the current step. Each case then goes
through load -> ``TrafficEnv`` -> ``BatchedTrafficEnv`` (a few steps) -> WOSAC export
validation and scoring (constant velocity), and must either be refused with a ``TbsimError``
naming the file or give only finite outputs (``pipeline_support.run_pipeline``).
"""

from __future__ import annotations

import copy
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from tbsim_env.data.protos import scenario_pb2
from tests.pipeline_support import (
    OBJECT_STATE_FLOATS,
    read_proto,
    run_pipeline,
    small_proto,
    write_proto,
)
from tests.real_format_support import mutate_document
from tests.test_bad_input import time_guard

CASE_LIMIT_S = 10.0
FLOATS = (
    float("nan"),
    float("inf"),
    float("-inf"),
    1e30,
    -1e30,
    0.0,
    -1.0,
    -5.0,
    1e20,
    3e38,
    1e-30,
    1.01e7,
    600.0,
    150.0,
)
"""Values written into float fields (beyond and inside the plausibility bounds)."""
INT32 = (0, -1, -5, 1, 10, 11, 90, 91, 2**31 - 1, -(2**31))
INT64 = (0, -1, 7, 2**63 - 1, -(2**63))
JSON_VALUES: tuple[Any, ...] = (
    *FLOATS,
    0,
    -1,
    2**31,
    10**20,
    10**400,
    2.7,
    True,
    False,
    "5",
    None,
    [],
)
"""Values written into JSON number fields: also booleans, strings, nulls and huge integers."""


# ----------------------------------------------------------------------------- protobuf edits


def _pick(rng: np.random.Generator, items):
    return items[int(rng.integers(len(items)))]


def _map_points(msg: scenario_pb2.Scenario) -> list:
    points = []
    for f in msg.map_features:
        member = f.WhichOneof("feature_data")
        if member == "stop_sign":
            points.append(f.stop_sign.position)
        elif member in ("crosswalk", "speed_bump", "driveway"):
            points.extend(getattr(f, member).polygon)
        elif member is not None:
            points.extend(getattr(f, member).polyline)
    return points


def _state_float(msg, rng) -> None:
    track = _pick(rng, msg.tracks)
    n = len(track.states)  # an earlier edit of the case may have cut or cleared them
    step = msg.current_time_index if rng.random() < 0.5 else int(rng.integers(max(n, 1)))
    name = _pick(rng, OBJECT_STATE_FLOATS)
    value = _pick(rng, FLOATS)
    for k in range(n) if name in ("length", "width", "height") else [step] if step < n else []:
        setattr(track.states[k], name, value)


def _map_float(msg, rng) -> None:
    setattr(_pick(rng, _map_points(msg)), _pick(rng, "xyz"), _pick(rng, FLOATS))


def _speed_limit(msg, rng) -> None:
    lanes = [f for f in msg.map_features if f.WhichOneof("feature_data") == "lane"]
    if not lanes:  # an earlier edit cleared them
        return _map_float(msg, rng)
    _pick(rng, lanes).lane.speed_limit_mph = _pick(rng, FLOATS)


def _stop_point(msg, rng) -> None:
    states = [s for d in msg.dynamic_map_states for s in d.lane_states]
    if states:
        setattr(_pick(rng, states).stop_point, _pick(rng, "xyz"), _pick(rng, FLOATS))
    else:
        _map_float(msg, rng)


def _timestamp(msg, rng) -> None:
    msg.timestamps_seconds[int(rng.integers(len(msg.timestamps_seconds)))] = _pick(rng, FLOATS)


def _int32(msg, rng) -> None:
    value = _pick(rng, INT32)
    kind = int(rng.integers(5))
    if kind == 0:
        _pick(rng, msg.tracks).id = value
    elif kind == 1:
        msg.current_time_index = value
    elif kind == 2:
        msg.sdc_track_index = value
    elif kind == 3:
        msg.tracks_to_predict.add(track_index=value)
    else:
        msg.objects_of_interest.append(value)


def _int64(msg, rng) -> None:
    kind = int(rng.integers(3))
    if kind == 0:
        feature = _pick(rng, msg.map_features)
        other = _pick(rng, msg.map_features).id
        feature.id = other if rng.random() < 0.3 else _pick(rng, INT64)
    elif kind == 1:
        states = [s for d in msg.dynamic_map_states for s in d.lane_states]
        if states:
            _pick(rng, states).lane = _pick(rng, INT64)
    else:
        lanes = [f for f in msg.map_features if f.WhichOneof("feature_data") == "lane"]
        _pick(rng, lanes).lane.entry_lanes.append(_pick(rng, INT64))


def _clear(msg, rng) -> None:
    kind = int(rng.integers(6))
    if kind < 3:
        msg.ClearField(("scenario_id", "current_time_index", "sdc_track_index")[kind])
    elif kind == 3:
        _pick(rng, msg.tracks).ClearField("states")
    elif kind == 4:
        feature = _pick(rng, msg.map_features)
        feature.ClearField(feature.WhichOneof("feature_data"))
    else:
        msg.ClearField("tracks_to_predict")


def _short(msg, rng) -> None:
    n = int(_pick(rng, (1, 2, 5, 10, 11, 12, 50)))
    del msg.timestamps_seconds[n:]
    del msg.dynamic_map_states[n:]
    for t in msg.tracks:
        del t.states[n:]


def _invalid(msg, rng) -> None:
    now = msg.current_time_index
    kind = int(rng.integers(3))
    sdc = msg.sdc_track_index  # an earlier edit of the case may have moved it off the tracks
    tracks = [msg.tracks[sdc]] if kind == 0 and 0 <= sdc < len(msg.tracks) else msg.tracks
    for t in tracks:
        for k in range(len(t.states)) if kind == 2 else [now]:
            if 0 <= k < len(t.states):
                t.states[k].valid = False


def _valid_placeholder(msg, rng) -> None:
    """Mark an invalid state (zero placeholders, size 0) valid."""
    states = [s for t in msg.tracks for s in t.states if not s.valid]
    if states:
        _pick(rng, states).valid = True
    else:
        _state_float(msg, rng)


PROTO_EDITS: tuple[Callable, ...] = (
    _state_float,
    _state_float,
    _state_float,
    _map_float,
    _speed_limit,
    _stop_point,
    _timestamp,
    _int32,
    _int64,
    _clear,
    _short,
    _invalid,
    _valid_placeholder,
)


# ----------------------------------------------------------------------------- JSON edits


def _number_paths(doc: Any, prefix: tuple = ()) -> list[tuple]:
    """Paths of every number (not boolean) in a decoded JSON document."""
    out = []
    items = (
        doc.items() if isinstance(doc, dict) else enumerate(doc) if isinstance(doc, list) else ()
    )
    for key, value in items:
        if isinstance(value, (dict, list)):
            out.extend(_number_paths(value, (*prefix, key)))
        elif isinstance(value, (int, float)) and not isinstance(value, bool):
            out.append((*prefix, key))
    return out


def _set(doc: Any, path: tuple, value: Any) -> None:
    for key in path[:-1]:
        doc = doc[key]
    doc[path[-1]] = value


def _json_number(doc, rng, paths) -> None:
    # Half the edits hit the few metadata / id numbers, half any number of the scene.
    few = [p for p in paths if p[0] == "metadata" or p[-1] in ("id", "map_element_id")]
    path = _pick(rng, few if few and rng.random() < 0.5 else paths)
    _set(doc, path, copy.deepcopy(_pick(rng, JSON_VALUES)))


def _json_short(doc, rng, paths) -> None:
    n = int(_pick(rng, (1, 2, 5, 10, 11, 12, 50)))
    for obj in doc["objects"]:
        for key in ("position", "velocity", "heading", "valid"):
            obj[key] = obj[key][:n]


def _json_invalid(doc, rng, paths) -> None:
    for obj in doc["objects"]:
        obj["valid"][10] = False


def _json_structure(doc, rng, paths) -> dict:
    return mutate_document(doc, rng)


JSON_EDITS = (_json_number, _json_number, _json_number, _json_short, _json_invalid)


# ----------------------------------------------------------------------------- the test


def _proto_case(base, rng, path: Path) -> None:
    msg = scenario_pb2.Scenario()
    msg.CopyFrom(base)
    for _ in range(1 + int(rng.random() < 0.3)):
        _pick(rng, PROTO_EDITS)(msg, rng)
    write_proto(path, msg)


def _json_case(doc, paths, rng, path: Path) -> None:
    if rng.random() < 0.25:
        out = _json_structure(doc, rng, paths)
    else:
        out = copy.deepcopy(doc)
        _pick(rng, JSON_EDITS)(out, rng, paths)
    path.write_text(json.dumps(out, default=lambda a: a.tolist()))  # arrays of JUNK_VALUES


CASES = 300


def run_fuzz(
    cases: int, seed: int, work_dir: Path, womd_dir: Path, on_case: Callable | None = None
) -> dict[str, list[int]]:
    """Make and run ``cases`` fuzz cases (2 proto cases for each JSON case) in ``work_dir``.

    Args:
        on_case: called as ``on_case(case, path)`` around each run (``run_pipeline``'s
            outcome is what it returns; by default ``run_pipeline`` under the time guard).

    Returns:
        {outcome: [case numbers]} ("ok", "refused", or what ``on_case`` returns).
    """
    rng = np.random.default_rng(seed)
    one = womd_dir / "waymo-open-dataset" / "motion_data_one_scenario.tfrecord"
    two = womd_dir / "waymo-open-dataset" / "womd_scenario_input.tfrecord"
    small = [small_proto(read_proto(p)) for p in (one, two)]
    doc = json.loads((womd_dir / "gpudrive" / "tfrecord-00000-of-01000_222.json").read_text())
    paths = _number_paths(doc)
    outcomes: dict[str, list[int]] = {"ok": [], "refused": []}
    for case in range(cases):
        if case % 3 == 2:
            path = work_dir / f"case{case}.json"
            _json_case(doc, paths, rng, path)
        else:
            path = work_dir / f"case{case}.tfrecord"
            _proto_case(small[case % 2], rng, path)
        if on_case is None:
            with time_guard(CASE_LIMIT_S):
                outcome = run_pipeline(path)
        else:
            outcome = on_case(case, path)
        outcomes.setdefault(outcome, []).append(case)
        path.unlink()
    return outcomes


def test_fuzz_bad_values_through_the_pipeline(
    tmp_path: Path, womd_dir: Path, torch_one_thread
) -> None:
    """Every case is refused naming its file or runs with finite outputs (both must occur);
    ``bench/fuzz.py`` runs the same cases at scale."""
    outcomes = run_fuzz(CASES, 20250828, tmp_path, womd_dir)
    assert set(outcomes) == {"ok", "refused"}
    assert len(outcomes["ok"]) >= CASES // 5 and len(outcomes["refused"]) >= CASES // 5, {
        k: len(v) for k, v in outcomes.items()
    }
