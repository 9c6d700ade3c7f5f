"""Raw WOMD ``Scenario`` TFRecords -> typed ``Scenario`` (no TensorFlow).

Records are framed by ``tbsim_env.data.tfrecord`` and decoded with the generated classes of
``tbsim_env/data/protos/scenario.proto``. Conversion builds whole arrays at once: one
comprehension over all object states of all tracks gives an [A * T, 10] table, which is then
reshaped, masked and wrapped with numpy.

Conventions of the result (see ``tbsim_env.data.scenario``): headings wrapped to [-pi, pi),
invalid track entries zeroed, one traffic-signal row per unique controlled lane id.
Problems raise ``ScenarioFormatError`` naming the file, record, byte offset and field.
"""

from __future__ import annotations

import os
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cached_property
from operator import attrgetter

import numpy as np
from google.protobuf.message import DecodeError

from tbsim_env.core.constants import MapFeatureType
from tbsim_env.core.errors import ScenarioFormatError
from tbsim_env.data.protos import scenario_pb2
from tbsim_env.data.scenario import RoadMap, Scenario, Tracks, TrafficSignals
from tbsim_env.data.tfrecord import TFRecordIndex, build_index, iter_records, read_record

PathLike = str | os.PathLike

# One row per ObjectState: x, y, z, length, width, height, heading, vx, vy, valid.
_STATE_FIELDS = attrgetter(
    "center_x",
    "center_y",
    "center_z",
    "length",
    "width",
    "height",
    "heading",
    "velocity_x",
    "velocity_y",
    "valid",
)
_XYZ = attrgetter("x", "y", "z")
_NO_IDS = np.zeros(0, np.int64)
_FLOAT32_PI = np.float32(np.pi)

# oneof member name -> (MapFeatureType, polyline attribute, has a ``type`` subtype field).
_MAP_KINDS: dict[str, tuple[MapFeatureType, str, bool]] = {
    "lane": (MapFeatureType.LANE, "polyline", True),
    "road_line": (MapFeatureType.ROAD_LINE, "polyline", True),
    "road_edge": (MapFeatureType.ROAD_EDGE, "polyline", True),
    "stop_sign": (MapFeatureType.STOP_SIGN, "position", False),
    "crosswalk": (MapFeatureType.CROSSWALK, "polygon", False),
    "speed_bump": (MapFeatureType.SPEED_BUMP, "polygon", False),
    "driveway": (MapFeatureType.DRIVEWAY, "polygon", False),
}


@dataclass(frozen=True)
class _Where:
    """Location of a record, for error messages."""

    path: str | None
    record: int | None = None
    offset: int | None = None

    @property
    def source(self) -> str:
        name = self.path if self.path is not None else "<memory>"
        return name if self.record is None else f"{name}#record{self.record}"

    def error(self, reason: str) -> ScenarioFormatError:
        return ScenarioFormatError(reason, self.path, self.record, self.offset)

    def message(self, reason: str) -> str:
        """``reason`` prefixed with the location, as in a ``ScenarioFormatError``."""
        return str(self.error(reason))


def wrap_heading_f32(heading: np.ndarray) -> np.ndarray:
    """Wrap radians to [-pi, pi) and cast to float32, keeping the bound after rounding.

    Args:
        heading: any shape, radians (float64 or float32).

    Returns:
        Same shape, float32 in [-pi, pi) as float32 compares (float32(pi) maps to -pi).
    """
    h = ((np.asarray(heading, np.float64) + np.pi) % (2.0 * np.pi) - np.pi).astype(np.float32)
    return np.where(h >= _FLOAT32_PI, -_FLOAT32_PI, h)


def _scenario_id(msg: scenario_pb2.Scenario, where: _Where) -> str:
    if not msg.HasField("scenario_id") or not msg.scenario_id:
        raise where.error("field 'scenario_id' (5) is missing: not a WOMD Scenario record")
    sid = msg.scenario_id
    if isinstance(sid, bytes):  # proto2 strings with bad UTF-8 come back as bytes
        raise where.error(f"field 'scenario_id' (5) is not valid UTF-8: {sid[:32]!r}")
    return sid


def _timestamps(msg: scenario_pb2.Scenario, where: _Where) -> np.ndarray:
    ts = np.asarray(msg.timestamps_seconds, dtype=np.float64)
    if ts.shape[0] == 0:
        raise where.error("field 'timestamps_seconds' (1) is empty: not a WOMD Scenario record")
    if not np.isfinite(ts).all():
        raise where.error("field 'timestamps_seconds' (1) has a non-finite value")
    if ts.shape[0] > 1 and not (np.diff(ts) > 0).all():
        bad = int(np.argmax(np.diff(ts) <= 0)) + 1
        raise where.error(f"field 'timestamps_seconds' (1) is not increasing at step {bad}")
    return ts


