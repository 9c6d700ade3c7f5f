"""Sharded on-disk cache of preprocessed scenarios (``SceneTokens``) for training.

Layout of a cache folder::

    manifest.json        {"format": "tbsim-tokens-v1", "token_config": {...},
                          "shards": [{"file": "shard-00000.safetensors", "count": 64}, ...],
                          "scenario_ids": [...], "sources": [...]}
    shard-00000.safetensors
    ...

Each shard is one safetensors file (no pickle): the arrays of scene i are stored under the keys
``"{i}.{field}"``, the scenario ids in the file metadata. ``TokenCache`` is a
``torch.utils.data.Dataset`` over the whole folder that keeps the shards it read last in memory
(an LRU of ``max_shards`` shards, or all of them), so a sequential or shard-grouped sampler reads
each file once per epoch and a random sampler over a cache that fits in memory reads it once.
``open_training_data("a,b*20")`` joins several caches, oversampling some (few real scenes among
thousands of generated ones).

``build_cache`` fills a folder from WOMD TFRecords, GPUDrive JSON or the procedural generator with
several worker processes and a progress bar.
"""

from __future__ import annotations

import dataclasses
import json
import multiprocessing as mp
import re
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from safetensors import safe_open
from safetensors.numpy import save_file
from torch.utils.data import ConcatDataset, Dataset
from tqdm import tqdm

from tbsim_env.core.config import TokenConfig
from tbsim_env.core.constants import NUM_STEPS
from tbsim_env.core.errors import TbsimError
from tbsim_env.core.lru import LRU
from tbsim_env.data.scenario import Scenario
from tbsim_env.data.tokens import SceneTokens

FORMAT = "tbsim-tokens-v1"
_ARRAY_FIELDS = tuple(f.name for f in dataclasses.fields(SceneTokens) if f.name != "scenario_id")
_GENERATED = re.compile(
    r"^generated(?P<recorded>-recorded)?:(?P<layouts>[a-z_,]+):(?P<start>\d+)-(?P<stop>\d+)$"
)
_ADDED_FIELDS = {"frame_yaw": np.zeros((), np.float64)}
"""Fields that shards written before them lack, with the value that keeps such a shard's
meaning (``frame_yaw`` 0: its ``map_boundary`` is axis-aligned in the token frame)."""


class CacheError(TbsimError, ValueError):
    """A cache folder or shard is missing, corrupt or of another format."""


def write_shard(tokens: Sequence[SceneTokens], path: str | Path) -> None:
    """Write scenes to one safetensors shard."""
    arrays: dict[str, np.ndarray] = {}
    for i, t in enumerate(tokens):
        for name in _ARRAY_FIELDS:
            arrays[f"{i}.{name}"] = np.ascontiguousarray(getattr(t, name))
    meta = {"format": FORMAT, "count": str(len(tokens))}
    meta["scenario_ids"] = json.dumps([t.scenario_id for t in tokens])
    save_file(arrays, str(path), metadata=meta)


def read_shard(path: str | Path) -> list[SceneTokens]:
    """Read every scene of a shard (arrays are numpy, fields checked)."""
    path = Path(path)
    try:
        with safe_open(str(path), framework="numpy") as f:
            meta = f.metadata() or {}
            if meta.get("format") != FORMAT:
                raise CacheError(f"{path}: not a {FORMAT} shard (metadata {meta.get('format')!r})")
            ids = json.loads(meta["scenario_ids"])
            keys = set(f.keys())
            out = []
            for i, sid in enumerate(ids):
                fields = {name: _read_field(f, keys, f"{i}.{name}") for name in _ARRAY_FIELDS}
                out.append(SceneTokens(scenario_id=sid, **fields))
            return out
    except CacheError:
        raise
    except Exception as err:  # safetensors raises several exception types on damaged files
        raise CacheError(f"{path}: cannot read shard: {err}") from err


