"""Raw WOMD Scenario reader: exact counts on the real files, wire-format tolerance, errors."""

from __future__ import annotations

import struct
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pytest
from google.protobuf import descriptor_pb2

from tbsim_env.core.constants import MapFeatureType, ObjectType, SignalState
from tbsim_env.core.errors import ScenarioFormatError
from tbsim_env.data.protos import scenario_pb2
from tbsim_env.data.scenario import Scenario
from tbsim_env.data.tfrecord import iter_records, write_records
from tbsim_env.data.womd import (
    ScenarioFile,
    parse_scenario,
    read_scenarios,
    scenario_from_proto,
    wrap_heading_f32,
)

PROTO_DIR = Path(__file__).resolve().parents[1] / "tbsim_env" / "data" / "protos"


def _payload(path: Path) -> bytes:
    ((_, _, payload),) = list(iter_records(path))
    return payload


def _read_one(path: Path) -> Scenario:
    (scenario,) = list(read_scenarios(path))
    return scenario


def _type_counts(s: Scenario) -> dict[str, int]:
    counts = np.bincount(s.tracks.object_type, minlength=len(ObjectType))
    return {t.name: int(counts[t]) for t in ObjectType if counts[t]}


def _map_counts(s: Scenario) -> dict[str, int]:
    counts = np.bincount(s.road_map.feature_type, minlength=len(MapFeatureType))
    return {t.name: int(counts[t]) for t in MapFeatureType if counts[t]}


# ----------------------------------------------------------------------------- schema


def test_committed_pb2_matches_proto_source(tmp_path: Path) -> None:
    pytest.importorskip("grpc_tools")
    out = tmp_path / "set.pb"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "grpc_tools.protoc",
            f"-I{PROTO_DIR}",
            f"--descriptor_set_out={out}",
            "scenario.proto",
        ],
        check=True,
        capture_output=True,
    )
    fresh = descriptor_pb2.FileDescriptorSet.FromString(out.read_bytes()).file[0]
    committed = descriptor_pb2.FileDescriptorProto()
    scenario_pb2.DESCRIPTOR.CopyToProto(committed)
    assert fresh.name == committed.name == "scenario.proto"
    assert fresh.package == "waymo.open_dataset"
    for proto in (fresh, committed):  # CopyToProto leaves out the derived json_name
        for message in proto.message_type:
            stack = [message]
            while stack:
                m = stack.pop()
                stack.extend(m.nested_type)
                for field in m.field:
                    field.ClearField("json_name")
    assert fresh == committed


def test_field_numbers_follow_the_womd_schema() -> None:
    numbers = {f.name: f.number for f in scenario_pb2.Scenario.DESCRIPTOR.fields}
    assert numbers == {
        "scenario_id": 5,
        "timestamps_seconds": 1,
        "current_time_index": 10,
        "tracks": 2,
        "dynamic_map_states": 7,
        "map_features": 8,
        "sdc_track_index": 6,
        "objects_of_interest": 4,
        "tracks_to_predict": 11,
        "compressed_frame_laser_data": 12,
        "frame_camera_tokens": 13,
    }
    state = {f.name: f.number for f in scenario_pb2.ObjectState.DESCRIPTOR.fields}
    assert state["center_x"] == 2 and state["heading"] == 8 and state["valid"] == 11
    feature = {f.name: f.number for f in scenario_pb2.MapFeature.DESCRIPTOR.fields}
    assert feature == {
        "id": 1,
        "lane": 3,
        "road_line": 4,
        "road_edge": 5,
        "stop_sign": 7,
        "crosswalk": 8,
        "speed_bump": 9,
        "driveway": 10,
    }


# ----------------------------------------------------------------------------- real files