def _tracks(msg: scenario_pb2.Scenario, n_steps: int, where: _Where) -> Tracks:
    """[A, T] track arrays from ``msg.tracks`` (one comprehension over all states)."""
    tracks = msg.tracks
    if len(tracks) == 0:
        raise where.error("field 'tracks' (2) is empty: a scenario needs at least one track")
    counts = np.fromiter((len(t.states) for t in tracks), dtype=np.int64, count=len(tracks))
    if (counts != n_steps).any():
        k = int(np.argmax(counts != n_steps))
        raise where.error(
            f"track {k} (id {tracks[k].id}): field 'states' has {int(counts[k])} entries but "
            f"'timestamps_seconds' has {n_steps}"
        )
    a = len(tracks)
    ids = np.fromiter((t.id for t in tracks), dtype=np.int64, count=a)
    types = np.fromiter((t.object_type for t in tracks), dtype=np.int8, count=a)
    rows = np.array([_STATE_FIELDS(s) for t in tracks for s in t.states], dtype=np.float64)
    rows = rows.reshape(a, n_steps, 10)
    valid = rows[..., 9] != 0.0
    rows = np.where(valid[..., None], rows, 0.0)
    with np.errstate(over="ignore", invalid="ignore"):
        return Tracks(
            id=ids,
            object_type=types,
            xyz=np.ascontiguousarray(rows[..., 0:3]),
            heading=wrap_heading_f32(rows[..., 6]),
            velocity=rows[..., 7:9].astype(np.float32),
            size=rows[..., 3:6].astype(np.float32),
            valid=valid,
            raw_heading=rows[..., 6].astype(np.float32),
        )


def _points(points) -> np.ndarray:
    """[n, 3] float64 from a repeated ``MapPoint``."""
    return np.array([_XYZ(p) for p in points], dtype=np.float64).reshape(-1, 3)


def _road_map(msg: scenario_pb2.Scenario, where: _Where) -> RoadMap:
    """Static map; features with no payload or no geometry are skipped (with a warning)."""
    ids: list[int] = []
    kinds: list[int] = []
    subtypes: list[int] = []
    polylines: list[np.ndarray] = []
    speed: list[float] = []
    entry: list[np.ndarray] = []
    exit_: list[np.ndarray] = []
    left: list[np.ndarray] = []
    right: list[np.ndarray] = []
    controlled: list[np.ndarray] = []
    no_geometry: list[int] = []
    for feature in msg.map_features:
        member = feature.WhichOneof("feature_data")
        if member is None:
            continue
        kind, geom_attr, has_subtype = _MAP_KINDS[member]
        data = getattr(feature, member)
        if member == "stop_sign":
            pts = _points([data.position]) if data.HasField("position") else np.zeros((0, 3))
        else:
            pts = _points(getattr(data, geom_attr))
        if pts.shape[0] == 0:
            no_geometry.append(feature.id)
            continue
        ids.append(feature.id)
        kinds.append(int(kind))
        subtypes.append(data.type if has_subtype else 0)
        polylines.append(pts)
        is_lane = member == "lane"
        speed.append(data.speed_limit_mph if is_lane else 0.0)
        entry.append(np.asarray(data.entry_lanes, np.int64) if is_lane else _NO_IDS)
        exit_.append(np.asarray(data.exit_lanes, np.int64) if is_lane else _NO_IDS)
        left.append(
            np.array([n.feature_id for n in data.left_neighbors], np.int64) if is_lane else _NO_IDS
        )
        right.append(
            np.array([n.feature_id for n in data.right_neighbors], np.int64) if is_lane else _NO_IDS
        )
        controlled.append(np.asarray(data.lane, np.int64) if member == "stop_sign" else _NO_IDS)
    if no_geometry:
        warnings.warn(
            where.message(
                f"skipped {len(no_geometry)} map feature(s) without geometry "
                f"(ids {no_geometry[:5]})"
            ),
            stacklevel=4,
        )
    with np.errstate(over="ignore", invalid="ignore"):
        speed_arr = np.asarray(speed, np.float32)
    return RoadMap(
        id=np.asarray(ids, np.int64),
        feature_type=np.asarray(kinds, np.int8),
        subtype=np.asarray(subtypes, np.int8),
        polylines=tuple(polylines),
        speed_limit_mph=speed_arr,
        entry_lanes=tuple(entry),
        exit_lanes=tuple(exit_),
        left_neighbors=tuple(left),
        right_neighbors=tuple(right),
        controlled_lanes=tuple(controlled),
    )


