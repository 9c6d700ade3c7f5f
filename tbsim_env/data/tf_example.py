"""WOMD ``tf.train.Example`` TFRecords (the "tf_example" motion files) -> typed ``Scenario``,
without TensorFlow.

Records are framed by ``tbsim_env.data.tfrecord`` and decoded with the generated classes of
``tbsim_env/data/protos/tf_example.proto``; the features are then read as fixed-shape arrays
(docs/formats.md, "tf.train.Example motion files"; A agent slots, 128 in WOMD; P past, 1 current and
F future steps, 10 / 1 / 80; S signal slots, 16):

* ``state/{past,current,future}/{x,y,z,bbox_yaw,velocity_x,velocity_y,length,width,height}``
  [A, P | 1 | F] float, ``.../valid`` int64: one track per slot valid at some step (empty
  padding slots are dropped), ``state/id`` and ``state/type`` [A] (floats holding integers),
  ``state/{is_sdc,tracks_to_predict,objects_of_interest,difficulty_level}`` [A] int64.
  ``bbox_yaw`` is kept as stored in ``Tracks.raw_heading`` and wrapped in ``Tracks.heading``.
* ``roadgraph_samples/{xyz [N, 3], type, id, valid [N]}``: the valid samples grouped by id (in
  order of first appearance, samples in file order) give one map feature each. **These are
  sampled points, not the original polylines**: a long feature may be cut where the N samples
  ran out, and lanes carry no speed limit or connectivity. ``type`` numbers lanes, road lines,
  road edges and the point features like GPUDrive's ``map_element_id``
  (``gpudrive.map_element_to_feature``, the one table of that numbering).
* ``traffic_light_state/{past,current,future}/{state,valid,id,x,y,z}`` [P | 1 | F, S] (time
  major): one signal row per lane id, stop point at (x, y, z).
* Timestamps from ``traffic_light_state/{past,current,future}/timestamp_micros`` [T]; the
  current step is P (10).

Problems raise ``ScenarioFormatError`` naming the file, record, byte offset and feature key.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Iterator

import numpy as np
from google.protobuf.message import DecodeError

from tbsim_env.core.errors import ScenarioFormatError
from tbsim_env.data.conversion import signals_from_entries
from tbsim_env.data.gpudrive import map_element_to_feature
from tbsim_env.data.protos import tf_example_pb2
from tbsim_env.data.scenario import RoadMap, Scenario, Tracks, TrafficSignals
from tbsim_env.data.womd import _Where, iter_parsed_records, wrap_heading_f32

PathLike = str | os.PathLike

PARTS = ("past", "current", "future")
"""Time blocks of the state and signal features, in time order."""
SCENARIO_ID_KEY = "scenario/id"
_TRACK_FIELDS = ("x", "y", "z", "bbox_yaw", "velocity_x", "velocity_y", "length", "width", "height")
_SIGNAL_FIELDS = ("state", "valid", "id", "x", "y", "z")
_NUM_SIGNAL_STATES = 9
_MAX_ID = 2.0**53  # float32 ids beyond this are not exact integers anyway


def decode_example(payload: bytes, where: _Where | None = None) -> dict[str, np.ndarray | list]:
    """Features of one serialized ``tf.train.Example``: key -> float32 / int64 array, or a list
    of bytes for a bytes list. Empty features are left out.

    Raises:
        ScenarioFormatError: not a valid Example protobuf.
    """
    where = where or _Where(None)
    try:
        example = tf_example_pb2.Example.FromString(payload)
    except Exception as err:  # DecodeError, and from the C runtime also other types
        kind = "" if isinstance(err, DecodeError) else f"{type(err).__name__}: "
        raise where.error(f"not a valid tf.Example protobuf: {kind}{err}") from err
    out: dict[str, np.ndarray | list] = {}
    for key, feature in example.features.feature.items():
        kind = feature.WhichOneof("kind")
        if kind == "bytes_list":
            out[key] = list(feature.bytes_list.value)
        elif kind == "float_list":
            out[key] = np.asarray(feature.float_list.value, np.float32)
        elif kind == "int64_list":
            out[key] = np.asarray(feature.int64_list.value, np.int64)
    return out


def is_tf_example(payload: bytes) -> bool:
    """Whether ``payload`` decodes as a ``tf.train.Example`` holding a ``scenario/id``.

    A WOMD ``Scenario`` record decodes as an Example with no features (its field 1 has another
    wire type), so this tells the two TFRecord payloads apart.
    """
    try:
        example = tf_example_pb2.Example.FromString(payload)
    except Exception:  # not an Example at all
        return False
    return SCENARIO_ID_KEY in example.features.feature


# ----------------------------------------------------------------------------- arrays


def _array(feats: dict, key: str, where: _Where, kind: str) -> np.ndarray:
    """Feature ``key`` as an array of ``kind`` ('f' float_list, 'i' int64_list)."""
    if key not in feats:
        raise where.error(f"feature {key!r} is missing: not a WOMD tf.Example record")
    value = feats[key]
    if not isinstance(value, np.ndarray) or value.dtype.kind != kind:
        want = "float_list" if kind == "f" else "int64_list"
        raise where.error(f"feature {key!r} is not a {want}")
    return value


def _blocks(
    feats: dict, prefix: str, name: str, rows: int, where: _Where, kind: str, time_major: bool
) -> list[np.ndarray]:
    """``prefix/{past,current,future}/name`` as [rows, n_part] arrays (transposed if time major)."""
    out = []
    for part in PARTS:
        key = f"{prefix}/{part}/{name}"
        arr = _array(feats, key, where, kind)
        if rows == 0 or arr.size % rows:
            raise where.error(f"feature {key!r} has {arr.size} values, not a multiple of {rows}")
        out.append(arr.reshape(-1, rows).T if time_major else arr.reshape(rows, -1))
    return out


def _steps(feats: dict, num_agents: int, where: _Where) -> tuple[int, int]:
    """(T, current index) from the lengths of ``state/{past,current,future}/x``."""
    n = [b.shape[1] for b in _blocks(feats, "state", "x", num_agents, where, "f", False)]
    if n[1] != 1:
        raise where.error(f"feature 'state/current/x' holds {n[1]} steps per agent, expected 1")
    return sum(n), n[0]


def _timestamps(feats: dict, n_steps: int, where: _Where) -> np.ndarray:
    """[T] float64 seconds from ``traffic_light_state/*/timestamp_micros``."""
    parts = [_array(feats, f"traffic_light_state/{p}/timestamp_micros", where, "i") for p in PARTS]
    micros = np.concatenate(parts)
    if micros.shape[0] != n_steps:
        raise where.error(
            f"features 'traffic_light_state/*/timestamp_micros' hold {micros.shape[0]} steps, "
            f"the states {n_steps}"
        )
    if n_steps > 1 and not (np.diff(micros) > 0).all():
        step = int(np.argmax(np.diff(micros) <= 0)) + 1
        raise where.error(
            f"feature 'traffic_light_state/*/timestamp_micros' is not increasing at step {step}"
        )
    return micros.astype(np.float64) * 1e-6


