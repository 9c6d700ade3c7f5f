"""TFRecord framing: CRCs, lazy iteration, header index, writing, and every framing error."""

from __future__ import annotations

import struct
import warnings
from pathlib import Path

import crc32c
import pytest

from tbsim_env.core.errors import ScenarioFormatError
from tbsim_env.data.tfrecord import (
    FRAMING_BYTES,
    build_index,
    frame_record,
    iter_records,
    looks_like_tfrecord,
    masked_crc32c,
    read_record,
    write_records,
)

PAYLOADS = [b"first record", b"", bytes(range(256)) * 3, b"x" * 70_000]


def _offsets(payloads: list[bytes]) -> list[int]:
    out, at = [], 0
    for p in payloads:
        out.append(at)
        at += len(p) + FRAMING_BYTES
    return out


@pytest.fixture
def four(tmp_path: Path) -> Path:
    path = tmp_path / "four.tfrecord"
    assert write_records(path, PAYLOADS) == 4
    return path


def test_crc32c_is_castagnoli_and_mask_matches_formula() -> None:
    assert crc32c.crc32c(b"123456789") == 0xE3069283  # the CRC-32C check value
    crc = crc32c.crc32c(b"abc")
    rotated = ((crc >> 15) | (crc << 17)) & 0xFFFFFFFF
    assert masked_crc32c(b"abc") == (rotated + 0xA282EAD8) & 0xFFFFFFFF
    assert masked_crc32c(b"abc") != crc


def test_frame_layout() -> None:
    rec = frame_record(b"hello")
    assert len(rec) == 5 + FRAMING_BYTES
    assert struct.unpack("<Q", rec[:8])[0] == 5
    assert struct.unpack("<I", rec[8:12])[0] == masked_crc32c(rec[:8])
    assert rec[12:17] == b"hello"
    assert struct.unpack("<I", rec[17:])[0] == masked_crc32c(b"hello")


def test_roundtrip_iter_index_and_random_access(four: Path) -> None:
    got = list(iter_records(four))
    assert [g[0] for g in got] == [0, 1, 2, 3]
    assert [g[1] for g in got] == _offsets(PAYLOADS)
    assert [g[2] for g in got] == PAYLOADS
    index = build_index(four)
    assert len(index) == 4
    assert index.offsets.tolist() == _offsets(PAYLOADS)
    assert index.lengths.tolist() == [len(p) for p in PAYLOADS]
    assert index.file_size == four.stat().st_size
    for k in (3, 0, 2, -1):
        assert index.read(k) == PAYLOADS[k]
    assert read_record(four, int(index.offsets[2])) == PAYLOADS[2]
    with pytest.raises(IndexError, match="out of range"):
        index.read(4)


def test_real_file_frames_verify(one_scenario_path: Path) -> None:
    (rec,) = list(iter_records(one_scenario_path))
    assert rec[:2] == (0, 0)
    assert len(rec[2]) == 952_947 == one_scenario_path.stat().st_size - FRAMING_BYTES
    index = build_index(one_scenario_path)
    assert index.offsets.tolist() == [0] and index.lengths.tolist() == [952_947]
    assert looks_like_tfrecord(one_scenario_path)


def test_empty_file_yields_nothing(tmp_path: Path) -> None:
    path = tmp_path / "empty.tfrecord"
    path.write_bytes(b"")
    assert list(iter_records(path)) == []
    assert len(build_index(path)) == 0


def test_missing_file_is_file_not_found(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError):
        list(iter_records(tmp_path / "nope.tfrecord"))


def _corrupt(path: Path, at: int, xor: int = 0x5A) -> None:
    data = bytearray(path.read_bytes())
    data[at] ^= xor
    path.write_bytes(bytes(data))


@pytest.mark.parametrize(
    ("where", "message"),
    [
        (lambda off: off + 3, "length CRC mismatch"),  # inside the length
        (lambda off: off + 9, "length CRC mismatch"),  # inside the length CRC
        (lambda off: off + 12 + 100, "data CRC mismatch"),  # inside the payload
        (lambda off: off + 12 + len(PAYLOADS[2]) + 1, "data CRC mismatch"),  # data CRC
    ],
)
def test_corruption_names_file_record_and_offset(four: Path, where, message: str) -> None:
    off = _offsets(PAYLOADS)[2]
    _corrupt(four, where(off))
    with pytest.raises(ScenarioFormatError, match=message) as info:
        list(iter_records(four))
    err = info.value
    assert (err.path, err.record, err.offset) == (str(four), 2, off)
    assert (
        "record 2" in str(err) and f"byte offset {off}" in str(err) and "four.tfrecord" in str(err)
    )


def test_iteration_is_lazy_good_records_come_before_the_error(four: Path) -> None:
    _corrupt(four, _offsets(PAYLOADS)[3] + 12 + 5)
    it = iter_records(four)
    assert [next(it)[2] for _ in range(3)] == PAYLOADS[:3]
    with pytest.raises(ScenarioFormatError, match="record 3"):
        next(it)