def _signals(msg: scenario_pb2.Scenario, n_steps: int, where: _Where) -> TrafficSignals:
    """One row per unique controlled lane id; [S, T] states and valid mask."""
    dyn = msg.dynamic_map_states
    if len(dyn) > n_steps:
        raise where.error(
            f"field 'dynamic_map_states' (7) has {len(dyn)} entries, more than the {n_steps} "
            "timestamps"
        )
    entries = [(t, s.lane, s.state) for t, d in enumerate(dyn) for s in d.lane_states]
    if not entries:
        return TrafficSignals.empty(n_steps)
    table = np.array(entries, dtype=np.int64).reshape(-1, 3)
    has_stop = np.array([s.HasField("stop_point") for d in dyn for s in d.lane_states])
    stops = np.array(
        [_XYZ(s.stop_point) for d in dyn for s in d.lane_states], dtype=np.float64
    ).reshape(-1, 3)
    lane_id, row = np.unique(table[:, 1], return_inverse=True)
    n = lane_id.shape[0]
    state = np.zeros((n, n_steps), np.int8)
    valid = np.zeros((n, n_steps), bool)
    state[row, table[:, 0]] = table[:, 2]
    valid[row, table[:, 0]] = True
    stop_point = np.zeros((n, 3), np.float64)
    with_stop = np.flatnonzero(has_stop)
    # np.unique's return_index gives the first occurrence: the first valid stop point per lane.
    stop_rows, first = np.unique(row[with_stop], return_index=True)
    stop_point[stop_rows] = stops[with_stop[first]]
    return TrafficSignals(lane_id=lane_id, state=state, valid=valid, stop_point=stop_point)


def _required_int(msg: scenario_pb2.Scenario, name: str, number: int, where: _Where) -> int:
    if not msg.HasField(name):
        raise where.error(f"field {name!r} ({number}) is missing: not a WOMD Scenario record")
    return int(getattr(msg, name))


def _convert(msg: scenario_pb2.Scenario, where: _Where) -> Scenario:
    sid = _scenario_id(msg, where)
    ts = _timestamps(msg, where)
    n_steps = ts.shape[0]
    current = _required_int(msg, "current_time_index", 10, where)
    sdc = _required_int(msg, "sdc_track_index", 6, where)
    tracks = _tracks(msg, n_steps, where)
    road_map = _road_map(msg, where)
    if road_map.num_features == 0:
        warnings.warn(where.message(f"scenario {sid!r} has no map features"), stacklevel=3)
    ttp = msg.tracks_to_predict
    scenario = Scenario(
        scenario_id=sid,
        timestamps=ts,
        current_index=current,
        tracks=tracks,
        road_map=road_map,
        signals=_signals(msg, n_steps, where),
        sdc_index=sdc,
        tracks_to_predict=np.fromiter((r.track_index for r in ttp), np.int64, count=len(ttp)),
        predict_difficulty=np.fromiter((r.difficulty for r in ttp), np.int8, count=len(ttp)),
        objects_of_interest=np.asarray(msg.objects_of_interest, np.int64),
        source=where.source,
    )
    try:
        return scenario.validate()
    except ScenarioFormatError as err:
        raise where.error(err.reason) from err


def scenario_from_proto(
    msg: scenario_pb2.Scenario,
    *,
    source: str = "<memory>",
    record: int | None = None,
    offset: int | None = None,
) -> Scenario:
    """Convert a parsed ``waymo.open_dataset.Scenario`` message to a validated ``Scenario``.

    Args:
        msg: the message.
        source: file name (or description) for messages and ``Scenario.source``.
        record: record index in that file, if any.
        offset: byte offset of the record, if any.

    Raises:
        ScenarioFormatError: the message is not a usable Scenario (missing id, timestamps,
            tracks; states count mismatch; bad cross references; non-finite values).
    """
    return _convert(msg, _Where(source, record, offset))


def parse_scenario(
    payload: bytes,
    *,
    path: PathLike | None = None,
    record: int | None = None,
    offset: int | None = None,
) -> Scenario:
    """Decode one serialized ``Scenario`` protobuf and convert it.

    Args:
        payload: serialized ``waymo.open_dataset.Scenario`` bytes.
        path: file it came from (for messages).
        record: record index inside the file.
        offset: byte offset of the record inside the file.

    Raises:
        ScenarioFormatError: not a valid Scenario protobuf, or not a usable Scenario.
    """
    where = _Where(None if path is None else os.fspath(path), record, offset)
    msg = _decode(scenario_pb2.Scenario, payload, where)
    return _convert(msg, where)


def _decode(message_type, payload: bytes, where: _Where):
    """``message_type.FromString(payload)``; any error of the protobuf runtime (``DecodeError``,
    and from the C runtime also e.g. ``ValueError``, ``RecursionError``, ``MemoryError``) is
    re-raised as a ``ScenarioFormatError`` naming the file and record."""
    try:
        return message_type.FromString(payload)
    except Exception as err:
        kind = "" if isinstance(err, DecodeError) else f"{type(err).__name__}: "
        raise where.error(f"not a valid Scenario protobuf: {kind}{err}") from err