# ----------------------------------------------------------------------------- tracks


def _integral(values: np.ndarray, key: str, where: _Where) -> np.ndarray:
    """int64 from a float feature that must hold integers (``state/id``, ``state/type``)."""
    ok = np.isfinite(values) & (np.abs(values) < _MAX_ID)
    ok &= np.floor(np.where(ok, values, 0.0)) == np.where(ok, values, 0.0)
    if not ok.all():
        k = int(np.argmax(~ok))
        raise where.error(f"feature {key!r}: slot {k} holds {float(values[k])!r}, not an integer")
    return values.astype(np.int64)


def _tracks(feats: dict, n_steps: int, where: _Where) -> tuple[Tracks, np.ndarray]:
    """Tracks of the slots valid at some step, and those slots' indices [A]."""
    slots = _array(feats, "state/id", where, "f").shape[0]
    cols = {
        name: np.concatenate(_blocks(feats, "state", name, slots, where, "f", False), axis=1)
        for name in _TRACK_FIELDS
    }  # each [slots, T]
    valid_all = np.concatenate(_blocks(feats, "state", "valid", slots, where, "i", False), 1) > 0
    if any(c.shape[1] != n_steps for c in cols.values()) or valid_all.shape[1] != n_steps:
        raise where.error(f"features 'state/*' do not all hold {n_steps} steps per agent")
    keep = np.flatnonzero(valid_all.any(axis=1))
    if keep.shape[0] == 0:
        raise where.error("feature 'state/*/valid': no agent is valid at any step")
    ids = _integral(_array(feats, "state/id", where, "f")[keep], "state/id", where)
    types = _integral(_array(feats, "state/type", where, "f"), "state/type", where)
    if types.shape[0] != slots:
        raise where.error(f"feature 'state/type' has {types.shape[0]} values, 'state/id' {slots}")
    valid = valid_all[keep]
    c = {k: v[keep].astype(np.float64) for k, v in cols.items()}
    v3 = valid[..., None]
    with np.errstate(over="ignore", invalid="ignore"):
        tracks = Tracks(
            id=ids,
            object_type=types[keep].clip(-128, 127).astype(np.int8),
            xyz=np.where(v3, np.stack([c["x"], c["y"], c["z"]], -1), 0.0),
            heading=np.where(valid, wrap_heading_f32(c["bbox_yaw"]), np.float32(0.0)),
            velocity=np.where(v3, np.stack([c["velocity_x"], c["velocity_y"]], -1), 0.0).astype(
                np.float32
            ),
            size=np.where(v3, np.stack([c["length"], c["width"], c["height"]], -1), 0.0).astype(
                np.float32
            ),
            valid=valid,
            raw_heading=np.where(valid, c["bbox_yaw"], 0.0).astype(np.float32),
        )
    return tracks, keep


