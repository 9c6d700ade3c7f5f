"""ScenarioNet / MetaDrive ``ScenarioDescription`` pickles -> typed ``Scenario``.

The pickles are read only through ``RestrictedUnpickler``, which builds nothing but numpy
arrays, dtypes and scalars, ``collections.defaultdict`` / ``OrderedDict``, plain builtins and
``ScenarioDescription`` (as ``dict``); any other global refuses the file with a
``ScenarioFormatError`` naming it, before anything runs. Never plain ``pickle.load``.

Layout (data/womd/scenarionet_more/README.md): ``{id, version, length, tracks,
dynamic_map_states, map_features, metadata}``.

* ``tracks``: ``{id string: {type, state: {position [T, 3 or 2], heading [T], velocity [T, 2],
  valid [T], length / width / height [T] or [T, 1], or size [T, 3] (length, width, height)}}}``.
  Track ids are the decimal keys, as ints. Headings are radians as stored (often off by whole
  turns): ``Tracks.heading`` is wrapped, ``Tracks.raw_heading`` keeps them.
* ``map_features``: ``{id string: {type, polyline | polygon | position, ...}}`` with ScenarioNet
  type names, mapped to ``MapFeatureType`` and WOMD subtypes by ``map_type``. Lanes keep
  their speed limit (mph), entry/exit lanes and neighbours; stop signs their lanes.
* ``dynamic_map_states``: one entry per controlled lane, in one of two layouts: ``lane`` and
  ``stop_point`` beside ``state.object_state`` ([T] names such as ``"LANE_STATE_STOP"``, None
  where no state is known), or (older MetaDrive) ``state.{lane [T], object_state [T] raw enum
  values, stop_point [T, 3]}`` where lane 0 marks a step with no state.
* ``metadata``: ``ts`` [T] seconds (else the 0.1 s grid), ``sdc_id`` (else
  ``sdc_track_index``), ``tracks_to_predict`` ``{id: {track_index, difficulty, ...}}``,
  ``objects_of_interest`` [ids], ``current_time_index``.

The current step is ``metadata.current_time_index`` when it is positive. The WOMD 20 s scenes
(197-200 steps) store 0 and the older MetaDrive files none; such a scene would have no
history, so it gets ``constants.CURRENT_INDEX`` (10), as for every other WOMD scene: 11 history
steps, and all the following ones as its future. Every stored step is kept (no cut to 91).
A scene without an SDC mark, or with no (or an empty) ``tracks_to_predict``, gets them from
``conversion.choose_sdc`` / ``choose_tracks_to_predict`` (difficulty 0).
"""

from __future__ import annotations

import collections
import io
import os
import pickle
import warnings
from typing import Any

import numpy as np

from tbsim_env.core.constants import (
    CURRENT_INDEX,
    DT,
    LaneType,
    MapFeatureType,
    ObjectType,
    RoadEdgeType,
    RoadLineType,
    SignalState,
)
from tbsim_env.core.errors import ScenarioFormatError
from tbsim_env.data.compressed import read_all
from tbsim_env.data.conversion import (
    choose_sdc,
    choose_tracks_to_predict,
    signal_state_from_name,
    signals_from_entries,
)
from tbsim_env.data.scenario import RoadMap, Scenario, Tracks, TrafficSignals
from tbsim_env.data.womd import wrap_heading_f32

try:  # numpy >= 2 keeps the array constructors in numpy._core, older ones in numpy.core
    from numpy._core import multiarray as _multiarray
except ImportError:  # pragma: no cover - numpy < 2
    from numpy.core import multiarray as _multiarray

PathLike = str | os.PathLike

PICKLE_MAGIC = b"\x80"
"""First byte of a pickle of protocol 2 or later (the PROTO opcode)."""

_NUMPY_MODULES = ("numpy.core.multiarray", "numpy._core.multiarray")


def _latin1_bytes(text: str, encoding: str = "latin1") -> bytes:
    """``_codecs.encode`` as pickle protocol 2 uses it for bytes: latin-1 only."""
    if not isinstance(text, str) or encoding not in ("latin1", "latin-1"):
        raise pickle.UnpicklingError(f"_codecs.encode with {encoding!r} is not allowed")
    return text.encode("latin1")


