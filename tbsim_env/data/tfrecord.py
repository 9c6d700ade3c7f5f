"""Streaming TFRecord framing (no TensorFlow): read, index and write records.

A TFRecord file is a plain concatenation of records, each laid out as::

    offset 0        8 B   uint64 LE  payload length n
    offset 8        4 B   uint32 LE  masked CRC32C of the 8 length bytes
    offset 12       n B   payload (one serialized protobuf)
    offset 12 + n   4 B   uint32 LE  masked CRC32C of the payload

CRC32C is the Castagnoli CRC (``crc32c`` package); the mask is
``((crc >> 15 | crc << 17) + 0xA282EAD8) mod 2**32`` (rotation on 32 bits).

Every framing problem raises ``ScenarioFormatError`` naming the file, the 0-based record index,
the byte offset of the record start and what is wrong. Reading is lazy: one record is held in
memory at a time, so multi-GB shards are fine. Gzip-compressed files are read the same way, as
a stream (``tbsim_env.data.compressed``); random access (``build_index``, ``read_record``) needs
an uncompressed file.
"""

from __future__ import annotations

import os
import struct
import warnings
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from typing import BinaryIO

import crc32c as _crc32c
import numpy as np

from tbsim_env.core.errors import ScenarioFormatError
from tbsim_env.data.compressed import GzipStream, is_gzip, open_scenario_file, read_head

HEADER_BYTES = 12
"""Length (8 B) plus length CRC (4 B)."""
FOOTER_BYTES = 4
"""Payload CRC."""
FRAMING_BYTES = HEADER_BYTES + FOOTER_BYTES
_MASK_DELTA = 0xA282EAD8
_U32 = 0xFFFFFFFF
MAX_STREAM_RECORD_BYTES = 1 << 30
"""Largest payload accepted from a compressed stream, whose size is unknown until read
(a WOMD Scenario record is a few MB)."""
_CHUNK_BYTES = 1 << 24

PathLike = str | os.PathLike


def masked_crc32c(data: bytes) -> int:
    """Masked CRC32C of ``data`` as TFRecord stores it (uint32)."""
    crc = _crc32c.crc32c(data)
    return (((crc >> 15) | (crc << 17)) + _MASK_DELTA) & _U32


def frame_record(payload: bytes) -> bytes:
    """One TFRecord record (header, payload, footer) around ``payload``."""
    length = struct.pack("<Q", len(payload))
    return (
        length
        + struct.pack("<I", masked_crc32c(length))
        + payload
        + struct.pack("<I", masked_crc32c(payload))
    )


def write_records(path: PathLike, payloads: Iterable[bytes]) -> int:
    """Write ``payloads`` as a TFRecord file (overwrites). Returns the number of records."""
    count = 0
    with open(path, "wb") as fh:
        for payload in payloads:
            fh.write(frame_record(bytes(payload)))
            count += 1
    return count


def _read_header(
    fh: BinaryIO | GzipStream,
    path: str,
    index: int | None,
    offset: int,
    file_size: int | None,
    *,
    verify: bool,
) -> int | None:
    """Read and check the 12-byte header at ``offset``.

    Args:
        file_size: bytes in the file, bounding the length; ``None`` for a gzip stream, whose
            lengths are bounded by ``MAX_STREAM_RECORD_BYTES`` (a short payload is caught when
            it is read).

    Returns:
        The payload length, or ``None`` at a clean end of file.
    """
    head = fh.read(HEADER_BYTES)
    if not head:
        return None
    if len(head) < HEADER_BYTES:
        raise ScenarioFormatError(
            f"truncated record header: {len(head)} of {HEADER_BYTES} bytes before end of file",
            path,
            index,
            offset,
        )
    (length,) = struct.unpack("<Q", head[:8])
    (length_crc,) = struct.unpack("<I", head[8:])
    if verify and masked_crc32c(head[:8]) != length_crc:
        raise ScenarioFormatError(
            f"length CRC mismatch (stored 0x{length_crc:08x}, computed "
            f"0x{masked_crc32c(head[:8]):08x}): not a TFRecord or corrupt header",
            path,
            index,
            offset,
        )
    if file_size is None:
        if length > MAX_STREAM_RECORD_BYTES:
            raise ScenarioFormatError(
                f"absurd record length: header says {length} payload bytes, more than the "
                f"{MAX_STREAM_RECORD_BYTES} a record of a compressed stream may hold",
                path,
                index,
                offset,
            )
        return length
    remaining = file_size - offset - FRAMING_BYTES
    if length > remaining:
        what = "absurd record length" if length > file_size else "truncated payload"
        raise ScenarioFormatError(
            f"{what}: header says {length} payload bytes but only {max(remaining, 0)} "
            f"remain before end of file",
            path,
            index,
            offset,
        )
    return length