def test_verify_false_skips_crc_checks(four: Path) -> None:
    _corrupt(four, _offsets(PAYLOADS)[0] + 12 + 2)
    _corrupt(four, _offsets(PAYLOADS)[1] + 9)
    got = [g[2] for g in iter_records(four, verify=False)]
    assert got[0] != PAYLOADS[0] and got[1:] == PAYLOADS[1:]


@pytest.mark.parametrize(
    "cut", [1, 7, 11, 12, 13, 12 + len(PAYLOADS[0]), 12 + len(PAYLOADS[0]) + 3]
)
def test_truncation(tmp_path: Path, cut: int) -> None:
    path = tmp_path / "cut.tfrecord"
    path.write_bytes(frame_record(PAYLOADS[0])[:cut])
    with pytest.raises(ScenarioFormatError, match="truncated") as info:
        list(iter_records(path))
    assert info.value.record == 0 and info.value.offset == 0
    if cut >= 12:
        with pytest.raises(ScenarioFormatError, match="truncated"):
            build_index(path)


def test_absurd_length_with_valid_length_crc(tmp_path: Path) -> None:
    length = struct.pack("<Q", 2**60)
    path = tmp_path / "absurd.tfrecord"
    path.write_bytes(length + struct.pack("<I", masked_crc32c(length)) + b"tiny")
    for fn in (lambda: list(iter_records(path)), lambda: build_index(path)):
        with pytest.raises(ScenarioFormatError, match="absurd record length"):
            fn()
    assert not looks_like_tfrecord(path)


def test_trailing_garbage_is_a_truncated_header(four: Path) -> None:
    four.write_bytes(four.read_bytes() + b"\x01\x02\x03")
    with pytest.raises(ScenarioFormatError, match="truncated record header") as info:
        list(iter_records(four))
    assert info.value.record == 4


def test_skip_bad_data_crc_continues_with_next_record(four: Path) -> None:
    _corrupt(four, _offsets(PAYLOADS)[1] + 12 + 1)  # data CRC of the empty payload
    with pytest.warns(UserWarning, match=r"record 1.*data CRC mismatch.*skipping"):
        got = list(iter_records(four, skip_bad=True))
    assert [g[0] for g in got] == [0, 2, 3]
    assert [g[2] for g in got] == [PAYLOADS[0], PAYLOADS[2], PAYLOADS[3]]


def test_skip_bad_corrupt_length_cannot_resync_and_stops(four: Path) -> None:
    _corrupt(four, _offsets(PAYLOADS)[2] + 1)
    with pytest.warns(UserWarning, match=r"record 2.*length CRC mismatch.*stopping"):
        got = list(iter_records(four, skip_bad=True))
    assert [g[0] for g in got] == [0, 1]


def test_build_index_checks_length_crc_but_not_payload(four: Path) -> None:
    off = _offsets(PAYLOADS)[3]
    _corrupt(four, off + 12 + 10)
    index = build_index(four)  # header scan only: payload corruption is not seen here
    assert len(index) == 4
    with pytest.raises(ScenarioFormatError, match="data CRC mismatch"):
        index.read(3)
    _corrupt(four, off + 2)
    with pytest.raises(ScenarioFormatError, match="length CRC mismatch"):
        build_index(four)


def test_read_record_at_a_wrong_offset(four: Path) -> None:
    with pytest.raises(ScenarioFormatError, match="length CRC mismatch"):
        read_record(four, 5)
    with pytest.raises(ScenarioFormatError, match="no record at byte offset"):
        read_record(four, 10**9)


def test_gzip_file_is_streamed(tmp_path: Path) -> None:
    import gzip

    path = tmp_path / "z.tfrecord.gz"
    path.write_bytes(gzip.compress(b"".join(frame_record(p) for p in PAYLOADS)))
    assert looks_like_tfrecord(path)
    assert [p for _, _, p in iter_records(path)] == PAYLOADS
    assert [o for _, o, _ in iter_records(path)] == _offsets(PAYLOADS)


def test_gzip_stream_with_an_absurd_length_is_refused(tmp_path: Path) -> None:
    import gzip

    head = struct.pack("<Q", 1 << 40)
    path = tmp_path / "z.tfrecord.gz"
    path.write_bytes(gzip.compress(head + struct.pack("<I", masked_crc32c(head)) + b"x" * 10))
    with pytest.raises(ScenarioFormatError, match="absurd record length"):
        list(iter_records(path))


def test_looks_like_tfrecord_rejects_json(tmp_path: Path) -> None:
    path = tmp_path / "a.json"
    path.write_text('{"scenario_id": "x", "objects": []}')
    assert not looks_like_tfrecord(path)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ScenarioFormatError, match="length CRC mismatch"):
            list(iter_records(path))