ALLOWED_GLOBALS: dict[tuple[str, str], Any] = {
    **{(m, "_reconstruct"): _multiarray._reconstruct for m in _NUMPY_MODULES},
    **{(m, "scalar"): _multiarray.scalar for m in _NUMPY_MODULES},
    ("numpy", "ndarray"): np.ndarray,
    ("numpy", "dtype"): np.dtype,
    ("collections", "defaultdict"): collections.defaultdict,
    ("collections", "OrderedDict"): collections.OrderedDict,
    ("metadrive.scenario.scenario_description", "ScenarioDescription"): dict,
    ("_codecs", "encode"): _latin1_bytes,  # byte strings in protocol <= 2
    **{
        ("builtins", t.__name__): t
        for t in (int, float, complex, bool, str, bytes, bytearray, list, dict, tuple, set)
    },
    ("builtins", "frozenset"): frozenset,
}
"""(module, name) -> object: every global a ScenarioNet pickle may name. Each builds plain data
and runs no other code; ``ScenarioDescription`` (a dict subclass) is read as ``dict``."""

TRACK_TYPES: dict[str, ObjectType] = {
    "VEHICLE": ObjectType.VEHICLE,
    "PEDESTRIAN": ObjectType.PEDESTRIAN,
    "CYCLIST": ObjectType.CYCLIST,
    "OTHER": ObjectType.OTHER,
    "UNSET": ObjectType.UNSET,
}

_POLYGONS = {
    "CROSSWALK": MapFeatureType.CROSSWALK,
    "CROSS_WALK": MapFeatureType.CROSSWALK,
    "SPEED_BUMP": MapFeatureType.SPEED_BUMP,
    "DRIVEWAY": MapFeatureType.DRIVEWAY,
}
MAP_TYPES: dict[str, tuple[MapFeatureType, int]] = {
    **{f"LANE_{t.name}": (MapFeatureType.LANE, int(t)) for t in LaneType},
    "LANE_UNKNOWN": (MapFeatureType.LANE, int(LaneType.UNDEFINED)),
    **{f"ROAD_LINE_{t.name}": (MapFeatureType.ROAD_LINE, int(t)) for t in RoadLineType},
    "UNKNOWN_LINE": (MapFeatureType.ROAD_LINE, int(RoadLineType.UNKNOWN)),
    **{f"ROAD_EDGE_{t.name}": (MapFeatureType.ROAD_EDGE, int(t)) for t in RoadEdgeType},
    "STOP_SIGN": (MapFeatureType.STOP_SIGN, 0),
    **{name: (kind, 0) for name, kind in _POLYGONS.items()},
}
"""ScenarioNet map type name -> (``MapFeatureType``, raw WOMD subtype). ``"UNKNOWN"`` is a
lane of undefined type when the feature carries lane fields (see ``map_type``)."""

_LANE_FIELDS = ("entry_lanes", "exit_lanes", "left_neighbor", "right_neighbor")
_NO_IDS = np.zeros(0, np.int64)
_INT64_LIMIT = 2**63


def _error(reason: str, source: str) -> ScenarioFormatError:
    return ScenarioFormatError(reason, source)


class RestrictedUnpickler(pickle.Unpickler):
    """A ``pickle.Unpickler`` that resolves only the globals in ``ALLOWED_GLOBALS``.

    Any other global (``os.system``, ``builtins.eval``, a class of some library ...) raises
    ``ScenarioFormatError`` naming its module and name, when the unpickler meets it: nothing
    it would build or call is imported or run. Persistent ids are refused too.
    """

    def __init__(self, file: io.BufferedIOBase, source: str) -> None:
        super().__init__(file)
        self.source = source

    def find_class(self, module: str, name: str) -> Any:
        try:
            return ALLOWED_GLOBALS[(module, name)]
        except (KeyError, TypeError):
            raise _error(
                f"pickle refers to {module}.{name}, which a ScenarioNet scene does not need; "
                "refused (only numpy arrays, builtins and ScenarioDescription are allowed)",
                self.source,
            ) from None

    def persistent_load(self, pid: Any) -> Any:
        raise _error("pickle uses a persistent id; refused", self.source)