def test_motion_data_one_scenario_exact_counts(one_scenario_path: Path) -> None:
    s = _read_one(one_scenario_path)
    assert s.scenario_id == "637f20cafde22ff8"
    assert s.num_steps == 91 and s.current_index == 10
    assert s.timestamps[0] == pytest.approx(0.0) and s.timestamps[-1] == pytest.approx(
        9.0, abs=0.01
    )
    assert s.tracks.num_tracks == 83
    assert _type_counts(s) == {"VEHICLE": 70, "PEDESTRIAN": 10, "CYCLIST": 3}
    assert s.sdc_index == 82 and s.sdc_id == 2406
    assert s.tracks_to_predict.tolist() == [72, 43, 42]
    assert s.predict_difficulty.tolist() == [1, 1, 2]
    assert s.tracks.object_type[[72, 43, 42]].tolist() == [2, 1, 1]
    assert s.objects_of_interest.tolist() == []
    assert s.road_map.num_features == 301
    assert _map_counts(s) == {
        "LANE": 199,
        "ROAD_LINE": 59,
        "ROAD_EDGE": 28,
        "STOP_SIGN": 8,
        "CROSSWALK": 4,
        "SPEED_BUMP": 3,
    }
    assert int(s.tracks.valid[:, 10].sum()) == 50
    sig = s.signals
    assert sig.num_signals == 12 and sig.state.shape == (12, 91)
    assert sig.valid.all()  # 91 dynamic states x 12 lane states each
    assert set(np.unique(sig.state).tolist()) == {
        SignalState.UNKNOWN,
        SignalState.ARROW_STOP,
        SignalState.STOP,
    }
    assert np.isin(sig.lane_id, s.road_map.id[s.road_map.indices_of(MapFeatureType.LANE)]).all()
    assert (np.abs(sig.stop_point[:, :2]) > 1.0).all()  # real stop points, not defaults
    assert s.source.endswith("motion_data_one_scenario.tfrecord#record0")


def test_womd_scenario_input_exact_counts(scenario_input_path: Path) -> None:
    s = _read_one(scenario_input_path)  # carries the unknown top-level field #3
    assert s.scenario_id == "ee519cf571686d19"
    assert s.num_steps == 91
    assert s.timestamps[-1] == pytest.approx(9.02, abs=0.005)
    assert s.tracks.num_tracks == 257
    assert _type_counts(s) == {"VEHICLE": 189, "PEDESTRIAN": 68}
    assert s.sdc_index == 256 and s.sdc_id == 2893
    assert s.tracks_to_predict.tolist() == [18, 234, 229, 26]
    assert s.predict_difficulty.tolist() == [0, 0, 0, 0]
    assert s.objects_of_interest.tolist() == [625, 2694]
    assert _map_counts(s) == {
        "LANE": 114,
        "ROAD_LINE": 12,
        "ROAD_EDGE": 75,
        "STOP_SIGN": 4,
        "CROSSWALK": 4,
        "SPEED_BUMP": 6,
    }
    assert s.signals.num_signals == 0 and s.signals.state.shape == (0, 91)


def test_unknown_field_3_is_really_in_the_file_and_tolerated(scenario_input_path: Path) -> None:
    payload = _payload(scenario_input_path)
    # Unknown fields are kept on parse; discarding them must shrink the payload by exactly
    # 2 bytes (tag 0x1a + zero length).
    msg = scenario_pb2.Scenario.FromString(payload)
    assert msg.ByteSize() == len(payload)
    clean = scenario_pb2.Scenario.FromString(payload)
    clean.DiscardUnknownFields()
    assert len(payload) - clean.ByteSize() == 2
    assert b"\x1a\x00" in payload


def test_headings_wrapped_and_invalid_entries_zeroed(
    one_scenario_path: Path, scenario_input_path: Path
) -> None:
    for path, raw_outside in ((one_scenario_path, 868), (scenario_input_path, 3665)):
        s = _read_one(path)
        h = s.tracks.heading
        assert h.dtype == np.float32
        assert (h >= -np.float32(np.pi)).all() and (h < np.float32(np.pi)).all()
        msg = scenario_pb2.Scenario.FromString(_payload(path))
        raw = np.array([[st.heading for st in t.states] for t in msg.tracks], np.float64)
        valid = np.array([[st.valid for st in t.states] for t in msg.tracks])
        outside = valid & ((raw < -np.pi) | (raw >= np.pi))
        assert int(outside.sum()) == raw_outside  # the raw data really is unwrapped
        diff = (h.astype(np.float64) - raw + np.pi) % (2 * np.pi) - np.pi
        assert np.abs(diff[valid]).max() < 1e-5  # same angle modulo 2 pi
        inv = ~s.tracks.valid
        assert (s.tracks.xyz[inv] == 0).all() and (s.tracks.size[inv] == 0).all()
        assert (h[inv] == 0).all() and (s.tracks.velocity[inv] == 0).all()


