"""WOMD tf.Example reader (no TensorFlow): the shared record against the data README, the
sniffing of Example vs Scenario records, malformed input, fuzz."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from tbsim_env.core.constants import CURRENT_INDEX, MapFeatureType, ObjectType, SignalState
from tbsim_env.core.errors import ScenarioFormatError
from tbsim_env.data.protos import tf_example_pb2
from tbsim_env.data.tf_example import (
    decode_example,
    is_tf_example,
    parse_tf_example,
    read_tf_examples,
)
from tbsim_env.data.tfrecord import iter_records, write_records
from tests.real_format_support import check_raw_heading, heading_error, mutate_bytes, outcome

PROTO_DIR = Path(__file__).resolve().parents[1] / "tbsim_env" / "data" / "protos"


@pytest.fixture(scope="module")
def example(tf_example_path: Path):
    (scenario,) = list(read_tf_examples(tf_example_path))
    return scenario


def test_the_shared_record_matches_the_readme(example) -> None:
    s = example
    t = s.tracks
    assert s.scenario_id == "a3bb37c25ce56418" and s.num_steps == 91
    assert s.current_index == CURRENT_INDEX == 10
    counts = np.bincount(t.object_type, minlength=len(ObjectType))
    assert counts[ObjectType.VEHICLE] == 119 and counts[ObjectType.PEDESTRIAN] == 8
    assert counts[ObjectType.CYCLIST] == 1 and t.num_tracks == 128
    assert t.valid[:, 10].sum() == 73
    assert len(s.tracks_to_predict) == 8 and s.tracks.valid[s.tracks_to_predict, 10].all()
    assert s.sdc_index == 8 and s.objects_of_interest.tolist() == [7, 333]
    assert np.all(np.diff(s.timestamps) > 0.09) and abs(s.timestamps[10] - 0.99921) < 1e-6
    assert heading_error(s) < 0.1
    check_raw_heading(s)
    raw = t.raw_heading[t.valid]
    assert raw.min() < -np.pi and raw.max() > np.pi  # bbox_yaw kept as stored (-5.2 .. 7.4)


def test_roadgraph_samples_become_features(example, tf_example_path: Path) -> None:
    rm = example.road_map
    assert rm.num_features == 254  # one per roadgraph id
    kinds = np.bincount(rm.feature_type, minlength=len(MapFeatureType))
    assert kinds[MapFeatureType.LANE] == 131 and kinds[MapFeatureType.ROAD_LINE] == 78
    assert kinds[MapFeatureType.ROAD_EDGE] == 45
    ((_, _, payload),) = list(iter_records(tf_example_path))
    feats = decode_example(payload)
    assert sum(len(p) for p in rm.polylines) == int((feats["roadgraph_samples/valid"] > 0).sum())
    ids = feats["roadgraph_samples/id"]
    first = rm.id[0]
    np.testing.assert_array_equal(
        rm.polylines[0], feats["roadgraph_samples/xyz"].reshape(-1, 3)[ids == first]
    )


def test_signals_group_slots_by_lane(example) -> None:
    sig = example.signals
    assert sig.num_signals == 21 and sig.lane_id[0] == 231
    assert sig.valid.sum(axis=1).max() == 91
    assert set(np.unique(sig.state[sig.valid]).tolist()) <= {int(x) for x in SignalState}


def test_example_and_scenario_records_are_told_apart(
    tf_example_path: Path, one_scenario_path: Path
) -> None:
    ((_, _, example),) = list(iter_records(tf_example_path))
    ((_, _, scenario),) = list(iter_records(one_scenario_path))
    assert is_tf_example(example) and not is_tf_example(scenario)
    assert not is_tf_example(b"\xff\xff\xff") and not is_tf_example(b"")


def test_committed_pb2_matches_proto_source(tmp_path: Path) -> None:
    import subprocess
    import sys

    from google.protobuf import descriptor_pb2

    pytest.importorskip("grpc_tools")
    out = tmp_path / "set.pb"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "grpc_tools.protoc",
            f"-I{PROTO_DIR}",
            f"--descriptor_set_out={out}",
            "tf_example.proto",
        ],
        check=True,
        capture_output=True,
    )
    fresh = descriptor_pb2.FileDescriptorSet.FromString(out.read_bytes()).file[0]
    committed = descriptor_pb2.FileDescriptorProto()
    tf_example_pb2.DESCRIPTOR.CopyToProto(committed)
    for proto in (fresh, committed):  # CopyToProto leaves out the derived json_name
        for message in proto.message_type:
            for m in [message, *message.nested_type]:
                for field in m.field:
                    field.ClearField("json_name")
    assert fresh == committed


# ----------------------------------------------------------------------------- malformed input

A, P, F, S, N = 4, 10, 10, 2, 12  # agent slots, past / future steps, signal slots, samples


def _tiny_features() -> dict[str, np.ndarray | list]:
    """A small WOMD-shaped Example: 3 agents (one empty slot), 3 roadgraph ids, 2 signals."""
    t = np.arange(P + 1 + F, dtype=np.float32)
    x = (t[None] * 1.0 + 10.0 * np.arange(A)[:, None]).astype(np.float32)  # 10 m/s along +x
    per_step = {
        "x": x,
        "y": np.tile(3.0 * np.arange(A, dtype=np.float32)[:, None], (1, t.size)),
        "z": np.zeros((A, t.size), np.float32),
        "bbox_yaw": np.zeros((A, t.size), np.float32),
        "velocity_x": np.full((A, t.size), 10.0, np.float32),
        "velocity_y": np.zeros((A, t.size), np.float32),
        "length": np.full((A, t.size), 4.5, np.float32),
        "width": np.full((A, t.size), 2.0, np.float32),
        "height": np.full((A, t.size), 1.5, np.float32),
        "valid": np.ones((A, t.size), np.int64),
        "timestamp_micros": np.tile((t * 1e5).astype(np.int64), (A, 1)),
    }
    per_step["valid"][3] = 0  # an empty padding slot
    feats: dict[str, np.ndarray | list] = {"scenario/id": [b"tiny"]}
    cuts = {"past": slice(0, P), "current": slice(P, P + 1), "future": slice(P + 1, None)}
    for part, cut in cuts.items():
        for name, arr in per_step.items():
            feats[f"state/{part}/{name}"] = arr[:, cut].reshape(-1)
        n = len(t[cut])
        feats[f"traffic_light_state/{part}/timestamp_micros"] = (t[cut] * 1e5).astype(np.int64)
        feats[f"traffic_light_state/{part}/state"] = np.tile([4, 6], n).astype(np.int64)
        feats[f"traffic_light_state/{part}/valid"] = np.ones(n * S, np.int64)
        feats[f"traffic_light_state/{part}/id"] = np.tile([101, 102], n).astype(np.int64)
        for c, v in (("x", 50.0), ("y", 0.0), ("z", 0.0)):
            feats[f"traffic_light_state/{part}/{c}"] = np.full(n * S, v, np.float32)
    feats["state/id"] = np.array([7, 8, 9, -1], np.float32)
    feats["state/type"] = np.array([1, 1, 2, -1], np.float32)
    feats["state/is_sdc"] = np.array([0, 0, 1, 0], np.int64)
    feats["state/tracks_to_predict"] = np.array([1, 0, 0, 0], np.int64)
    feats["state/difficulty_level"] = np.array([1, 0, 0, 0], np.int64)
    feats["state/objects_of_interest"] = np.array([1, 1, 0, 0], np.int64)
    xs = np.arange(N, dtype=np.float32)
    feats["roadgraph_samples/xyz"] = np.stack([xs, xs * 0, xs * 0], 1).reshape(-1)
    feats["roadgraph_samples/dir"] = np.zeros(3 * N, np.float32)
    feats["roadgraph_samples/type"] = np.repeat([2, 15, 18], N // 3).astype(np.int64)
    feats["roadgraph_samples/id"] = np.repeat([101, 300, 400], N // 3).astype(np.int64)
    feats["roadgraph_samples/valid"] = np.ones(N, np.int64)
    return feats


def _encode(feats: dict) -> bytes:
    ex = tf_example_pb2.Example()
    for key, value in feats.items():
        feature = ex.features.feature[key]
        if isinstance(value, list):
            feature.bytes_list.value.extend(value)
        elif np.asarray(value).dtype.kind == "f":
            feature.float_list.value.extend(np.asarray(value).tolist())
        else:
            feature.int64_list.value.extend(np.asarray(value).tolist())
    return ex.SerializeToString()


def test_tiny_example_reads() -> None:
    s = parse_tf_example(_encode(_tiny_features()), path="mem")
    assert s.tracks.id.tolist() == [7, 8, 9] and s.num_steps == P + 1 + F
    assert s.current_index == P and s.sdc_index == 2
    assert s.tracks_to_predict.tolist() == [0] and s.predict_difficulty.tolist() == [1]
    assert s.objects_of_interest.tolist() == [7, 8]
    assert s.road_map.id.tolist() == [101, 300, 400]
    assert s.road_map.feature_type.tolist() == [0, 2, 4] and s.road_map.subtype.tolist() == [
        2,
        1,
        0,
    ]
    assert s.signals.lane_id.tolist() == [101, 102] and s.signals.valid.all()
    assert s.signals.state[:, 0].tolist() == [4, 6]


def _without(key: str):
    def mutate(f: dict) -> None:
        del f[key]

    return mutate


def _with(key: str, value):
    def mutate(f: dict) -> None:
        f[key] = value

    return mutate


def _poke(key: str, index: int, value):
    def mutate(f: dict) -> None:
        f[key] = np.array(f[key])
        f[key][index] = value

    return mutate


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (_without("scenario/id"), "'scenario/id' is missing"),
        (_with("scenario/id", [b"\xff\xfe"]), "'scenario/id' is not UTF-8"),
        (_without("state/past/x"), "'state/past/x' is missing"),
        (_with("state/current/x", np.zeros(7, np.float32)), "'state/current/x' has 7 values"),
        (_with("state/future/y", np.zeros(A, np.float32)), "do not all hold 21 steps"),
        (_with("state/id", np.array([7, 8, 9.5, -1], np.float32)), "'state/id': slot 2"),
        (_with("state/past/x", np.zeros(A * P, np.int64)), "'state/past/x' is not a float_list"),
        (_with("state/is_sdc", np.zeros(A, np.int64)), "'state/is_sdc' marks 0 slot"),
        (_with("state/is_sdc", np.array([0, 0, 0, 1])), "'state/is_sdc' marks 1 slot"),
        (_with("state/tracks_to_predict", np.array([0, 0, 0, 1])), "marks slot 3, never valid"),
        (_with("state/type", np.array([1, 9, 2, -1], np.float32)), "unknown 'object_type'"),
        (_poke("state/current/x", 1, np.nan), "non-finite"),
        (_with("roadgraph_samples/id", np.zeros(3, np.int64)), "'roadgraph_samples/\\*' disagree"),
        (_poke("traffic_light_state/future/state", 3, 12), "unknown state 12"),
        (_poke("traffic_light_state/current/timestamp_micros", 0, 0), "not increasing at step"),
        (_with("traffic_light_state/past/timestamp_micros", np.arange(3)), "hold 14 steps"),
    ],
)
def test_malformed_example_names_file_record_and_key(tmp_path: Path, mutate, message) -> None:
    feats = _tiny_features()
    mutate(feats)
    path = tmp_path / "bad.tfrecord"
    write_records(path, [_encode(_tiny_features()), _encode(feats)])
    with pytest.raises(ScenarioFormatError, match=message) as info:
        list(read_tf_examples(path))
    assert info.value.path == str(path) and info.value.record == 1
    with pytest.warns(UserWarning, match="skipping this record"):
        assert len(list(read_tf_examples(path, skip_bad=True))) == 1


def test_truncated_and_foreign_payloads(tmp_path: Path) -> None:
    payload = _encode(_tiny_features())
    for cut in (1, 10, len(payload) // 2, len(payload) - 1):
        with pytest.raises(ScenarioFormatError) as info:
            parse_tf_example(payload[:cut], path="cut.tfrecord", record=0)
        assert info.value.path == "cut.tfrecord"
    with pytest.raises(ScenarioFormatError, match="'scenario/id' is missing"):
        parse_tf_example(b"", path="empty")
    path = tmp_path / "trunc.tfrecord"
    write_records(path, [payload])
    path.write_bytes(path.read_bytes()[:-7])
    with pytest.raises(ScenarioFormatError, match="record 0"):
        list(read_tf_examples(path))


def test_seeded_fuzz_gives_a_scenario_or_a_format_error() -> None:
    rng = np.random.default_rng(25)
    feats = _tiny_features()
    payload = _encode(feats)
    results = [outcome(lambda: parse_tf_example(mutate_bytes(payload, rng))) for _ in range(30)]
    keys = sorted(feats)
    for _ in range(40):
        mutated = dict(feats)
        key = keys[int(rng.integers(len(keys)))]
        value = np.asarray(mutated[key]) if not isinstance(mutated[key], list) else None
        choice = int(rng.integers(4))
        if choice == 0 or value is None:
            del mutated[key]
        elif choice == 1:
            mutated[key] = value[: int(rng.integers(0, value.size + 1))]
        elif choice == 2:
            mutated[key] = value.astype(np.int64 if value.dtype.kind == "f" else np.float32)
        else:
            junk = value.copy()
            bad = [np.nan, -1.0, 1e30, 7.0] if value.dtype.kind == "f" else [-1, 7, 10**12, 0]
            if value.size:
                junk[int(rng.integers(value.size))] = bad[int(rng.integers(len(bad)))]
            mutated[key] = junk
        results.append(outcome(lambda m=mutated: parse_tf_example(_encode(m))))
    assert "error" in results and "ok" in results