def load_restricted_pickle(data: bytes, *, source: str = "<memory>") -> Any:
    """Unpickle ``data`` with ``RestrictedUnpickler``.

    Raises:
        ScenarioFormatError: a refused global, or not a readable pickle (truncated, corrupt,
            or an allowed constructor given bad arguments), naming ``source``.
    """
    try:
        return RestrictedUnpickler(io.BytesIO(data), source).load()
    except ScenarioFormatError:
        raise
    except Exception as err:  # the pickle runtime and numpy raise many types on bad input
        raise _error(f"not a readable pickle: {type(err).__name__}: {err}", source) from err


# ----------------------------------------------------------------------------- values


def _get(obj: Any, key: str, where: str, source: str) -> Any:
    if not isinstance(obj, dict):
        raise _error(f"{where}: expected a dict, got {type(obj).__name__}", source)
    if key not in obj:
        raise _error(f"{where}: missing key {key!r}", source)
    return obj[key]


def _int_id(value: Any, where: str, source: str) -> int:
    """An id stored as an int or a decimal string (ScenarioNet keys ids as strings)."""
    if isinstance(value, (bool, np.bool_)):
        raise _error(f"{where}: expected an integer id, got {value!r}", source)
    if isinstance(value, (int, np.integer)):
        out = int(value)
    elif isinstance(value, str) and value.strip().lstrip("-").isdigit() and len(value) < 20:
        out = int(value)
    else:
        raise _error(f"{where}: expected an integer id, got {value!r:.60}", source)
    if not -_INT64_LIMIT <= out < _INT64_LIMIT:
        raise _error(f"{where}: id {out} does not fit in 64 bits", source)
    return out


def _floats(value: Any, where: str, source: str) -> np.ndarray:
    if isinstance(value, (str, bytes, dict)) or value is None:
        raise _error(f"{where}: expected numbers, got {type(value).__name__}", source)
    try:
        with np.errstate(over="ignore", invalid="ignore"):
            return np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError, OverflowError) as err:
        raise _error(f"{where}: values are not numbers ({err})", source) from err


def _per_step(value: Any, n_steps: int, cols: tuple[int, ...], where: str, source: str):
    """[T, c] float64 from [T] (c = 1), [T, 1] or [T, c] with c in ``cols``."""
    arr = _floats(value, where, source)
    if arr.ndim == 1 and 1 in cols:
        arr = arr[:, None]
    if arr.ndim != 2 or arr.shape[0] != n_steps or arr.shape[1] not in cols:
        want = " or ".join(f"({n_steps}, {c})" for c in cols)
        raise _error(f"{where}: has shape {arr.shape}, expected {want}", source)
    return arr


def _xyz(arr: np.ndarray) -> np.ndarray:
    """[n, 3] from [n, 2] (z = 0) or [n, 3]."""
    return arr if arr.shape[1] == 3 else np.concatenate([arr, np.zeros((len(arr), 1))], 1)


def _valid(value: Any, n_steps: int, where: str, source: str) -> np.ndarray:
    arr = np.asarray(value) if isinstance(value, (list, tuple, np.ndarray)) else None
    if arr is None or arr.dtype.kind not in "biu" or arr.reshape(-1).shape[0] != n_steps:
        raise _error(f"{where}: expected {n_steps} booleans", source)
    return arr.reshape(-1) != 0


# ----------------------------------------------------------------------------- tracks


def _box_size(state: dict, n_steps: int, where: str, source: str) -> np.ndarray:
    """[T, 3] length, width, height from ``size`` [T, 3] or three [T] / [T, 1] arrays."""
    if "size" in state:
        return _per_step(state["size"], n_steps, (3,), f"{where}.size", source)
    parts = [
        _per_step(_get(state, k, where, source), n_steps, (1,), f"{where}.{k}", source)
        for k in ("length", "width", "height")
    ]
    return np.concatenate(parts, axis=1)