def _read_exact(fh: BinaryIO | GzipStream, size: int) -> bytes:
    """Up to ``size`` bytes, read in chunks so that a corrupt length allocates no more than
    the stream holds."""
    chunks, left = [], size
    while left > 0:
        chunk = fh.read(min(left, _CHUNK_BYTES))
        if not chunk:
            break
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def _read_payload(
    fh: BinaryIO | GzipStream,
    path: str,
    index: int | None,
    offset: int,
    length: int,
    *,
    verify: bool,
) -> bytes:
    """Read payload and footer after a checked header; verify the data CRC."""
    payload = _read_exact(fh, length)
    footer = fh.read(FOOTER_BYTES)
    if len(payload) < length or len(footer) < FOOTER_BYTES:
        raise ScenarioFormatError(
            f"truncated payload: expected {length} + {FOOTER_BYTES} bytes, got "
            f"{len(payload) + len(footer)}",
            path,
            index,
            offset,
        )
    if verify:
        (stored,) = struct.unpack("<I", footer)
        computed = masked_crc32c(payload)
        if stored != computed:
            raise ScenarioFormatError(
                f"data CRC mismatch (stored 0x{stored:08x}, computed 0x{computed:08x}) "
                f"over {length} payload bytes",
                path,
                index,
                offset,
            )
    return payload


def _located(err: ScenarioFormatError, index: int, offset: int) -> ScenarioFormatError:
    """``err`` with the record and offset filled in where the stream did not know them."""
    if err.record is not None:
        return err
    return ScenarioFormatError(err.reason, err.path, index, offset)


def iter_records(
    path: PathLike, *, verify: bool = True, skip_bad: bool = False
) -> Iterator[tuple[int, int, bytes]]:
    """Yield ``(index, offset, payload)`` for every record, lazily.

    A gzip-compressed file is decompressed as it is read (one record in memory at a time);
    offsets are then offsets into the decompressed stream.

    Args:
        path: TFRecord file, plain or gzip-compressed.
        verify: check both masked CRCs (the length bound against the file size is always checked).
        skip_bad: on a bad record, ``warnings.warn`` naming it instead of raising. A record whose
            header was fine but whose data CRC fails is skipped and iteration goes on with the
            next record; a bad header (length CRC, truncation) or bad gzip data cannot be
            resynchronised, so the warning says so and iteration stops.

    Yields:
        (record index, byte offset of the record start, payload bytes). An empty file yields
        nothing.

    Raises:
        ScenarioFormatError: framing or gzip problem (when ``skip_bad`` is False).
        FileNotFoundError: ``path`` does not exist.
    """
    name = os.fspath(path)
    compressed = is_gzip(name)
    file_size = None if compressed else os.path.getsize(name)
    with open_scenario_file(name) as fh:
        index, offset = 0, 0
        while True:
            try:
                length = _read_header(fh, name, index, offset, file_size, verify=verify)
            except ScenarioFormatError as err:
                if not skip_bad:
                    raise _located(err, index, offset) from None
                warnings.warn(
                    f"{_located(err, index, offset)}; cannot resynchronise, stopping", stacklevel=2
                )
                return
            if length is None:
                return
            try:
                payload = _read_payload(fh, name, index, offset, length, verify=verify)
            except ScenarioFormatError as err:
                if not skip_bad:
                    raise _located(err, index, offset) from None
                if compressed:  # a stream cannot skip what it could not read
                    warnings.warn(
                        f"{_located(err, index, offset)}; cannot resynchronise, stopping",
                        stacklevel=2,
                    )
                    return
                warnings.warn(f"{err}; skipping this record", stacklevel=2)
                payload = None
            if payload is not None:
                yield index, offset, payload
            index += 1
            offset += length + FRAMING_BYTES
            if not compressed:
                fh.seek(offset)


