"""GPUDrive and Nocturne JSON (conversions of one WOMD scenario) -> typed ``Scenario``.

Format (see data/womd/README.md, section 2): ``objects`` in ``Scenario.tracks`` order with
per-step ``position`` / ``velocity`` / ``heading`` / ``valid`` lists (invalid steps hold the
sentinel -10000), box sizes as scalars (the last valid state's), ``roads`` with GPUDrive map
types, ``tl_states`` and a ``metadata`` block with the WOMD indices and ids.

Every dialect of data/womd/gpudrive_history/README.md and data/womd/nocturne/ is read:

* ``gpudrive``: as above. ``gpudrive_early``: no ``metadata``, objects mostly without ``id``.
  ``nocturne_format`` / Nocturne: no ``scenario_id``, no ``metadata``, no object or road ids,
  2-D positions, no ``height``, and positions possibly as struct of arrays
  (``{"x": [T], "y": [T]}``).
* Objects without ``id`` (all objects of a file carry one, or none does) get ids 1, 2, ... in
  file order, and their ``heading`` is in **degrees** (not wrapped): only objects with an id
  store radians. Roads without ``id`` get ids 1, 2, ... likewise. (Both as in the WOSAC
  reference conversion of a Nocturne scene, data/womd/wosac_reference/README.md.)
* A missing ``height`` is ``conversion.DEFAULT_BOX_HEIGHT_M`` (1.5 m), a missing ``z`` 0.
  Length and width both 0 mean the converter recorded no size (58 objects of the three
  ``nocturne/`` files, many valid for most steps): such objects get the typical size of their
  type (``conversion.fill_unknown_sizes``), with a warning.
* A missing ``scenario_id`` is the stem of the file name (``tfrecord-00082-of-01000_465``).
* Without ``metadata`` the SDC is ``conversion.choose_sdc`` (the vehicle valid at every step
  nearest the centre of the map), the tracks to predict ``conversion.choose_tracks_to_predict``
  (up to 8 other objects valid from step 10 on whose path from there is longest, over 2 m;
  difficulty 0), and there are no objects of interest: the rule of the WOSAC reference
  conversion.
* ``tl_states`` maps a lane id to ``{state: [names], x, y[, z], time_index}`` lists, one entry
  per step with a known state (``time_index`` may be left out when the lists cover every step).
  When the roads carry no ids, a signal's lane is the lane whose first point lies at its stop
  point (within ``SIGNAL_LANE_MATCH_M``); a signal with no such lane is dropped with a warning.

What the JSON does not carry is filled as follows: timestamps are the 0.1 s grid
(``constants.DT``) and the current step is ``constants.CURRENT_INDEX``; sizes are broadcast over
steps; lane speed limits, entry/exit lanes, neighbours and stop-sign lanes are empty. Invalid
entries are zeroed, headings wrapped to [-pi, pi) (``Tracks.raw_heading`` keeps them unwrapped,
in radians).
"""

from __future__ import annotations

import json
import os
import warnings
from typing import Any

import numpy as np

from tbsim_env.core.constants import (
    CURRENT_INDEX,
    DT,
    MAX_FEATURE_ID,
    MAX_TRACK_ID,
    NUM_DIFFICULTY_LEVELS,
    MapFeatureType,
    ObjectType,
)
from tbsim_env.core.errors import ScenarioFormatError
from tbsim_env.data.compressed import read_all
from tbsim_env.data.conversion import (
    DEFAULT_BOX_HEIGHT_M,
    choose_sdc,
    choose_tracks_to_predict,
    fill_unknown_sizes,
    signal_state_from_name,
    signals_from_entries,
)
from tbsim_env.data.scenario import RoadMap, Scenario, Tracks, TrafficSignals
from tbsim_env.data.womd import wrap_heading_f32

PathLike = str | os.PathLike

INVALID_SENTINEL = -10000.0
"""Value GPUDrive writes into position/velocity/heading at invalid steps."""
_INT64 = 2**63
SIGNAL_LANE_MATCH_M = 0.5
"""Metres. Largest distance from a signal's stop point to the first point of the lane it is
matched to when the roads carry no ids (the controlled lane starts at the stop point: 0.00 m
in every gpudrive_early scene, whose roads carry ids)."""

OBJECT_TYPES: dict[str, ObjectType] = {
    "unset": ObjectType.UNSET,
    "vehicle": ObjectType.VEHICLE,
    "pedestrian": ObjectType.PEDESTRIAN,
    "cyclist": ObjectType.CYCLIST,
    "other": ObjectType.OTHER,
}