def _track_arrays(key: str, track: Any, n_steps: int | None, source: str) -> dict[str, Any]:
    """Per-step arrays of one track; ``n_steps`` None takes T from its position."""
    w = f"tracks[{key!r}]"
    type_name = _get(track, "type", w, source)
    if not isinstance(type_name, str) or type_name not in TRACK_TYPES:
        raise _error(f"{w}.type: unknown object type {type_name!r:.40}", source)
    state = _get(track, "state", w, source)
    ws = f"{w}.state"
    pos = _floats(_get(state, "position", ws, source), f"{ws}.position", source)
    if n_steps is None:
        n_steps = pos.shape[0] if pos.ndim == 2 else -1
    pos = _per_step(pos, n_steps, (2, 3), f"{ws}.position", source)
    return {
        "id": _int_id(key, f"{w} (key)", source),
        "type": int(TRACK_TYPES[type_name]),
        "pos": _xyz(pos),
        "vel": _per_step(
            _get(state, "velocity", ws, source), n_steps, (2,), f"{ws}.velocity", source
        ),
        "heading": _per_step(
            _get(state, "heading", ws, source), n_steps, (1,), f"{ws}.heading", source
        )[:, 0],
        "valid": _valid(_get(state, "valid", ws, source), n_steps, f"{ws}.valid", source),
        "size": _box_size(state, n_steps, ws, source),
    }


def _tracks(tracks: Any, n_steps: int | None, source: str) -> Tracks:
    """All tracks, in the dict's order.

    Args:
        tracks: the ``tracks`` dict.
        n_steps: T when known from the metadata, else taken from the first track.
    """
    if not isinstance(tracks, dict) or not tracks:
        raise _error("'tracks' must be a non-empty dict (a scenario needs a track)", source)
    keys = list(tracks)
    first = _track_arrays(keys[0], tracks[keys[0]], n_steps, source)
    n = first["valid"].shape[0]
    per = [first] + [_track_arrays(k, tracks[k], n, source) for k in keys[1:]]
    valid = np.stack([p["valid"] for p in per])  # [A, T]
    heading = np.stack([p["heading"] for p in per])  # [A, T] radians as stored
    v3 = valid[..., None]
    with np.errstate(over="ignore", invalid="ignore"):
        out = Tracks(
            id=np.array([p["id"] for p in per], np.int64),
            object_type=np.array([p["type"] for p in per], np.int8),
            xyz=np.where(v3, np.stack([p["pos"] for p in per]), 0.0),
            heading=np.where(valid, wrap_heading_f32(heading), np.float32(0.0)),
            velocity=np.where(v3, np.stack([p["vel"] for p in per]), 0.0).astype(np.float32),
            size=np.where(v3, np.stack([p["size"] for p in per]), 0.0).astype(np.float32),
            valid=valid,
            raw_heading=np.where(valid, heading, 0.0).astype(np.float32),
        )
    return out


# ----------------------------------------------------------------------------- map


def map_type(type_name: Any, feature: dict) -> tuple[MapFeatureType, int] | None:
    """(``MapFeatureType``, raw WOMD subtype) of a ScenarioNet map feature, or None if unknown.

    ``MAP_TYPES`` names every WOMD lane, road-line and road-edge subtype (``LANE_FREEWAY``,
    ``ROAD_LINE_SOLID_DOUBLE_YELLOW``, ``ROAD_EDGE_MEDIAN`` ...), stop signs, crosswalks
    (``CROSSWALK`` or ``CROSS_WALK``), speed bumps and driveways. ``UNKNOWN`` is what
    ScenarioNet writes for a lane of type TYPE_UNDEFINED: a lane when the feature carries lane
    fields (``entry_lanes`` ...), else unknown.
    """
    if not isinstance(type_name, str):
        return None
    if type_name == "UNKNOWN":
        return (MapFeatureType.LANE, 0) if any(k in feature for k in _LANE_FIELDS) else None
    return MAP_TYPES.get(type_name)


