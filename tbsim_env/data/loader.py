"""One entry point for scenarios: files, folders, globs or ``Scenario`` objects -> ``Scenario``s.

Formats are detected by content, then by extension: TFRecords (a valid length header) of raw
WOMD ``Scenario`` records (``tbsim_env.data.womd``) or of WOMD ``tf.train.Example`` records
(``tbsim_env.data.tf_example``; told apart by decoding the first record), ScenarioNet /
MetaDrive pickles (protocol header byte 0x80; ``tbsim_env.data.scenarionet``, restricted
unpickler) and GPUDrive / Nocturne JSON (a JSON object; ``tbsim_env.data.gpudrive``). Each may
be gzip-compressed (``.json.gz``, ``.pkl.gz``, ``.tfrecord.gz``; detected by content and read as a
stream, ``tbsim_env.data.compressed``). A folder or list may mix them.
"""

from __future__ import annotations

import enum
import glob
import os
import warnings
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import TypeAlias

from tbsim_env.core.errors import ScenarioFormatError
from tbsim_env.data.compressed import read_head, strip_gz
from tbsim_env.data.gpudrive import read_gpudrive_json
from tbsim_env.data.scenario import Scenario
from tbsim_env.data.scenarionet import PICKLE_MAGIC, read_scenarionet_pickle
from tbsim_env.data.tf_example import is_tf_example, read_tf_examples
from tbsim_env.data.tfrecord import iter_records, looks_like_tfrecord
from tbsim_env.data.womd import read_scenarios

ScenarioSource: TypeAlias = "str | os.PathLike | Scenario | Iterable[ScenarioSource]"
"""A path, glob, folder, ``Scenario``, or an iterable of those."""

_GLOB_CHARS = frozenset("*?[")
_SNIFF_BYTES = 64


class ScenarioFileFormat(enum.Enum):
    """File formats ``load_scenarios`` reads."""

    TFRECORD = "tfrecord"
    TF_EXAMPLE = "tf_example"
    SCENARIONET_PICKLE = "scenarionet_pickle"
    GPUDRIVE_JSON = "gpudrive_json"


_PICKLE_SUFFIXES = (".pkl", ".pickle")


def _is_scenario_file_name(path: Path) -> bool:
    plain = Path(strip_gz(path.name))
    return ".tfrecord" in path.name or plain.suffix in (".json", *_PICKLE_SUFFIXES)


def _tfrecord_kind(path: Path) -> ScenarioFileFormat:
    """Scenario or tf.Example TFRecord, by decoding the first record (Scenario if unsure)."""
    try:
        for _, _, payload in iter_records(path, verify=False):
            if is_tf_example(payload):
                return ScenarioFileFormat.TF_EXAMPLE
            break
    except ScenarioFormatError:
        pass  # reading it as a Scenario file reports the framing problem
    return ScenarioFileFormat.TFRECORD


def detect_format(path: str | os.PathLike) -> ScenarioFileFormat:
    """Format of one file: TFRecord framing (then Scenario or tf.Example records), a pickle
    header or a JSON object, else by extension; a gzip file by its decompressed content and
    its name without ``.gz``.

    Raises:
        FileNotFoundError: no such file.
        ScenarioFormatError: neither format, or a gzip file that does not decompress.
    """
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"no such scenario file: {str(p)!r}")
    if looks_like_tfrecord(p):
        return _tfrecord_kind(p)
    raw = read_head(p, _SNIFF_BYTES)
    head = raw.lstrip()
    p = p.with_name(strip_gz(p.name))
    if raw.startswith(PICKLE_MAGIC):
        return ScenarioFileFormat.SCENARIONET_PICKLE
    if head.startswith(b"{"):
        return ScenarioFileFormat.GPUDRIVE_JSON
    if p.suffix == ".json":
        return ScenarioFileFormat.GPUDRIVE_JSON
    if p.suffix in _PICKLE_SUFFIXES:
        return ScenarioFileFormat.SCENARIONET_PICKLE
    if ".tfrecord" in p.name:
        return ScenarioFileFormat.TFRECORD
    raise ScenarioFormatError(
        "unrecognised scenario file: neither TFRecord framing, a pickle nor a JSON object "
        f"(first bytes {head[:16]!r})",
        str(p),
    )