ROAD_TYPES: dict[str, MapFeatureType] = {
    "lane": MapFeatureType.LANE,
    "road_line": MapFeatureType.ROAD_LINE,
    "road_edge": MapFeatureType.ROAD_EDGE,
    "stop_sign": MapFeatureType.STOP_SIGN,
    "crosswalk": MapFeatureType.CROSSWALK,
    "speed_bump": MapFeatureType.SPEED_BUMP,
    "driveway": MapFeatureType.DRIVEWAY,
}


def map_element_to_feature(element_id: int) -> tuple[MapFeatureType, int] | None:
    """GPUDrive ``map_element_id`` -> (``MapFeatureType``, raw WOMD subtype).

    GPUDrive numbers map elements like the WOMD tf.Example ``roadgraph_samples/type`` (also
    Waymax ``MapElementIds``): the WOMD sub-enums laid end to end with gaps. Lane types
    0-3 are ``LaneCenter.LaneType`` 0-3 as is; 4 is unused; 5-13 are ``RoadLine.RoadLineType``
    0-8 (offset 5); 14-16 are ``RoadEdge.RoadEdgeType`` 0-2 (offset 14); then 17 stop sign,
    18 crosswalk, 19 speed bump, 20 driveway (no subtype). Checked against the three sample
    files: every road's ``type`` string agrees with its id range, ``road_line`` ids are 6, 7
    and 12 (broken single white, solid single white, solid double yellow: the usual lane and
    centre markings) and ``road_edge`` ids are 15 (boundary, i.e. curbs), consistent with this
    reading and not with a 0-based one.

    Returns:
        The pair, or ``None`` for -1 (unknown) and any id outside the table.
    """
    if 0 <= element_id <= 3:
        return MapFeatureType.LANE, element_id
    if 5 <= element_id <= 13:
        return MapFeatureType.ROAD_LINE, element_id - 5
    if 14 <= element_id <= 16:
        return MapFeatureType.ROAD_EDGE, element_id - 14
    fixed = {
        17: MapFeatureType.STOP_SIGN,
        18: MapFeatureType.CROSSWALK,
        19: MapFeatureType.SPEED_BUMP,
        20: MapFeatureType.DRIVEWAY,
    }
    if element_id in fixed:
        return fixed[element_id], 0
    return None


class _Ctx:
    """Error helper bound to one file."""

    def __init__(self, path: str) -> None:
        self.path = path

    def error(self, reason: str) -> ScenarioFormatError:
        return ScenarioFormatError(reason, self.path)


def _get(obj: Any, key: str, where: str, ctx: _Ctx) -> Any:
    if not isinstance(obj, dict):
        raise ctx.error(f"{where}: expected a JSON object, got {type(obj).__name__}")
    if key not in obj:
        raise ctx.error(f"{where}: missing key {key!r}")
    return obj[key]


def _is_number(value: Any) -> bool:
    """A JSON number: int or float, not a boolean (``true`` is not 1.0 here)."""
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _first_non_number(rows: Any) -> tuple[bool, Any]:
    """(found, leaf): the first leaf of a number or a (nested) list of numbers that is not a
    JSON number (``_is_number``)."""
    if isinstance(rows, (list, tuple)):
        for item in rows:
            found, leaf = _first_non_number(item)
            if found:
                return True, leaf
        return False, None
    return (False, None) if _is_number(rows) else (True, rows)


def _array(rows: Any, dtype: type, where: str, ctx: _Ctx) -> np.ndarray:
    """``rows`` (a number or nested lists of numbers) as an array; booleans, strings, nulls
    and integers beyond float64 are refused."""
    found, leaf = _first_non_number(rows)
    if found:
        raise ctx.error(f"{where}: expected numbers, got {leaf!r:.40}")
    try:
        return np.asarray(rows, dtype=dtype)
    except (TypeError, ValueError, OverflowError) as err:
        raise ctx.error(f"{where}: values are not numbers of this range ({err})") from err