def _ids(value: Any, where: str, source: str) -> np.ndarray:
    """[n] int64 from a list of ids (ints or decimal strings)."""
    if not isinstance(value, (list, tuple, np.ndarray)):
        raise _error(f"{where}: expected a list of ids, got {type(value).__name__}", source)
    out = [_int_id(v, f"{where}[{i}]", source) for i, v in enumerate(value)]
    return np.asarray(out, np.int64).reshape(-1)


def _neighbor_ids(value: Any, where: str, source: str) -> np.ndarray:
    """[n] int64 neighbour lane ids from a list of ``{feature_id, ...}``."""
    if not isinstance(value, (list, tuple)):
        raise _error(f"{where}: expected a list, got {type(value).__name__}", source)
    out = [
        _int_id(_get(n, "feature_id", f"{where}[{i}]", source), f"{where}[{i}]", source)
        for i, n in enumerate(value)
    ]
    return np.asarray(out, np.int64).reshape(-1)


def _geometry(feature: dict, kind: MapFeatureType, where: str, source: str) -> np.ndarray:
    """[n, 3] float64: a stop sign's position, else its polygon or polyline (n may be 0)."""
    if kind == MapFeatureType.STOP_SIGN:
        pos = _floats(_get(feature, "position", where, source), f"{where}.position", source)
        if pos.size not in (2, 3):
            raise _error(f"{where}.position: has shape {pos.shape}, expected (3,)", source)
        return _xyz(pos.reshape(1, -1))
    key = "polygon" if "polygon" in feature else "polyline"
    pts = _floats(_get(feature, key, where, source), f"{where}.{key}", source)
    if pts.size == 0:
        return np.zeros((0, 3))
    if pts.ndim != 2 or pts.shape[1] not in (2, 3):
        raise _error(f"{where}.{key}: has shape {pts.shape}, expected (n, 3)", source)
    return _xyz(pts)


def _lane_links(feature: dict, where: str, source: str) -> tuple[float, list[np.ndarray]]:
    """(speed limit mph, [entry, exit, left, right] lane ids) of a lane feature."""
    speed = feature.get("speed_limit_mph", 0.0)
    if isinstance(speed, bool) or not isinstance(speed, (int, float, np.number)):
        raise _error(f"{where}.speed_limit_mph: expected a number, got {speed!r:.40}", source)
    links = [
        _ids(feature.get("entry_lanes", []), f"{where}.entry_lanes", source),
        _ids(feature.get("exit_lanes", []), f"{where}.exit_lanes", source),
        _neighbor_ids(feature.get("left_neighbor", []), f"{where}.left_neighbor", source),
        _neighbor_ids(feature.get("right_neighbor", []), f"{where}.right_neighbor", source),
    ]
    return float(speed), links


def _road_map(features: Any, source: str) -> RoadMap:
    """Static map in the dict's order; unknown types and empty geometry are skipped (warned)."""
    if not isinstance(features, dict):
        raise _error(f"'map_features' must be a dict, got {type(features).__name__}", source)
    rows: list[tuple] = []
    skipped: list[str] = []
    for key, feature in features.items():
        w = f"map_features[{key!r}]"
        kind = map_type(_get(feature, "type", w, source), feature)
        if kind is None:
            skipped.append(f"{w} (type {feature['type']!r:.40})")
            continue
        pts = _geometry(feature, kind[0], w, source)
        if pts.shape[0] == 0:
            skipped.append(f"{w} (no geometry)")
            continue
        speed, links = 0.0, [_NO_IDS] * 4
        if kind[0] == MapFeatureType.LANE:
            speed, links = _lane_links(feature, w, source)
        lanes = _NO_IDS
        if kind[0] == MapFeatureType.STOP_SIGN:
            lanes = _ids(feature.get("lane", []), f"{w}.lane", source)
        rows.append((_int_id(key, f"{w} (key)", source), kind, pts, speed, links, lanes))
    if skipped:
        warnings.warn(
            str(_error(f"skipped {len(skipped)} map feature(s): {', '.join(skipped[:5])}", source)),
            stacklevel=3,
        )
    if not rows:
        return RoadMap.empty()
    with np.errstate(over="ignore", invalid="ignore"):
        speed_mph = np.array([r[3] for r in rows], np.float32)
    return RoadMap(
        id=np.array([r[0] for r in rows], np.int64),
        feature_type=np.array([int(r[1][0]) for r in rows], np.int8),
        subtype=np.array([r[1][1] for r in rows], np.int8),
        polylines=tuple(r[2] for r in rows),
        speed_limit_mph=speed_mph,
        entry_lanes=tuple(r[4][0] for r in rows),
        exit_lanes=tuple(r[4][1] for r in rows),
        left_neighbors=tuple(r[4][2] for r in rows),
        right_neighbors=tuple(r[4][3] for r in rows),
        controlled_lanes=tuple(r[5] for r in rows),
    )