def _refuse_gzip(name: str) -> None:
    """Random access needs byte offsets into the file: refuse a compressed one."""
    if is_gzip(name):
        raise ScenarioFormatError(
            "gzip-compressed TFRecords are read in order only (load_scenarios, "
            "iter_scenarios); gunzip the file for access by record index or scenario id",
            name,
        )


@dataclass(frozen=True)
class TFRecordIndex:
    """Record offsets of one TFRecord file, from a header-only scan.

    Attributes:
        path: the file.
        offsets: [R] int64, byte offset of each record start.
        lengths: [R] int64, payload byte count of each record.
        file_size: file size in bytes at scan time.
    """

    path: str
    offsets: np.ndarray
    lengths: np.ndarray
    file_size: int

    def __len__(self) -> int:
        return int(self.offsets.shape[0])

    def read(self, index: int, *, verify: bool = True) -> bytes:
        """Payload of record ``index`` (0-based)."""
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"record {index} out of range: {self.path!r} has {n} records")
        return read_record(self.path, int(self.offsets[index]), verify=verify)


def build_index(path: PathLike) -> TFRecordIndex:
    """Scan record headers (seeking over payloads) and return their offsets.

    The length CRC and the length bound are checked; payloads are not read, so data CRCs are
    checked only when a record is read.

    Raises:
        ScenarioFormatError: bad or truncated header.
    """
    name = os.fspath(path)
    _refuse_gzip(name)
    file_size = os.path.getsize(name)
    offsets: list[int] = []
    lengths: list[int] = []
    with open(name, "rb") as fh:
        offset = 0
        while True:
            length = _read_header(fh, name, len(offsets), offset, file_size, verify=True)
            if length is None:
                break
            offsets.append(offset)
            lengths.append(length)
            offset += length + FRAMING_BYTES
            fh.seek(offset)
    return TFRecordIndex(
        path=name,
        offsets=np.asarray(offsets, dtype=np.int64),
        lengths=np.asarray(lengths, dtype=np.int64),
        file_size=file_size,
    )


def read_record(
    path: PathLike, offset: int, *, verify: bool = True, record: int | None = None
) -> bytes:
    """Read the one record that starts at byte ``offset``.

    Args:
        path: TFRecord file.
        offset: byte offset of the record start (from ``build_index``).
        verify: check both CRCs.
        record: record index, only used in error messages.

    Raises:
        ScenarioFormatError: bad framing at that offset (or no record there).
    """
    name = os.fspath(path)
    _refuse_gzip(name)
    file_size = os.path.getsize(name)
    if not 0 <= offset < file_size:
        raise ScenarioFormatError(
            f"no record at byte offset {offset}: file has {file_size} bytes", name, record, offset
        )
    with open(name, "rb") as fh:
        fh.seek(offset)
        length = _read_header(fh, name, record, offset, file_size, verify=verify)
        if length is None:  # unreachable: offset < file_size guarantees bytes to read
            raise ScenarioFormatError("no record at this offset", name, record, offset)
        return _read_payload(fh, name, record, offset, length, verify=verify)


def looks_like_tfrecord(path: PathLike) -> bool:
    """Whether the file starts with a valid TFRecord header (length CRC and length bound),
    after decompression for a gzip file.

    An empty file (or empty stream) counts as a TFRecord with zero records.

    Raises:
        ScenarioFormatError: a gzip file whose first bytes do not decompress.
    """
    name = os.fspath(path)
    size = os.path.getsize(name)
    if size == 0:
        return True
    compressed = is_gzip(name)
    head = read_head(name, HEADER_BYTES)
    if compressed and not head:
        return True
    if len(head) < HEADER_BYTES:
        return False
    (length,) = struct.unpack("<Q", head[:8])
    (length_crc,) = struct.unpack("<I", head[8:])
    bound = MAX_STREAM_RECORD_BYTES if compressed else size - FRAMING_BYTES
    return masked_crc32c(head[:8]) == length_crc and length <= bound