def _int(value: Any, where: str, ctx: _Ctx, lo: int, hi: int) -> int:
    """A JSON integer in [lo, hi] (booleans and non-integral numbers are refused)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ctx.error(f"{where}: expected an integer, got {value!r:.40}")
    if not lo <= value <= hi:
        text = (
            str(value) if value.bit_length() <= 128 else f"an integer of {value.bit_length()} bits"
        )
        raise ctx.error(f"{where}: {text} outside [{lo}, {hi}]")
    return value


def _xyz_columns(points: dict, keys: tuple[str, ...], where: str, ctx: _Ctx) -> np.ndarray:
    """[n, len(keys)] float64 from a struct of arrays {"x": [n], "y": [n], ...} (z: 0)."""
    cols = []
    for key in keys:
        if key == "z" and "z" not in points:
            cols.append(None)
            continue
        col = _array(_get(points, key, where, ctx), np.float64, f"{where}.{key}", ctx)
        if col.ndim != 1:
            raise ctx.error(f"{where}.{key}: expected a list of numbers")
        cols.append(col)
    n = {c.shape[0] for c in cols if c is not None}
    if len(n) != 1:
        raise ctx.error(f"{where}: the lists {keys} have different lengths")
    return np.stack([np.zeros(n.pop()) if c is None else c for c in cols], axis=1)


def _xyz_rows(points: Any, keys: tuple[str, ...], where: str, ctx: _Ctx) -> np.ndarray:
    """[n, len(keys)] float64 from a list of {"x", "y", ...} dicts, or from a struct of
    arrays {"x": [n], "y": [n], ...} (z defaults to 0)."""
    if isinstance(points, dict):
        return _xyz_columns(points, keys, where, ctx)
    if not isinstance(points, list):
        raise ctx.error(f"{where}: expected a list, got {type(points).__name__}")
    try:
        rows = [tuple(p[k] if k != "z" else p.get("z", 0.0) for k in keys) for p in points]
    except (KeyError, TypeError, AttributeError, IndexError, ValueError) as err:
        bad = next(
            (
                i
                for i, p in enumerate(points)
                if not isinstance(p, dict) or not {"x", "y"} <= p.keys()
            ),
            0,
        )
        raise ctx.error(f"{where}[{bad}]: expected an object with keys {keys} ({err!r})") from err
    return _array(rows, np.float64, where, ctx).reshape(-1, len(keys))


def _object_arrays(obj: Any, k: int, ctx: _Ctx, has_ids: bool) -> dict[str, Any]:
    """Per-step arrays of one object (index ``k`` in ``objects``).

    ``has_ids``: the file's objects carry ``id`` (heading in radians); else the id is k + 1
    and the heading is in degrees.
    """
    w = f"objects[{k}]"
    pos = _xyz_rows(_get(obj, "position", w, ctx), ("x", "y", "z"), f"{w}.position", ctx)
    vel = _xyz_rows(_get(obj, "velocity", w, ctx), ("x", "y"), f"{w}.velocity", ctx)
    heading = _array(_get(obj, "heading", w, ctx), np.float64, f"{w}.heading", ctx)
    valid_raw = _get(obj, "valid", w, ctx)
    if not isinstance(valid_raw, list) or not all(
        isinstance(v, bool) or (isinstance(v, int) and v in (0, 1)) for v in valid_raw
    ):
        raise ctx.error(f"{w}.valid: expected a list of booleans")
    valid = np.asarray(valid_raw, dtype=bool)
    lengths = {len(pos), len(vel), heading.reshape(-1).shape[0], len(valid)}
    if len(lengths) != 1 or heading.ndim != 1:
        raise ctx.error(
            f"{w}: position/velocity/heading/valid have different lengths "
            f"({len(pos)}, {len(vel)}, {heading.size}, {len(valid)})"
        )
    if not has_ids:
        heading = np.deg2rad(heading)
    size = [
        _array(_get(obj, key, w, ctx), np.float64, f"{w}.{key}", ctx) for key in ("length", "width")
    ]
    size.append(_array(obj.get("height", DEFAULT_BOX_HEIGHT_M), np.float64, f"{w}.height", ctx))
    if any(s.ndim != 0 for s in size):
        raise ctx.error(f"{w}: 'length', 'width' and 'height' must be numbers")
    type_name = _get(obj, "type", w, ctx)
    if not isinstance(type_name, str) or type_name not in OBJECT_TYPES:
        raise ctx.error(f"{w}.type: unknown object type {type_name!r}")
    obj_id = _int(_get(obj, "id", w, ctx), f"{w}.id", ctx, 0, MAX_TRACK_ID) if has_ids else k + 1
    return {
        "id": obj_id,
        "type": int(OBJECT_TYPES[type_name]),
        "pos": pos,
        "vel": vel,
        "heading": heading,
        "valid": valid,
        "size": np.stack(size),
    }


def _tracks(objects: Any, ctx: _Ctx) -> Tracks:
    if not isinstance(objects, list) or not objects:
        raise ctx.error("key 'objects' must be a non-empty list (a scenario needs a track)")
    has_ids = any(isinstance(obj, dict) and "id" in obj for obj in objects)
    per = [_object_arrays(obj, k, ctx, has_ids) for k, obj in enumerate(objects)]
    steps = np.array([p["valid"].shape[0] for p in per])
    if (steps != steps[0]).any():
        k = int(np.argmax(steps != steps[0]))
        raise ctx.error(
            f"objects[{k}]: has {int(steps[k])} steps but objects[0] has {int(steps[0])}"
        )
    valid = np.stack([p["valid"] for p in per])  # [A, T]
    pos = np.stack([p["pos"] for p in per])  # [A, T, 3]
    vel = np.stack([p["vel"] for p in per])  # [A, T, 2]
    heading = np.stack([p["heading"] for p in per])  # [A, T]
    size = np.stack([p["size"] for p in per])  # [A, 3] length, width, height
    size, unknown = fill_unknown_sizes(size, np.array([p["type"] for p in per]))
    if (unknown & valid.any(axis=1)).any():
        k = np.flatnonzero(unknown & valid.any(axis=1))
        warnings.warn(
            str(
                ctx.error(
                    f"{len(k)} object(s) with length and width 0 (size not recorded, "
                    f"objects {k[:5].tolist()}...) get the typical size of their type"
                )
            ),
            stacklevel=3,
        )
    sentinel = valid & (pos[..., 0] == INVALID_SENTINEL) & (pos[..., 1] == INVALID_SENTINEL)
    if sentinel.any():
        k, t = (int(i) for i in np.argwhere(sentinel)[0])
        raise ctx.error(
            f"objects[{k}]: step {t} is marked valid but its position is the invalid "
            f"sentinel {INVALID_SENTINEL}"
        )
    v3 = valid[..., None]
    with np.errstate(over="ignore", invalid="ignore"):
        return Tracks(
            id=np.array([p["id"] for p in per], dtype=np.int64),
            object_type=np.array([p["type"] for p in per], dtype=np.int8),
            xyz=np.where(v3, pos, 0.0),
            heading=np.where(valid, wrap_heading_f32(heading), np.float32(0.0)),
            velocity=np.where(v3, vel, 0.0).astype(np.float32),
            size=np.where(v3, size[:, None, :], 0.0).astype(np.float32),
            valid=valid,
            raw_heading=np.where(valid, heading, 0.0).astype(np.float32),
        )


def _road_map(roads: Any, ctx: _Ctx) -> RoadMap:
    """Roads in file order; ids k + 1 when no road carries ``id`` (see the module docstring)."""
    if not isinstance(roads, list):
        raise ctx.error("key 'roads' must be a list")
    has_ids = _roads_have_ids(roads)
    ids: list[int] = []
    kinds: list[int] = []
    subtypes: list[int] = []
    polylines: list[np.ndarray] = []
    skipped: list[str] = []
    for k, road in enumerate(roads):
        w = f"roads[{k}]"
        type_name = _get(road, "type", w, ctx)
        element = road.get("map_element_id")
        is_int = isinstance(element, int) and not isinstance(element, bool)
        mapped = map_element_to_feature(element) if is_int else None
        if mapped is None:
            if not isinstance(type_name, str) or type_name not in ROAD_TYPES:
                skipped.append(f"{w} (type {type_name!r}, map_element_id {element!r})")
                continue
            # No usable element id: take the kind from the type string, subtype unknown.
            mapped = (ROAD_TYPES[type_name], 0)
        elif not isinstance(type_name, str) or ROAD_TYPES.get(type_name) != mapped[0]:
            raise ctx.error(
                f"{w}: type {type_name!r} disagrees with map_element_id {element} "
                f"({mapped[0].name.lower()})"
            )
        feature_id = (
            _int(_get(road, "id", w, ctx), f"{w}.id", ctx, 0, MAX_FEATURE_ID) if has_ids else k + 1
        )
        pts = _xyz_rows(_get(road, "geometry", w, ctx), ("x", "y", "z"), f"{w}.geometry", ctx)
        if pts.shape[0] == 0:
            skipped.append(f"{w} (no geometry)")
            continue
        ids.append(feature_id)
        kinds.append(int(mapped[0]))
        subtypes.append(mapped[1])
        polylines.append(pts)
    if skipped:
        warnings.warn(
            str(ctx.error(f"skipped {len(skipped)} road(s): {', '.join(skipped[:5])}")),
            stacklevel=3,
        )
    return RoadMap.from_polylines(ids, kinds, subtypes, polylines)


def _roads_have_ids(roads: Any) -> bool:
    return isinstance(roads, list) and any(isinstance(r, dict) and "id" in r for r in roads)


def _int_list(value: Any, where: str, ctx: _Ctx, lo: int, hi: int) -> np.ndarray:
    """[n] int64 from a JSON list of integers in [lo, hi]."""
    if not isinstance(value, list):
        raise ctx.error(f"{where}: expected a list of integers")
    out = [_int(v, f"{where}[{i}]", ctx, lo, hi) for i, v in enumerate(value)]
    return np.asarray(out, np.int64).reshape(-1)


def _tl_entry(
    key: str, entry: Any, n_steps: int, ctx: _Ctx
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """([n] steps, [n] raw states, [n, 3] stop points) of one ``tl_states`` lane."""
    w = f"tl_states[{key!r}]"
    names = _get(entry, "state", w, ctx)
    if not isinstance(names, list):
        raise ctx.error(f"{w}.state: expected a list of state names")
    states = [signal_state_from_name(name) for name in names]
    if None in states:
        i = states.index(None)
        raise ctx.error(f"{w}.state[{i}]: unknown traffic-signal state {names[i]!r:.40}")
    if "time_index" in entry:
        steps = _int_list(entry["time_index"], f"{w}.time_index", ctx, -_INT64, _INT64 - 1)
    elif len(names) == n_steps:
        steps = np.arange(n_steps, dtype=np.int64)
    else:
        raise ctx.error(f"{w}: missing key 'time_index' ({len(names)} states, {n_steps} steps)")
    stops = _xyz_columns(entry, ("x", "y", "z"), w, ctx)
    if not len(steps) == len(names) == stops.shape[0]:
        raise ctx.error(f"{w}: 'state', 'time_index', 'x' and 'y' have different lengths")
    if len(steps) and (steps.min() < 0 or steps.max() >= n_steps):
        raise ctx.error(f"{w}.time_index: a step outside [0, {n_steps})")
    return steps, np.array([int(x) for x in states], np.int64), stops


def _lane_starting_at(point: np.ndarray, road_map: RoadMap) -> int | None:
    """Id of the lane whose first point is nearest ``point`` (x, y), within
    ``SIGNAL_LANE_MATCH_M``; None if there is none."""
    lanes = road_map.indices_of(MapFeatureType.LANE)
    if lanes.shape[0] == 0:
        return None
    starts = np.array([road_map.polylines[i][0, :2] for i in lanes])
    dist = np.linalg.norm(starts - point[:2], axis=1)
    best = int(np.argmin(dist))
    return int(road_map.id[lanes[best]]) if dist[best] <= SIGNAL_LANE_MATCH_M else None


def _signals(
    tl_states: Any, road_map: RoadMap, by_id: bool, n_steps: int, ctx: _Ctx
) -> TrafficSignals:
    """Signals of ``tl_states``; ``by_id``: its keys are road ids (else matched by geometry)."""
    if not tl_states:
        return TrafficSignals.empty(n_steps)
    if not isinstance(tl_states, dict):
        raise ctx.error(f"key 'tl_states' must be an object, got {type(tl_states).__name__}")
    parts, dropped = [], []
    for key, entry in tl_states.items():
        steps, states, stops = _tl_entry(key, entry, n_steps, ctx)
        if len(steps) == 0:
            continue
        if by_id:
            if not key.strip().isdigit() or len(key) > 18:
                raise ctx.error(f"tl_states: key {key!r} is not a lane id")
            lane = int(key)
        else:
            lane = _lane_starting_at(stops[0], road_map)
            if lane is None:
                dropped.append(key)
                continue
        parts.append((steps, np.full(len(steps), lane, np.int64), states, stops))
    if dropped:
        warnings.warn(
            str(
                ctx.error(
                    f"dropped {len(dropped)} signal(s) whose lane starts at no stop "
                    f"point (tl_states keys {dropped[:5]})"
                )
            ),
            stacklevel=3,
        )
    if not parts:
        return TrafficSignals.empty(n_steps)
    step, lane, state, stop = (np.concatenate(p) for p in zip(*parts))
    return signals_from_entries(step, lane, state, stop, n_steps)


def _metadata(meta: Any, ctx: _Ctx) -> tuple[int, np.ndarray, np.ndarray, np.ndarray]:
    """(sdc index, tracks_to_predict indices, difficulties, objects_of_interest ids)."""
    last = MAX_TRACK_ID  # Scenario.validate names an index outside the track list
    sdc = _int(
        _get(meta, "sdc_track_index", "metadata", ctx), "metadata.sdc_track_index", ctx, 0, last
    )
    ttp = meta.get("tracks_to_predict", [])
    if not isinstance(ttp, list):
        raise ctx.error("metadata.tracks_to_predict: expected a list")
    idx, diff = [], []
    for i, r in enumerate(ttp):
        w = f"metadata.tracks_to_predict[{i}]"
        idx.append(_int(_get(r, "track_index", w, ctx), f"{w}.track_index", ctx, 0, last))
        level = r.get("difficulty", 0)
        diff.append(_int(level, f"{w}.difficulty", ctx, 0, NUM_DIFFICULTY_LEVELS - 1))
    ooi = meta.get("objects_of_interest", [])
    return (
        sdc,
        np.asarray(idx, np.int64).reshape(-1),
        np.asarray(diff, np.int8).reshape(-1),
        _int_list(ooi, "metadata.objects_of_interest", ctx, 0, MAX_TRACK_ID),
    )


def scenario_from_gpudrive(data: Any, *, source: str = "<memory>") -> Scenario:
    """Convert an already-decoded GPUDrive JSON document to a validated ``Scenario``.

    Args:
        data: the decoded JSON (a dict).
        source: file name for messages and ``Scenario.source``.

    Raises:
        ScenarioFormatError: missing or malformed keys (naming the key and object index).
    """
    ctx = _Ctx(source)
    if not isinstance(data, dict):
        raise ctx.error(f"top level: expected a JSON object, got {type(data).__name__}")
    default_id = os.path.splitext(os.path.basename(source))[0]
    sid = data.get("scenario_id", default_id)
    if not isinstance(sid, str) or not sid:
        raise ctx.error(f"top level: 'scenario_id' must be a non-empty string, got {sid!r}")
    tracks = _tracks(_get(data, "objects", "top level", ctx), ctx)
    roads = _get(data, "roads", "top level", ctx)
    road_map = _road_map(roads, ctx)
    if road_map.num_features == 0:
        warnings.warn(str(ctx.error(f"scenario {sid!r} has no map features")), stacklevel=2)
    n_steps = tracks.num_steps
    signals = _signals(data.get("tl_states"), road_map, _roads_have_ids(roads), n_steps, ctx)
    if "metadata" in data:
        sdc, ttp, diff, ooi = _metadata(data["metadata"], ctx)
    else:  # the rule of the WOSAC reference conversion (module docstring)
        now = min(CURRENT_INDEX, n_steps - 1)
        sdc = choose_sdc(tracks, road_map, now)
        ttp = choose_tracks_to_predict(tracks, sdc, now)
        diff, ooi = np.zeros(ttp.shape[0], np.int8), np.zeros(0, np.int64)
    scenario = Scenario(
        scenario_id=sid,
        timestamps=np.arange(n_steps, dtype=np.float64) * DT,
        current_index=CURRENT_INDEX,
        tracks=tracks,
        road_map=road_map,
        signals=signals,
        sdc_index=sdc,
        tracks_to_predict=ttp,
        predict_difficulty=diff,
        objects_of_interest=ooi,
        source=source,
    )
    return scenario.validate()


def read_gpudrive_json(path: PathLike) -> Scenario:
    """Read one GPUDrive JSON scenario file, plain or gzip-compressed.

    Raises:
        FileNotFoundError: no such file.
        ScenarioFormatError: not JSON, bad gzip data, or not a GPUDrive scenario (names the key
            at fault).
    """
    name = os.fspath(path)
    raw = read_all(name)
    try:
        data = json.loads(raw)
    except (ValueError, UnicodeDecodeError) as err:  # JSONDecodeError, over-long integers
        raise ScenarioFormatError(f"not valid JSON: {err}", name) from err
    except RecursionError as err:
        raise ScenarioFormatError("not valid JSON: nested too deeply", name) from err
    return scenario_from_gpudrive(data, source=name)