# ----------------------------------------------------------------------------- signals

_NUM_SIGNAL_STATES = len(SignalState)
_SignalRows = tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]


def _state_value(value: Any, where: str, source: str) -> int | None:
    """Raw ``SignalState`` of one stored step: a state name, an enum value, or None (no state)."""
    if value is None:
        return None
    if isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_)):
        if 0 <= value < _NUM_SIGNAL_STATES:
            return int(value)
    elif isinstance(value, str) and signal_state_from_name(value) is not None:
        return int(signal_state_from_name(value))
    raise _error(f"{where}: unknown traffic-signal state {value!r:.40}", source)


def _named_states(entry: dict, n_steps: int, w: str, source: str) -> _SignalRows:
    """Layout ``{lane, stop_point, state: {object_state: [T] names or None}}``."""
    lane = _int_id(entry["lane"], f"{w}.lane", source)
    stop = _floats(_get(entry, "stop_point", w, source), f"{w}.stop_point", source)
    if stop.size not in (2, 3):
        raise _error(f"{w}.stop_point: has shape {stop.shape}, expected (3,)", source)
    states = _get(entry["state"], "object_state", f"{w}.state", source)
    if not isinstance(states, (list, tuple, np.ndarray)) or len(states) != n_steps:
        raise _error(f"{w}.state.object_state: expected {n_steps} states", source)
    values = [_state_value(v, f"{w}.state.object_state[{t}]", source) for t, v in enumerate(states)]
    steps = np.array([t for t, v in enumerate(values) if v is not None], np.int64)
    return (
        steps,
        np.full(steps.shape[0], lane, np.int64),
        np.array([v for v in values if v is not None], np.int64),
        np.tile(_xyz(stop.reshape(1, -1)), (steps.shape[0], 1)),
    )


def _per_step_states(state: dict, n_steps: int, w: str, source: str) -> _SignalRows:
    """Older MetaDrive layout ``state: {lane [T], object_state [T], stop_point [T, 3]}``.

    Steps whose lane is 0 hold no state (the converter's placeholder).
    """
    arrays = []
    for key in ("lane", "object_state"):
        arr = np.asarray(_get(state, key, f"{w}.state", source))
        if arr.dtype.kind not in "iu" or arr.reshape(-1).shape[0] != n_steps:
            raise _error(f"{w}.state.{key}: expected {n_steps} integers", source)
        arrays.append(arr.reshape(-1).astype(np.int64))
    lanes, states = arrays
    stop_raw = _get(state, "stop_point", f"{w}.state", source)
    stops = _per_step(stop_raw, n_steps, (2, 3), f"{w}.state.stop_point", source)
    steps = np.flatnonzero(lanes != 0)
    if len(np.unique(lanes[steps])) > 1:
        raise _error(f"{w}.state.lane: names more than one lane", source)
    bad = (states[steps] < 0) | (states[steps] >= _NUM_SIGNAL_STATES)
    if bad.any():
        t = int(steps[np.argmax(bad)])
        raise _error(f"{w}.state.object_state[{t}]: unknown state {int(states[t])}", source)
    return steps, lanes[steps], states[steps], _xyz(stops)[steps]