def test_track_values_match_the_proto(one_scenario_path: Path) -> None:
    s = _read_one(one_scenario_path)
    msg = scenario_pb2.Scenario.FromString(_payload(one_scenario_path))
    st = msg.tracks[82].states[10]
    assert st.valid and s.tracks.valid[82, 10]
    assert s.tracks.xyz[82, 10].tolist() == [st.center_x, st.center_y, st.center_z]
    assert s.tracks.size[82, 10].tolist() == pytest.approx([st.length, st.width, st.height])
    assert s.tracks.velocity[82, 10].tolist() == pytest.approx([st.velocity_x, st.velocity_y])
    lane = next(f for f in msg.map_features if f.WhichOneof("feature_data") == "lane")
    k = s.road_map.index_of_id()[lane.id]
    assert s.road_map.polylines[k].shape == (len(lane.lane.polyline), 3)
    assert s.road_map.polylines[k][0].tolist() == [
        lane.lane.polyline[0].x,
        lane.lane.polyline[0].y,
        lane.lane.polyline[0].z,
    ]
    assert s.road_map.entry_lanes[k].tolist() == list(lane.lane.entry_lanes)
    assert s.road_map.left_neighbors[k].tolist() == [n.feature_id for n in lane.lane.left_neighbors]
    assert s.road_map.speed_limit_mph[k] == pytest.approx(lane.lane.speed_limit_mph)
    stops = s.road_map.indices_of(MapFeatureType.STOP_SIGN)
    assert all(s.road_map.polylines[i].shape == (1, 3) for i in stops)
    assert sum(len(s.road_map.controlled_lanes[i]) for i in stops) > 0
    assert sum(len(x) for x in s.road_map.exit_lanes) > 0
    assert sum(len(x) for x in s.road_map.right_neighbors) > 0


def test_parse_time_per_real_file(one_scenario_path: Path, scenario_input_path: Path) -> None:
    for path in (one_scenario_path, scenario_input_path):
        payload = _payload(path)
        parse_scenario(payload)  # warm-up
        t0 = time.perf_counter()
        parse_scenario(payload)
        ms = (time.perf_counter() - t0) * 1e3
        print(f"{path.name}: {ms:.1f} ms per parse")
        assert ms < 2000  # generous bound for a shared 2-core machine


# ----------------------------------------------------------------------------- wire tolerance


def _tiny_scenario(n_steps: int = 3) -> scenario_pb2.Scenario:
    msg = scenario_pb2.Scenario(scenario_id="0123456789abcdef", current_time_index=1)
    msg.sdc_track_index = 0
    msg.timestamps_seconds.extend([0.1 * t for t in range(n_steps)])
    for track_id in (7, 9):
        track = msg.tracks.add(id=track_id, object_type=1)
        for t in range(n_steps):
            track.states.add(
                center_x=float(t), center_y=2.0, center_z=0.5, length=4.0, width=2.0,
                height=1.5, heading=7.0, velocity_x=10.0, velocity_y=0.0, valid=True,
            )  # fmt: skip
    lane = msg.map_features.add(id=100)
    lane.lane.polyline.add(x=0.0, y=0.0, z=0.0)
    lane.lane.polyline.add(x=1.0, y=0.0, z=0.0)
    return msg


def _state(track: int, step: int, **values: float):
    """A mutation of ``_tiny_scenario`` that sets fields of one (valid) state."""

    def mutate(msg: scenario_pb2.Scenario) -> None:
        for name, value in values.items():
            setattr(msg.tracks[track].states[step], name, value)

    return mutate


def _varint(value: int) -> bytes:
    out = bytearray()
    while True:
        low, value = value & 0x7F, value >> 7
        out.append(low | (0x80 if value else 0))
        if not value:
            return bytes(out)


def test_packed_and_unpacked_repeated_scalars_and_unknown_fields() -> None:
    base = _tiny_scenario().SerializeToString()
    ids = [7, 9, 300]
    unpacked = b"".join(bytes([4 << 3 | 0]) + _varint(v) for v in ids)
    body = b"".join(_varint(v) for v in ids)
    packed = bytes([4 << 3 | 2]) + _varint(len(body)) + body
    unknown = (
        b"\x1a\x00"  # field 3, empty length-delimited (as in womd_scenario_input)
        + _varint(99 << 3 | 0)
        + _varint(12345)  # field 99 varint
        + _varint(98 << 3 | 5)
        + b"\x00\x00\x80\x3f"  # field 98 fixed32
        + _varint(97 << 3 | 2)
        + _varint(3)
        + b"abc"  # field 97 bytes
    )
    a = parse_scenario(base + unpacked + unknown)
    b = parse_scenario(unknown + base + packed)
    assert a.objects_of_interest.tolist() == ids == b.objects_of_interest.tolist()
    # timestamps: the real files use unpacked doubles; packed must decode the same.
    doubles = struct.pack("<3d", 0.0, 0.1, 0.2)  # wire format: little-endian doubles
    no_ts = _tiny_scenario()
    del no_ts.timestamps_seconds[:]
    packed_ts = bytes([1 << 3 | 2]) + _varint(len(doubles)) + doubles
    c = parse_scenario(no_ts.SerializeToString() + packed_ts)
    np.testing.assert_array_equal(c.timestamps, a.timestamps)
    assert c.tracks.heading[0, 0] == pytest.approx(7.0 - 2 * np.pi)


