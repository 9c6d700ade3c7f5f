"""Exception types of tbsim. Every message names the file, record and field at fault."""

from __future__ import annotations


class TbsimError(Exception):
    """Base class of every error raised on purpose by tbsim."""


class ScenarioFormatError(TbsimError, ValueError):
    """A scenario file or record is malformed.

    Attributes:
        path: file the record came from (or a description such as ``"<generated>"``).
        record: 0-based record index inside the file, or ``None`` for single-record formats.
        offset: byte offset of the record start inside the file, or ``None``.
        reason: what is wrong, naming the field where possible.
    """

    def __init__(
        self,
        reason: str,
        path: str | None = None,
        record: int | None = None,
        offset: int | None = None,
    ) -> None:
        self.path = path
        self.record = record
        self.offset = offset
        self.reason = reason
        where = []
        if path is not None:
            where.append(f"file {path!r}")
        if record is not None:
            where.append(f"record {record}")
        if offset is not None:
            where.append(f"byte offset {offset}")
        prefix = ", ".join(where)
        super().__init__(f"{prefix}: {reason}" if prefix else reason)


class ActionError(TbsimError, ValueError):
    """An action given to the environment is not usable (NaN, wrong shape, unknown agent)."""


class CheckpointError(TbsimError, ValueError):
    """A checkpoint does not match the model it is loaded into."""