def _read_field(f, keys: set[str], key: str) -> np.ndarray:
    """Array ``key`` ("{scene}.{field}") of an open shard; the default of a field that older
    shards lack (``_ADDED_FIELDS``) where it is absent."""
    name = key.split(".", 1)[1]
    if key not in keys and name in _ADDED_FIELDS:
        return _ADDED_FIELDS[name].copy()
    return f.get_tensor(key)


def parse_generated(spec: str) -> list[tuple[str, int, bool]]:
    """``"generated:intersection,merge:0-99"`` -> [(layout, seed, recorded), ...], layouts
    alternating; ``generated-recorded:...`` marks the scenes to be generated with the fitted
    recording (parked vehicles, tracker jitter: ``generator.recording.RECORDED``)."""
    m = _GENERATED.match(spec)
    if not m:
        raise ValueError(
            f"bad generator source {spec!r}; use e.g. generated:intersection,merge:0-99"
        )
    layouts = m["layouts"].split(",")
    recorded = m["recorded"] is not None
    first, last = int(m["start"]), int(m["stop"])
    return [(layouts[s % len(layouts)], s, recorded) for s in range(first, last + 1)]


def _iter_sources(sources: Sequence[str]) -> Iterator[Scenario | tuple[str, int, bool]]:
    from tbsim_env.data.loader import iter_scenarios

    for src in sources:
        if str(src).startswith(("generated:", "generated-recorded:")):
            yield from parse_generated(str(src))
        else:
            yield from iter_scenarios(src)


def _work(item: Scenario | tuple[str, int, bool], cfg: TokenConfig) -> SceneTokens | str:
    from tbsim_env.data.preprocess import preprocess_scenario

    try:
        if isinstance(item, tuple):
            from tbsim_env.data.generator import generate_scenario
            from tbsim_env.data.generator.recording import RECORDED

            layout, seed, recorded = item
            item = generate_scenario(layout, seed, recording=RECORDED if recorded else None)
        # Training and validation losses compare with the whole logged episode (of WOMD's
        # 91 steps: 20 s scenes are cut to them, as WOSAC scores them).
        item = item.motion_window()
        item.require_log_until(NUM_STEPS - 1, "a token cache (training targets)")
        return preprocess_scenario(item, cfg)
    except ValueError as err:  # e.g. too many relevant agents, a history-only scene
        sid = item.scenario_id if isinstance(item, Scenario) else str(item)
        return f"skipped {sid}: {err}"


def _work_star(args):
    return _work(*args)