def _slot_flags(feats: dict, key: str, slots: int, where: _Where) -> np.ndarray:
    arr = _array(feats, key, where, "i")
    if arr.shape[0] != slots:
        raise where.error(f"feature {key!r} has {arr.shape[0]} values, 'state/id' {slots}")
    return arr


def _roles(
    feats: dict, keep: np.ndarray, ids: np.ndarray, where: _Where
) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """(SDC index, tracks-to-predict indices, their difficulties, objects-of-interest ids)."""
    slots = _array(feats, "state/id", where, "f").shape[0]
    row = np.full(slots, -1, np.int64)
    row[keep] = np.arange(keep.shape[0])
    sdc = np.flatnonzero(_slot_flags(feats, "state/is_sdc", slots, where) > 0)
    if sdc.shape[0] != 1 or row[sdc[0]] < 0:
        raise where.error(
            f"feature 'state/is_sdc' marks {sdc.shape[0]} slot(s) {sdc[:4].tolist()}; "
            "expected one agent valid at some step"
        )
    ttp = np.flatnonzero(_slot_flags(feats, "state/tracks_to_predict", slots, where) > 0)
    if (row[ttp] < 0).any():
        k = int(ttp[np.argmax(row[ttp] < 0)])
        raise where.error(f"feature 'state/tracks_to_predict' marks slot {k}, never valid")
    difficulty = _slot_flags(feats, "state/difficulty_level", slots, where)[ttp]
    if ((difficulty < 0) | (difficulty > 127)).any():
        raise where.error("feature 'state/difficulty_level' holds a value outside [0, 127]")
    ooi = np.flatnonzero(_slot_flags(feats, "state/objects_of_interest", slots, where) > 0)
    ooi_ids = ids[row[ooi][row[ooi] >= 0]]
    return int(row[sdc[0]]), row[ttp], difficulty.astype(np.int8), ooi_ids


# ----------------------------------------------------------------------------- map, signals


def _road_map(feats: dict, where: _Where) -> RoadMap:
    """One map feature per roadgraph id (valid samples only; unknown types skipped, warned)."""
    xyz = _array(feats, "roadgraph_samples/xyz", where, "f").astype(np.float64)
    kind = _array(feats, "roadgraph_samples/type", where, "i")
    rid = _array(feats, "roadgraph_samples/id", where, "i")
    valid = _array(feats, "roadgraph_samples/valid", where, "i") > 0
    n = kind.shape[0]
    if xyz.shape[0] != 3 * n or rid.shape[0] != n or valid.shape[0] != n:
        raise where.error(
            f"features 'roadgraph_samples/*' disagree: xyz {xyz.shape[0]} values, type {n}, "
            f"id {rid.shape[0]}, valid {valid.shape[0]} (expected 3:1:1:1)"
        )
    xyz, kind, rid = xyz.reshape(n, 3)[valid], kind[valid], rid[valid]
    ids, first = np.unique(rid, return_index=True)
    order = np.argsort(first, kind="stable")
    groups = np.argsort(rid, kind="stable")  # sample rows grouped by id, file order inside
    bounds = np.searchsorted(rid[groups], ids)
    rows, skipped = [], []
    for g in order:
        members = groups[bounds[g] : bounds[g + 1] if g + 1 < len(ids) else None]
        mapped = map_element_to_feature(int(kind[members[0]]))
        if mapped is None or (kind[members] != kind[members[0]]).any():
            skipped.append(int(ids[g]))
            continue
        rows.append((int(ids[g]), int(mapped[0]), mapped[1], xyz[members]))
    if skipped:
        warnings.warn(
            str(
                where.error(
                    f"skipped {len(skipped)} roadgraph id(s) of unknown or mixed type "
                    f"(ids {skipped[:5]})"
                )
            ),
            stacklevel=4,
        )
    return RoadMap.from_polylines(
        [r[0] for r in rows], [r[1] for r in rows], [r[2] for r in rows], [r[3] for r in rows]
    )