def test_scenario_from_proto_and_no_map_warning() -> None:
    msg = _tiny_scenario()
    s = scenario_from_proto(msg, source="tiny")
    assert s.source == "tiny" and s.tracks.num_tracks == 2 and s.road_map.num_features == 1
    msg.ClearField("map_features")
    with pytest.warns(UserWarning, match="no map features"):
        s = scenario_from_proto(msg, source="tiny")
    assert s.road_map.num_features == 0


def test_feature_without_payload_is_skipped() -> None:
    msg = _tiny_scenario()
    msg.map_features.add(id=555)  # no oneof member set
    s = parse_scenario(msg.SerializeToString())
    assert s.road_map.id.tolist() == [100]


def test_wrap_heading_f32_edges() -> None:
    x = np.array([np.pi, -np.pi, np.pi - 1e-9, 3 * np.pi, 10.19, -4.70])
    h = wrap_heading_f32(x)
    assert h.dtype == np.float32
    assert (h >= -np.float32(np.pi)).all() and (h < np.float32(np.pi)).all()
    assert h[4] == pytest.approx(10.19 - 4 * np.pi, abs=1e-6)


# ----------------------------------------------------------------------------- content errors


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (lambda m: m.ClearField("scenario_id"), "'scenario_id'"),
        (lambda m: m.ClearField("timestamps_seconds"), "'timestamps_seconds'"),
        (lambda m: m.ClearField("tracks"), "'tracks'"),
        (lambda m: m.ClearField("current_time_index"), "'current_time_index'"),
        (lambda m: m.ClearField("sdc_track_index"), "'sdc_track_index'"),
        (lambda m: m.tracks[1].states.add(), r"track 1 \(id 9\).*'states' has 4"),
        (lambda m: m.timestamps_seconds.__setitem__(2, 0.05), "not increasing at step 2"),
        (lambda m: setattr(m, "sdc_track_index", 5), "sdc_track_index"),
        (lambda m: setattr(m, "current_time_index", 3), "current_time_index"),
        (lambda m: m.tracks_to_predict.add(track_index=2), "tracks_to_predict"),
        (lambda m: setattr(m.tracks[1], "id", 7), "not unique"),
        (lambda m: setattr(m.tracks[0].states[1], "center_x", float("nan")), "non-finite"),
        (lambda m: m.dynamic_map_states.extend([scenario_pb2.DynamicMapState()] * 4), "dynamic"),
        # Physically impossible values of valid states: the object, step and field are named.
        (_state(0, 1, length=0.0), r"track 7 \(index 0\) at step 1: field 'length' .*positive"),
        (_state(1, 2, width=-2.0), r"track 9 \(index 1\) at step 2: field 'width' .*positive"),
        (_state(0, 0, height=float("nan")), r"track 7 .* field 'height' .*non-finite"),
        (_state(0, 0, length=float("inf")), r"track 7 .* field 'length' .*non-finite"),
        (_state(1, 1, velocity_y=float("inf")), r"track 9 .* field 'velocity_y' .*non-finite"),
        (_state(1, 0, heading=float("-inf")), r"track 9 .* field 'heading' .*non-finite"),
        (_state(0, 2, center_y=1e30), r"track 7 .* field 'center_y' .*beyond 1e\+07 m"),
        (_state(0, 2, center_z=3e38), r"track 7 .* field 'center_z'"),
        (lambda m: setattr(m.map_features[0].lane.polyline[1], "x", 1e30), "feature 100: .*beyond"),
    ],
)
def test_bad_content_names_the_field(mutate, message: str) -> None:
    msg = _tiny_scenario()
    mutate(msg)
    with pytest.raises(ScenarioFormatError, match=message) as info:
        parse_scenario(msg.SerializeToString(), path="f.tfrecord", record=4, offset=99)
    assert (info.value.path, info.value.record, info.value.offset) == ("f.tfrecord", 4, 99)
    assert "record 4" in str(info.value)