def build_cache(
    sources: Sequence[str],
    out: str | Path,
    *,
    cfg: TokenConfig | None = None,
    workers: int = 2,
    shard_size: int = 64,
    exclude_ids: Sequence[str] = (),
    progress: bool = True,
) -> dict:
    """Preprocess scenarios into a cache folder.

    Args:
        sources: TFRecord / JSON paths, globs or folders, or ``generated:LAYOUTS:A-B`` specs.
        out: cache folder (created; an existing manifest is replaced).
        cfg: token limits (stored in the manifest).
        workers: worker processes (1 = in this process).
        shard_size: scenes per shard.
        exclude_ids: scenario ids to leave out (held-out sets).
        progress: show a tqdm bar.

    Returns:
        The manifest (also written to ``out/manifest.json``).
    """
    cfg = cfg or TokenConfig(training=True)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    excluded = set(exclude_ids)
    items = (
        x
        for x in _iter_sources(sources)
        if not (isinstance(x, Scenario) and x.scenario_id in excluded)
    )
    shards, ids, buffer, skipped = [], [], [], []

    def flush() -> None:
        if not buffer:
            return
        name = f"shard-{len(shards):05d}.safetensors"
        write_shard(buffer, out / name)
        shards.append({"file": name, "count": len(buffer)})
        buffer.clear()

    bar = tqdm(desc="preprocess", unit="scenario", disable=not progress)
    if workers > 1:
        ctx = mp.get_context("spawn")
        with ctx.Pool(workers) as pool:
            results = pool.imap(_work_star, ((x, cfg) for x in items), chunksize=4)
            for res in results:
                _collect(res, buffer, ids, skipped, excluded)
                bar.update(1)
                if len(buffer) >= shard_size:
                    flush()
    else:
        for x in items:
            _collect(_work(x, cfg), buffer, ids, skipped, excluded)
            bar.update(1)
            if len(buffer) >= shard_size:
                flush()
    flush()
    bar.close()
    manifest = {
        "format": FORMAT,
        "token_config": dataclasses.asdict(cfg),
        "shards": shards,
        "scenario_ids": ids,
        "sources": [str(s) for s in sources],
        "excluded": sorted(excluded),
        "skipped": skipped,
    }
    (out / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return manifest


def _collect(res, buffer: list, ids: list, skipped: list, excluded: set) -> None:
    if isinstance(res, str):
        skipped.append(res)
    elif res.scenario_id not in excluded:
        buffer.append(res)
        ids.append(res.scenario_id)


@dataclass
class TokenCache:
    """Map-style dataset over a cache folder; item i is a ``SceneTokens``.

    Attributes:
        root: the folder.
    """

    root: Path
    max_shards: int | None = 1

    def __post_init__(self) -> None:
        self.root = Path(self.root)
        if self.max_shards is not None and self.max_shards < 1:
            raise ValueError(f"max_shards must be >= 1 or None, got {self.max_shards}")
        path = self.root / "manifest.json"
        if not path.exists():
            raise CacheError(f"{self.root}: no manifest.json (build it with `tbsim preprocess`)")
        self.manifest = json.loads(path.read_text())
        if self.manifest.get("format") != FORMAT:
            raise CacheError(f"{path}: format {self.manifest.get('format')!r}, expected {FORMAT}")
        counts = [s["count"] for s in self.manifest["shards"]]
        self._starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self._loaded: LRU[int, list[SceneTokens]] = LRU(self.max_shards)

    def __len__(self) -> int:
        return int(self._starts[-1])

    @property
    def scenario_ids(self) -> list[str]:
        return list(self.manifest["scenario_ids"])

    def shard_of(self, index: int) -> int:
        return int(np.searchsorted(self._starts, index, side="right") - 1)

    def __getitem__(self, index: int) -> SceneTokens:
        if not 0 <= index < len(self):
            raise IndexError(f"index {index} outside [0, {len(self)})")
        k = self.shard_of(index)
        shard = self._loaded.get(k)
        if shard is None:
            shard = self._loaded.put(k, read_shard(self.root / self.manifest["shards"][k]["file"]))
        return shard[index - int(self._starts[k])]


def open_training_data(spec: str, max_shards: int | None = 1) -> Dataset:
    """Dataset over one or several cache folders.

    Args:
        spec: comma-separated cache folders; ``FOLDER*N`` repeats a folder N times (N >= 1), so
            a uniform sampler draws its scenes N times as often. Example:
            ``"runs/generated,runs/real*20"``.
        max_shards: shards each folder keeps in memory (None: all).

    Returns:
        A ``TokenCache`` for a single folder, else a ``ConcatDataset`` of them.

    Raises:
        CacheError: a folder is not a cache; ValueError: a malformed repeat count.
    """
    parts: list[Dataset] = []
    for item in (x.strip() for x in spec.split(",")):
        if not item:
            continue
        folder, _, rep = item.partition("*")
        if rep and (not rep.isdigit() or int(rep) < 1):
            raise ValueError(f"data spec {item!r}: repeat count must be a positive integer")
        cache = TokenCache(Path(folder), max_shards=max_shards)
        parts.extend([cache] * (int(rep) if rep else 1))
    if not parts:
        raise ValueError(f"data spec {spec!r} names no cache folder")
    return parts[0] if len(parts) == 1 else ConcatDataset(parts)