def read_scenarios(
    path: PathLike, *, skip_bad: bool = False, verify: bool = True
) -> Iterator[Scenario]:
    """Yield every scenario of a TFRecord file, one record at a time.

    Args:
        path: TFRecord file of ``Scenario`` records.
        skip_bad: warn about bad records (framing or content) and go on instead of raising.
        verify: check the TFRecord CRCs.

    Raises:
        ScenarioFormatError: bad record (unless ``skip_bad``), or no scenarios in the file.
        FileNotFoundError: no such file.
    """
    return iter_parsed_records(path, parse_scenario, skip_bad=skip_bad, verify=verify)


def iter_parsed_records(
    path: PathLike,
    parse: Callable[..., Scenario],
    *,
    skip_bad: bool = False,
    verify: bool = True,
) -> Iterator[Scenario]:
    """Yield ``parse(payload, path=, record=, offset=)`` of every record of a TFRecord file
    (the one loop of the TFRecord readers: skipping bad records, refusing an empty file).

    Raises:
        ScenarioFormatError: bad record (unless ``skip_bad``), or no scenarios in the file.
        FileNotFoundError: no such file.
    """
    name = os.fspath(path)
    yielded = bad = 0
    for index, offset, payload in iter_records(name, verify=verify, skip_bad=skip_bad):
        try:
            scenario = parse(payload, path=name, record=index, offset=offset)
        except ScenarioFormatError as err:
            if not skip_bad:
                raise
            warnings.warn(f"{err}; skipping this record", stacklevel=3)
            bad += 1
            continue
        yielded += 1
        yield scenario
    if yielded == 0:
        extra = f" ({bad} bad record(s) skipped)" if bad else ""
        raise ScenarioFormatError(f"no scenarios in file{extra}", name)


class ScenarioFile:
    """Random access to the scenarios of one TFRecord file by id or record index.

    The offset index is built lazily from record headers; the id index parses only field 5
    (``scenario_id``) of each record. Scenarios are decoded on access, one record at a time.

    Example:
        >>> f = ScenarioFile("training.tfrecord-00000-of-01000")
        >>> f.ids()[:2], len(f)
        >>> scenario = f["637f20cafde22ff8"]
    """

    def __init__(self, path: PathLike, *, verify: bool = True) -> None:
        self.path = os.fspath(path)
        self.verify = verify
        if not os.path.isfile(self.path):
            raise FileNotFoundError(f"no such scenario file: {self.path!r}")

    @cached_property
    def index(self) -> TFRecordIndex:
        """Record offsets (header scan)."""
        return build_index(self.path)

    @cached_property
    def _id_to_record(self) -> dict[str, int]:
        mapping: dict[str, int] = {}
        for k in range(len(self.index)):
            offset = int(self.index.offsets[k])
            where = _Where(self.path, k, offset)
            payload = read_record(self.path, offset, verify=self.verify, record=k)
            head = _decode(scenario_pb2.ScenarioIdOnly, payload, where)
            sid = _scenario_id(head, where)
            if sid in mapping:
                warnings.warn(
                    where.message(
                        f"duplicate scenario_id {sid!r} (first in record {mapping[sid]}); "
                        "lookups by id return the first"
                    ),
                    stacklevel=3,
                )
                continue
            mapping[sid] = k
        return mapping

    def ids(self) -> list[str]:
        """Scenario ids in file order (duplicates listed once)."""
        return list(self._id_to_record)

    def __len__(self) -> int:
        return len(self.index)

    def __contains__(self, scenario_id: object) -> bool:
        return scenario_id in self._id_to_record

    def record(self, index: int) -> Scenario:
        """Scenario at record ``index`` (0-based, negative counts from the end)."""
        n = len(self.index)
        if not -n <= index < n:
            raise IndexError(f"record {index} out of range: {self.path!r} has {n} records")
        index %= n
        offset = int(self.index.offsets[index])
        payload = read_record(self.path, offset, verify=self.verify, record=index)
        return parse_scenario(payload, path=self.path, record=index, offset=offset)

    def __getitem__(self, key: str | int) -> Scenario:
        """Scenario by id (``str``) or by record index (``int``)."""
        if isinstance(key, str):
            try:
                index = self._id_to_record[key]
            except KeyError:
                raise KeyError(f"scenario id {key!r} not in {self.path!r}") from None
            return self.record(index)
        if isinstance(key, (int, np.integer)):
            return self.record(int(key))
        raise TypeError(f"ScenarioFile keys are scenario ids (str) or record indices, got {key!r}")

    def __iter__(self) -> Iterator[Scenario]:
        return read_scenarios(self.path, verify=self.verify)

    def __repr__(self) -> str:
        return f"ScenarioFile({self.path!r})"