def test_impossible_values_of_invalid_states_are_fine() -> None:
    msg = _tiny_scenario()
    state = msg.tracks[1].states[0]
    state.valid, state.length, state.width, state.center_x = False, 0.0, -1.0, float("inf")
    s = parse_scenario(msg.SerializeToString())
    assert not s.tracks.valid[1, 0] and (s.tracks.size[1, 0] == 0).all()


@pytest.mark.parametrize(
    "error",
    [ValueError("Maximum allowed size exceeded"), MemoryError(), RuntimeError("upb"), KeyError(3)],
)
def test_protobuf_runtime_errors_name_file_and_record(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, error: Exception
) -> None:
    """Whatever the protobuf runtime raises while decoding comes back as a
    ``ScenarioFormatError`` naming the file and record, from every reading path."""
    import tbsim_env.data.womd as womd

    class Failing:
        @staticmethod
        def FromString(payload: bytes):  # noqa: N802 (the protobuf name)
            raise error

    path = tmp_path / "x.tfrecord"
    write_records(path, [_tiny_scenario().SerializeToString()] * 2)
    monkeypatch.setattr(womd.scenario_pb2, "Scenario", Failing)
    with pytest.raises(ScenarioFormatError, match=type(error).__name__) as info:
        list(read_scenarios(path))
    assert (info.value.path, info.value.record) == (str(path), 0)
    with pytest.raises(ScenarioFormatError, match="record 1"):
        ScenarioFile(path).record(1)
    monkeypatch.setattr(womd.scenario_pb2, "ScenarioIdOnly", Failing)
    with pytest.raises(ScenarioFormatError, match=f"'{path}', record 0"):
        ScenarioFile(path).ids()


def test_invalid_state_with_nan_is_fine() -> None:
    msg = _tiny_scenario()
    msg.tracks[0].states[2].center_x = float("nan")
    msg.tracks[0].states[2].valid = False
    s = parse_scenario(msg.SerializeToString())
    assert not s.tracks.valid[0, 2] and s.tracks.xyz[0, 2, 0] == 0.0


def test_bad_utf8_scenario_id() -> None:
    payload = _tiny_scenario().SerializeToString() + b"\x2a\x02\xff\xfe"  # field 5 again
    with pytest.raises(ScenarioFormatError, match="not valid UTF-8"):
        parse_scenario(payload)


# ----------------------------------------------------------------------------- random access


def test_scenario_file_random_access(
    tmp_path: Path, one_scenario_path: Path, scenario_input_path: Path
) -> None:
    path = tmp_path / "two.tfrecord"
    write_records(path, [_payload(one_scenario_path), _payload(scenario_input_path)])
    f = ScenarioFile(path)
    assert len(f) == 2
    assert f.ids() == ["637f20cafde22ff8", "ee519cf571686d19"]
    assert "ee519cf571686d19" in f and "nope" not in f
    second = f["ee519cf571686d19"]
    assert second.scenario_id == "ee519cf571686d19" and second.tracks.num_tracks == 257
    assert f[0].scenario_id == "637f20cafde22ff8" and f[-1].scenario_id == "ee519cf571686d19"
    np.testing.assert_array_equal(second.tracks.xyz, _read_one(scenario_input_path).tracks.xyz)
    assert [s.scenario_id for s in f] == f.ids()
    with pytest.raises(KeyError, match="nope"):
        f["nope"]
    with pytest.raises(IndexError):
        f[2]
    with pytest.raises(FileNotFoundError):
        ScenarioFile(tmp_path / "missing.tfrecord")


def test_scenario_file_duplicate_ids_warn(tmp_path: Path) -> None:
    payload = _tiny_scenario().SerializeToString()
    path = tmp_path / "dup.tfrecord"
    write_records(path, [payload, payload])
    f = ScenarioFile(path)
    with pytest.warns(UserWarning, match="duplicate scenario_id"):
        assert f.ids() == ["0123456789abcdef"]
    assert len(f) == 2


def test_index_ids_faster_than_full_parse(tmp_path: Path, scenario_input_path: Path) -> None:
    payload = _payload(scenario_input_path)
    path = tmp_path / "many.tfrecord"
    write_records(path, [payload] * 4)
    t0 = time.perf_counter()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        ScenarioFile(path).ids()
    index_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    list(read_scenarios(path))
    parse_s = time.perf_counter() - t0
    print(f"id index {index_s * 1e3:.1f} ms vs full parse {parse_s * 1e3:.1f} ms (4 records)")
    assert index_s < parse_s