def _expand_path(item: str | os.PathLike) -> list[Path]:
    """Files named by one path, folder or glob string, in sorted order."""
    p = Path(item)
    if p.is_file():
        return [p]
    if p.is_dir():
        found = sorted(c for c in p.iterdir() if c.is_file() and _is_scenario_file_name(c))
        if not found:
            raise FileNotFoundError(
                f"no *.tfrecord*, *.json or *.pkl files (or *.gz of them) in folder {str(p)!r}"
            )
        return found
    text = os.fspath(item)
    if isinstance(text, str) and _GLOB_CHARS & set(text):
        matches = sorted(Path(m) for m in glob.glob(text) if Path(m).is_file())
        if not matches:
            raise FileNotFoundError(f"glob pattern {text!r} matched no files")
        return matches
    raise FileNotFoundError(f"no such scenario file or folder: {text!r}")


def _plan(source: ScenarioSource) -> list[Scenario | Path]:
    """Flatten ``source`` into Scenarios and file paths (raises for missing paths now)."""
    if isinstance(source, Scenario):
        return [source]
    if isinstance(source, (str, os.PathLike)):
        return list(_expand_path(source))
    if isinstance(source, (bytes, bytearray)):
        raise TypeError("scenario source must be a path, not bytes")
    try:
        items = list(source)
    except TypeError:
        raise TypeError(
            f"scenario source must be a path, glob, folder, Scenario or a list of those; "
            f"got {type(source).__name__}"
        ) from None
    return [entry for item in items for entry in _plan(item)]


def _read_file(path: Path, skip_bad: bool) -> Iterator[Scenario]:
    fmt = detect_format(path)
    if fmt is ScenarioFileFormat.TFRECORD:
        yield from read_scenarios(path, skip_bad=skip_bad)
    elif fmt is ScenarioFileFormat.TF_EXAMPLE:
        yield from read_tf_examples(path, skip_bad=skip_bad)
    elif fmt is ScenarioFileFormat.SCENARIONET_PICKLE:
        yield read_scenarionet_pickle(path)
    else:
        yield read_gpudrive_json(path)


def _iterate(plan: list[Scenario | Path], skip_bad: bool) -> Iterator[Scenario]:
    count = 0
    for entry in plan:
        if isinstance(entry, Scenario):
            count += 1
            yield entry
            continue
        try:
            for scenario in _read_file(entry, skip_bad):
                count += 1
                yield scenario
        except ScenarioFormatError as err:
            if not skip_bad:
                raise
            warnings.warn(f"{err}; skipping the rest of this file", stacklevel=3)
    if count == 0:
        raise ScenarioFormatError(
            f"no scenarios could be loaded from {len(plan)} source(s) "
            f"(first: {str(plan[0]) if plan else 'none'!r})"
        )


def iter_scenarios(source: ScenarioSource, *, skip_bad: bool = False) -> Iterator[Scenario]:
    """Lazily yield scenarios from ``source``.

    Paths are resolved when this is called (a missing path raises at once); files are read
    one record at a time while iterating.

    Args:
        source: a file path, a glob string, a folder (every ``*.tfrecord*``, ``*.json``,
            ``*.pkl`` and ``*.pickle`` in it, and their ``.gz``, sorted; not its subfolders),
            a ``Scenario``
            (passed through), or a list of any of those.
        skip_bad: warn about bad records and bad files and go on instead of raising.

    Raises:
        FileNotFoundError: a path that does not exist, or a glob / folder with no files.
        ScenarioFormatError: a bad file or record (unless ``skip_bad``), or nothing loadable.
    """
    return _iterate(_plan(source), skip_bad)


def load_scenarios(source: ScenarioSource, *, skip_bad: bool = False) -> list[Scenario]:
    """All scenarios of ``source`` as a list (see ``iter_scenarios`` for the arguments)."""
    return list(iter_scenarios(source, skip_bad=skip_bad))