def _signals(dynamic: Any, n_steps: int, source: str) -> TrafficSignals:
    """One row per controlled lane; entries of another type than TRAFFIC_LIGHT are skipped."""
    if not isinstance(dynamic, dict):
        raise _error(f"'dynamic_map_states' must be a dict, got {type(dynamic).__name__}", source)
    parts: list[_SignalRows] = []
    for key, entry in dynamic.items():
        w = f"dynamic_map_states[{key!r}]"
        state = _get(entry, "state", w, source)
        kind = entry.get("type", "TRAFFIC_LIGHT")
        if not isinstance(kind, str) or kind != "TRAFFIC_LIGHT":
            continue
        if not isinstance(state, dict):
            raise _error(f"{w}.state: expected a dict, got {type(state).__name__}", source)
        if "lane" in entry:
            parts.append(_named_states(entry, n_steps, w, source))
        else:
            parts.append(_per_step_states(state, n_steps, w, source))
    if not parts:
        return TrafficSignals.empty(n_steps)
    step, lane, state, stop = (np.concatenate(p) for p in zip(*parts))
    return signals_from_entries(step, lane, state, stop.reshape(-1, 3), n_steps)


# ----------------------------------------------------------------------------- metadata


def _timestamps(meta: dict, n_steps: int, source: str) -> np.ndarray:
    """[T] float64 seconds from ``metadata.ts``, else the ``DT`` grid."""
    if meta.get("ts") is None:
        return np.arange(n_steps, dtype=np.float64) * DT
    ts = _floats(meta["ts"], "metadata.ts", source)
    if ts.shape != (n_steps,):
        raise _error(f"metadata.ts: has shape {ts.shape}, expected ({n_steps},)", source)
    if not np.isfinite(ts).all():
        raise _error("metadata.ts: has a non-finite value", source)
    if n_steps > 1 and not (np.diff(ts) > 0).all():
        step = int(np.argmax(np.diff(ts) <= 0)) + 1
        raise _error(f"metadata.ts: is not increasing at step {step}", source)
    return ts


def _current_index(meta: dict, source: str) -> int:
    """``metadata.current_time_index`` when positive, else ``CURRENT_INDEX`` (see module doc)."""
    value = meta.get("current_time_index")
    if value is None:
        return CURRENT_INDEX
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
        raise _error(f"metadata.current_time_index: expected an integer, got {value!r:.40}", source)
    if value < 0:
        raise _error(f"metadata.current_time_index: {int(value)} is negative", source)
    return int(value) if value > 0 else CURRENT_INDEX


def _sdc_index(meta: dict, id_to_index: dict[int, int], source: str) -> int | None:
    """Index of the SDC from ``sdc_id`` and/or ``sdc_track_index`` (None when neither)."""
    by_id = by_index = None
    if meta.get("sdc_id") is not None:
        sdc_id = _int_id(meta["sdc_id"], "metadata.sdc_id", source)
        if sdc_id not in id_to_index:
            raise _error(f"metadata.sdc_id: no track has id {sdc_id}", source)
        by_id = id_to_index[sdc_id]
    if meta.get("sdc_track_index") is not None:
        by_index = _int_id(meta["sdc_track_index"], "metadata.sdc_track_index", source)
        if not 0 <= by_index < len(id_to_index):
            raise _error(f"metadata.sdc_track_index: {by_index} outside the track list", source)
    if by_id is not None and by_index is not None and by_id != by_index:
        raise _error(
            f"metadata.sdc_track_index {by_index} is not the track of sdc_id (index {by_id})",
            source,
        )
    return by_id if by_id is not None else by_index


