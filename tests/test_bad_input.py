"""Bad input end to end: truncation, CRC damage, wrong formats, multi-record recovery, fuzzing.

Every case must either give a valid ``Scenario`` or raise ``ScenarioFormatError``: never another
exception type, never a hang (each fuzz case runs under a SIGALRM time guard).
"""

from __future__ import annotations

import contextlib
import signal
import threading
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from tbsim_env.core.errors import ScenarioFormatError
from tbsim_env.data.gpudrive import read_gpudrive_json
from tbsim_env.data.scenario import Scenario
from tbsim_env.data.tfrecord import FRAMING_BYTES, iter_records, write_records
from tbsim_env.data.womd import read_scenarios

CASE_LIMIT_S = 5.0


@contextlib.contextmanager
def time_guard(seconds: float) -> Iterator[None]:
    """Fail the case if it runs longer than ``seconds`` (SIGALRM on the main thread)."""
    if threading.current_thread() is not threading.main_thread():
        start = time.monotonic()
        yield
        assert time.monotonic() - start < seconds
        return

    def on_alarm(signum, frame):  # noqa: ARG001
        raise TimeoutError(f"case ran longer than {seconds} s")

    old = signal.signal(signal.SIGALRM, on_alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def _load_all(path: Path, *, verify: bool = True) -> list[Scenario]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return list(read_scenarios(path, verify=verify))


def _payload(path: Path) -> bytes:
    ((_, _, payload),) = list(iter_records(path))
    return payload


def _outcome(path: Path, *, verify: bool) -> str:
    """'ok' or 'error' (ScenarioFormatError); anything else propagates and fails the test."""
    with time_guard(CASE_LIMIT_S):
        try:
            scenarios = _load_all(path, verify=verify)
        except ScenarioFormatError:
            return "error"
    for s in scenarios:
        assert isinstance(s, Scenario)
        s.validate()
    return "ok"


# ----------------------------------------------------------------------------- targeted damage


def test_truncated_real_file_at_many_offsets(tmp_path: Path, one_scenario_path: Path) -> None:
    data = one_scenario_path.read_bytes()
    cuts = sorted({1, 7, 8, 11, 12, 13, 100, len(data) - 4, len(data) - 1})
    cuts += np.linspace(14, len(data) - 5, 25).astype(int).tolist()
    path = tmp_path / "cut.tfrecord"
    for cut in cuts:
        path.write_bytes(data[:cut])
        with pytest.raises(ScenarioFormatError, match="truncated") as info:
            _load_all(path)
        assert info.value.record == 0 and info.value.offset == 0, cut


@pytest.mark.parametrize(
    ("position", "message"),
    [
        (2, "length CRC mismatch"),  # length bytes
        (10, "length CRC mismatch"),  # length CRC
        (5000, "data CRC mismatch"),  # payload
        (-2, "data CRC mismatch"),  # data CRC
    ],
)
def test_flipped_byte(tmp_path: Path, one_scenario_path: Path, position: int, message: str) -> None:
    data = bytearray(one_scenario_path.read_bytes())
    data[position] ^= 0x01
    path = tmp_path / "flip.tfrecord"
    path.write_bytes(bytes(data))
    with pytest.raises(ScenarioFormatError, match=message) as info:
        _load_all(path)
    assert info.value.path == str(path) and info.value.record == 0


def test_tf_example_file_is_rejected(tf_example_path: Path) -> None:
    with pytest.raises(ScenarioFormatError, match="not a valid Scenario protobuf") as info:
        _load_all(tf_example_path)
    assert info.value.record == 0 and "motion_data_one_example" in str(info.value)


def test_empty_file(tmp_path: Path) -> None:
    path = tmp_path / "empty.tfrecord"
    path.write_bytes(b"")
    with pytest.raises(ScenarioFormatError, match="no scenarios in file"):
        _load_all(path)


def test_garbage_bytes(tmp_path: Path) -> None:
    rng = np.random.default_rng(0)
    path = tmp_path / "garbage.tfrecord"
    for size in (3, 12, 100, 5000):
        path.write_bytes(rng.bytes(size))
        with pytest.raises(ScenarioFormatError):
            _load_all(path)
        with pytest.raises(ScenarioFormatError):
            _load_all(path, verify=False)


def test_garbage_payload_in_valid_framing(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    path = tmp_path / "framed_garbage.tfrecord"
    for size in (0, 1, 50, 4000):
        write_records(path, [rng.bytes(size)])
        with pytest.raises(ScenarioFormatError) as info:
            _load_all(path)
        assert info.value.record == 0


def test_scenario_without_tracks(tmp_path: Path, one_scenario_path: Path) -> None:
    from tbsim_env.data.protos import scenario_pb2

    msg = scenario_pb2.Scenario.FromString(_payload(one_scenario_path))
    msg.ClearField("tracks")
    path = tmp_path / "no_tracks.tfrecord"
    write_records(path, [msg.SerializeToString()])
    with pytest.raises(ScenarioFormatError, match="'tracks'.*empty"):
        _load_all(path)


def test_multi_record_file_with_corrupt_middle(
    tmp_path: Path, one_scenario_path: Path, scenario_input_path: Path
) -> None:
    first, last = _payload(one_scenario_path), _payload(scenario_input_path)
    path = tmp_path / "three.tfrecord"
    write_records(path, [first, first[: len(first) // 2], last])  # middle: cut-off protobuf
    with pytest.raises(ScenarioFormatError, match="record 1"):
        list(read_scenarios(path))
    with pytest.warns(UserWarning, match=r"record 1, byte offset \d+: not a valid Scenario"):
        got = list(read_scenarios(path, skip_bad=True))
    assert [s.scenario_id for s in got] == ["637f20cafde22ff8", "ee519cf571686d19"]

    # Same with a data-CRC error in the middle record: framing lets iteration resume.
    data = bytearray(path.read_bytes())
    middle = len(first) + FRAMING_BYTES
    data[middle + 12 + 10] ^= 0xFF
    path.write_bytes(bytes(data))
    with pytest.warns(UserWarning, match=f"record 1, byte offset {middle}: data CRC mismatch"):
        got = list(read_scenarios(path, skip_bad=True))
    assert [s.scenario_id for s in got] == ["637f20cafde22ff8", "ee519cf571686d19"]


def test_all_records_bad_with_skip_bad_still_raises(tmp_path: Path) -> None:
    path = tmp_path / "bad.tfrecord"
    write_records(path, [b"\x00\x01", b"junk"])
    with pytest.warns(UserWarning), pytest.raises(ScenarioFormatError, match="no scenarios"):
        list(read_scenarios(path, skip_bad=True))


# ----------------------------------------------------------------------------- fuzzing


def _mutate(
    data: bytes, rng: np.random.Generator, *, lo: int = 0, structural: bool = True
) -> bytes:
    """1-8 random edits at offsets >= ``lo``.

    Edits are bit flips and byte sets, plus (if ``structural``) truncation, insertion and
    deletion. Without structural edits most cases still decode, so they reach the Scenario
    conversion and validation instead of stopping in the protobuf decoder.
    """
    buf = bytearray(data)
    for _ in range(int(rng.integers(1, 9))):
        kind = rng.integers(0, 5 if structural else 2)
        if len(buf) <= lo + 1:
            break
        at = int(rng.integers(lo, len(buf)))
        if kind == 0:
            buf[at] ^= 1 << int(rng.integers(0, 8))
        elif kind == 1:
            buf[at] = int(rng.integers(0, 256))
        elif kind == 2:
            del buf[at:]
        elif kind == 3:
            buf[at:at] = rng.bytes(int(rng.integers(1, 9)))
        else:
            del buf[at : at + int(rng.integers(1, 9))]
    return bytes(buf)


@pytest.fixture(scope="module")
def real_payloads(one_scenario_path: Path, scenario_input_path: Path) -> list[bytes]:
    return [_payload(one_scenario_path), _payload(scenario_input_path)]


def test_fuzz_raw_file_mutations_with_crc_check(
    tmp_path: Path, one_scenario_path: Path, scenario_input_path: Path
) -> None:
    """CRC on: any byte edit of a real file must be caught as a ScenarioFormatError."""
    rng = np.random.default_rng(20240501)
    files = [one_scenario_path.read_bytes(), scenario_input_path.read_bytes()]
    path = tmp_path / "fuzz.tfrecord"
    for case in range(120):
        path.write_bytes(_mutate(files[case % 2], rng))
        assert _outcome(path, verify=True) == "error", case


def test_fuzz_raw_file_mutations_without_crc_check(
    tmp_path: Path, one_scenario_path: Path, scenario_input_path: Path
) -> None:
    """CRC off: framing bounds, protobuf decoder and Scenario validation must all hold."""
    rng = np.random.default_rng(7)
    files = [one_scenario_path.read_bytes(), scenario_input_path.read_bytes()]
    path = tmp_path / "fuzz.tfrecord"
    outcomes = []
    for case in range(120):
        path.write_bytes(_mutate(files[case % 2], rng))
        outcomes.append(_outcome(path, verify=False))
    assert set(outcomes) <= {"ok", "error"} and "error" in outcomes


def test_fuzz_payload_mutations_in_valid_framing(
    tmp_path: Path, real_payloads: list[bytes]
) -> None:
    """Re-framed mutated payloads (valid CRCs) reach the decoder and the validation."""
    rng = np.random.default_rng(99)
    path = tmp_path / "fuzz.tfrecord"
    outcomes = []
    for case in range(300):
        mutated = _mutate(real_payloads[case % 2], rng, structural=case % 3 == 0)
        write_records(path, [mutated])
        outcomes.append(_outcome(path, verify=True))
    # Both branches must be exercised for the test to mean anything.
    assert outcomes.count("ok") >= 20 and outcomes.count("error") >= 20, outcomes.count("ok")


def test_fuzz_gpudrive_json_mutations(tmp_path: Path, womd_dir: Path) -> None:
    rng = np.random.default_rng(3)
    data = (womd_dir / "gpudrive" / "tfrecord-00000-of-01000_222.json").read_bytes()
    path = tmp_path / "fuzz.json"
    outcomes = []
    for _ in range(30):
        path.write_bytes(_mutate(data, rng))
        with time_guard(CASE_LIMIT_S), warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                read_gpudrive_json(path).validate()
                outcomes.append("ok")
            except ScenarioFormatError:
                outcomes.append("error")
    assert "error" in outcomes