def _signals(feats: dict, n_steps: int, where: _Where) -> TrafficSignals:
    """One row per lane id of ``traffic_light_state/*`` ([T, S] time-major blocks)."""
    slots = _array(feats, "traffic_light_state/current/state", where, "i").shape[0]
    if slots == 0:
        return TrafficSignals.empty(n_steps)
    cols = {}
    for name in _SIGNAL_FIELDS:
        kind = "f" if name in ("x", "y", "z") else "i"
        blocks = _blocks(feats, "traffic_light_state", name, slots, where, kind, True)
        cols[name] = np.concatenate(blocks, axis=1)  # [S, T]
        if cols[name].shape[1] != n_steps:
            raise where.error(
                f"features 'traffic_light_state/*/{name}' do not hold {n_steps} steps"
            )
    ok = (cols["valid"] > 0) & (cols["id"] >= 0)
    slot, step = np.nonzero(ok)
    state = cols["state"][slot, step]
    if ((state < 0) | (state >= _NUM_SIGNAL_STATES)).any():
        k = int(np.argmax((state < 0) | (state >= _NUM_SIGNAL_STATES)))
        raise where.error(
            f"feature 'traffic_light_state/*/state': unknown state {int(state[k])} at step "
            f"{int(step[k])}"
        )
    stop = np.stack([cols[c][slot, step] for c in ("x", "y", "z")], -1).astype(np.float64)
    return signals_from_entries(step, cols["id"][slot, step], state, stop, n_steps)


# ----------------------------------------------------------------------------- records


def _scenario_id(feats: dict, where: _Where) -> str:
    value = feats.get(SCENARIO_ID_KEY)
    if not isinstance(value, list) or len(value) != 1:
        raise where.error(f"feature {SCENARIO_ID_KEY!r} is missing or not one bytes value")
    try:
        sid = value[0].decode("utf-8")
    except UnicodeDecodeError as err:
        raise where.error(f"feature {SCENARIO_ID_KEY!r} is not UTF-8: {value[0][:32]!r}") from err
    if not sid:
        raise where.error(f"feature {SCENARIO_ID_KEY!r} is empty")
    return sid


def scenario_from_features(feats: dict, where: _Where) -> Scenario:
    """Convert decoded Example features (``decode_example``) to a validated ``Scenario``."""
    sid = _scenario_id(feats, where)
    slots = _array(feats, "state/id", where, "f").shape[0]
    n_steps, current = _steps(feats, slots, where)
    tracks, keep = _tracks(feats, n_steps, where)
    sdc, ttp, difficulty, ooi = _roles(feats, keep, tracks.id, where)
    road_map = _road_map(feats, where)
    if road_map.num_features == 0:
        warnings.warn(str(where.error(f"scenario {sid!r} has no map features")), stacklevel=3)
    scenario = Scenario(
        scenario_id=sid,
        timestamps=_timestamps(feats, n_steps, where),
        current_index=current,
        tracks=tracks,
        road_map=road_map,
        signals=_signals(feats, n_steps, where),
        sdc_index=sdc,
        tracks_to_predict=ttp,
        predict_difficulty=difficulty,
        objects_of_interest=ooi,
        source=where.source,
    )
    try:
        return scenario.validate()
    except ScenarioFormatError as err:
        raise where.error(err.reason) from err


def parse_tf_example(
    payload: bytes,
    *,
    path: PathLike | None = None,
    record: int | None = None,
    offset: int | None = None,
) -> Scenario:
    """Decode one serialized WOMD ``tf.train.Example`` and convert it.

    Raises:
        ScenarioFormatError: not a valid Example, or not a usable WOMD scene (names the key).
    """
    where = _Where(None if path is None else os.fspath(path), record, offset)
    return scenario_from_features(decode_example(payload, where), where)


def read_tf_examples(
    path: PathLike, *, skip_bad: bool = False, verify: bool = True
) -> Iterator[Scenario]:
    """Yield every scenario of a TFRecord file of WOMD tf.Example records, one at a time.

    Args:
        path: the TFRecord file.
        skip_bad: warn about bad records (framing or content) and go on instead of raising.
        verify: check the TFRecord CRCs.

    Raises:
        ScenarioFormatError: bad record (unless ``skip_bad``), or no scenarios in the file.
        FileNotFoundError: no such file.
    """
    return iter_parsed_records(path, parse_tf_example, skip_bad=skip_bad, verify=verify)