def _tracks_to_predict(
    meta: dict, id_to_index: dict[int, int], source: str
) -> tuple[np.ndarray, np.ndarray] | None:
    """([k] track indices, [k] difficulties) from ``{id: {difficulty, ...}}``; None if empty."""
    ttp = meta.get("tracks_to_predict")
    if ttp is None or (isinstance(ttp, dict) and not ttp):
        return None
    if not isinstance(ttp, dict):
        raise _error(
            f"metadata.tracks_to_predict: expected a dict, got {type(ttp).__name__}", source
        )
    index, difficulty = [], []
    for key, entry in ttp.items():
        w = f"metadata.tracks_to_predict[{key!r}]"
        if not isinstance(entry, dict):
            raise _error(f"{w}: expected a dict, got {type(entry).__name__}", source)
        track_id = _int_id(entry.get("track_id", key), w, source)
        if track_id not in id_to_index:
            raise _error(f"{w}: no track has id {track_id}", source)
        level = entry.get("difficulty", 0)
        if (
            isinstance(level, bool)
            or not isinstance(level, (int, np.integer))
            or not 0 <= level < 128
        ):
            raise _error(f"{w}.difficulty: expected a small integer, got {level!r:.40}", source)
        index.append(id_to_index[track_id])
        difficulty.append(int(level))
    return np.asarray(index, np.int64), np.asarray(difficulty, np.int8)


def scenario_from_scenarionet(data: Any, *, source: str = "<memory>") -> Scenario:
    """Convert an unpickled ``ScenarioDescription`` (a dict) to a validated ``Scenario``.

    Args:
        data: the unpickled scene (see the module docstring for its layout and what fills
            the marks it lacks).
        source: file name for messages and ``Scenario.source``.

    Raises:
        ScenarioFormatError: missing or malformed keys (naming the key, track or feature).
    """
    if not isinstance(data, dict):
        raise _error(
            f"top level: expected a ScenarioDescription dict, got {type(data).__name__}", source
        )
    meta = data.get("metadata", {})
    if not isinstance(meta, dict):
        raise _error(f"'metadata' must be a dict, got {type(meta).__name__}", source)
    sid = data.get("id", meta.get("scenario_id"))
    if not isinstance(sid, str) or not sid:
        raise _error(f"top level: 'id' must be a non-empty string, got {sid!r:.40}", source)
    tracks = _tracks(_get(data, "tracks", "top level", source), None, source)
    n_steps = tracks.num_steps
    length = data.get("length", n_steps)
    if isinstance(length, bool) or not isinstance(length, (int, np.integer)) or length != n_steps:
        raise _error(
            f"top level: 'length' {length!r:.20} but the tracks hold {n_steps} steps", source
        )
    road_map = _road_map(_get(data, "map_features", "top level", source), source)
    if road_map.num_features == 0:
        warnings.warn(str(_error(f"scenario {sid!r} has no map features", source)), stacklevel=2)
    current = _current_index(meta, source)
    id_to_index = {int(i): k for k, i in enumerate(tracks.id)}
    sdc = _sdc_index(meta, id_to_index, source)
    if sdc is None:
        sdc = choose_sdc(tracks, road_map, min(current, n_steps - 1))
    ttp = _tracks_to_predict(meta, id_to_index, source)
    if ttp is None:
        chosen = choose_tracks_to_predict(tracks, sdc, min(current, n_steps - 1))
        ttp = (chosen, np.zeros(chosen.shape[0], np.int8))
    ooi = meta.get("objects_of_interest")
    ooi = _ids([] if ooi is None else ooi, "metadata.objects_of_interest", source)
    scenario = Scenario(
        scenario_id=sid,
        timestamps=_timestamps(meta, n_steps, source),
        current_index=current,
        tracks=tracks,
        road_map=road_map,
        signals=_signals(data.get("dynamic_map_states", {}), n_steps, source),
        sdc_index=sdc,
        tracks_to_predict=ttp[0],
        predict_difficulty=ttp[1],
        objects_of_interest=ooi,
        source=source,
    )
    return scenario.validate()


def read_scenarionet_pickle(path: PathLike) -> Scenario:
    """Read one ScenarioNet / MetaDrive scenario pickle (plain or gzip-compressed) through
    ``RestrictedUnpickler``.

    Raises:
        FileNotFoundError: no such file.
        ScenarioFormatError: a refused global, not a pickle, bad gzip data, or not a ScenarioNet
            scene (naming the key, track or feature at fault).
    """
    name = os.fspath(path)
    data = read_all(name)
    return scenario_from_scenarionet(load_restricted_pickle(data, source=name), source=name)
