"""Transparent gzip for scenario files: every format may come gzip-compressed.

A file is gzip when it starts with the gzip magic bytes (``1f 8b``), whatever its name
(``.json.gz``, ``.pkl.gz``, ``.tfrecord.gz``, ...). Reading streams the decompressed bytes: a
TFRecord is read one record at a time, never as a whole decompressed copy. Every gzip problem
(bad header, corrupt deflate data, a stream cut short, a CRC or length trailer that does not
match) is one ``ScenarioFormatError`` naming the file.
"""

from __future__ import annotations

import gzip
import os
import zlib
from typing import BinaryIO

from tbsim_env.core.errors import ScenarioFormatError

GZIP_MAGIC = b"\x1f\x8b"
GZIP_SUFFIX = ".gz"

PathLike = str | os.PathLike

_GZIP_ERRORS = (OSError, EOFError, zlib.error)
"""What Python's gzip raises on bad data: ``BadGzipFile`` (an ``OSError``) for a bad header
or trailer, ``EOFError`` for a stream cut short, ``zlib.error`` for corrupt deflate data."""


def is_gzip(path: PathLike) -> bool:
    """Whether the file starts with the gzip magic bytes.

    Raises:
        FileNotFoundError: no such file.
    """
    with open(os.fspath(path), "rb") as fh:
        return fh.read(len(GZIP_MAGIC)) == GZIP_MAGIC


def strip_gz(name: str) -> str:
    """The file name without a trailing ``.gz`` (``a.json.gz`` -> ``a.json``)."""
    return name[: -len(GZIP_SUFFIX)] if name.endswith(GZIP_SUFFIX) else name


class GzipStream:
    """A readable binary stream over a gzip file whose read errors name the file.

    Only ``read`` (and the context-manager protocol) is offered: the TFRecord, JSON and pickle
    readers need nothing else.
    """

    def __init__(self, path: PathLike) -> None:
        self.name = os.fspath(path)
        self._fh = gzip.open(self.name, "rb")

    def read(self, size: int = -1) -> bytes:
        """Up to ``size`` decompressed bytes (all that is left for ``size < 0``).

        Raises:
            ScenarioFormatError: corrupt or truncated gzip data.
        """
        try:
            return self._fh.read(size)
        except _GZIP_ERRORS as err:
            raise ScenarioFormatError(
                f"corrupt or truncated gzip stream: {err or type(err).__name__}", self.name
            ) from err

    def close(self) -> None:
        self._fh.close()

    def __enter__(self) -> GzipStream:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_scenario_file(path: PathLike) -> BinaryIO | GzipStream:
    """Open ``path`` for reading its (decompressed) bytes: a gzip stream or the plain file.

    Raises:
        FileNotFoundError: no such file.
    """
    return GzipStream(path) if is_gzip(path) else open(os.fspath(path), "rb")


def read_head(path: PathLike, size: int) -> bytes:
    """The first ``size`` decompressed bytes of ``path`` (fewer when it is shorter).

    Raises:
        ScenarioFormatError: a gzip file whose first bytes do not decompress.
    """
    with open_scenario_file(path) as fh:
        return fh.read(size)


def read_all(path: PathLike) -> bytes:
    """The whole decompressed content of a single-scenario file (JSON, pickle).

    The gzip trailer (CRC-32 and length) is checked, so a stream cut short or altered raises
    instead of returning part of the file.

    Raises:
        ScenarioFormatError: corrupt or truncated gzip data.
    """
    with open_scenario_file(path) as fh:
        return fh.read()
