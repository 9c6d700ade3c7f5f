"""Sharded, resumable WOSAC jobs: export, evaluation and scoring at dataset scale.

A job is cut into shards (by default one per input file; ``shard_size`` cuts TFRecord files
into record ranges and groups single-scenario files). Each shard is one task, run in this
process (``LocalExecutor``) or as a Ray task (``RayExecutor``: a local Ray instance by default,
a cluster at an address). A task returns its output as bytes and the driver writes each
finished shard atomically (a temporary file, then ``os.replace``) into the work folder, so a
killed worker or driver leaves no partial shard. A rerun skips the shards already there:
nothing is written twice, nothing is lost. The folder's ``tbsim-run.json`` records the job's
settings and shard plan, and a rerun with other settings is refused instead of mixing them.

Finished shards are then merged: submission shards into one ``SimAgentsChallengeSubmission``
(or checked as a set of shard files), score shards into one dataset-level score table.

Ray is optional (the ``rl`` extra): only ``RayExecutor`` imports it.
"""

from __future__ import annotations

import dataclasses
import json
import os
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from tqdm import tqdm

from tbsim_env.core.errors import TbsimError
from tbsim_env.data.scenario import Scenario
from tbsim_env.evaluation import RolloutSettings

if TYPE_CHECKING:
    from tbsim_env.benchmark.runner import BenchmarkSettings

MANIFEST = "tbsim-run.json"
"""The work folder's record of the job (settings and shard plan)."""
TMP_MARK = ".tmp-"
"""Temporary files of unfinished writes carry this in their name (removed on a rerun)."""


class ShardRunError(TbsimError, RuntimeError):
    """A sharded job could not finish: failed shards, or a work folder of another job."""


@dataclass(frozen=True)
class ShardItem:
    """Scenarios of one file: records ``[start, stop)`` of a raw Scenario TFRecord, or the
    whole file when ``start`` is None."""

    path: str
    start: int | None = None
    stop: int | None = None


@dataclass(frozen=True)
class Shard:
    """One task: the scenarios of ``items``, written to the work folder as ``name``."""

    index: int
    name: str
    items: tuple[ShardItem, ...]


@dataclass(frozen=True)
class ShardOutput:
    """What a task returns: the shard file's bytes and counts for the report.

    Attributes:
        payload: the file content.
        num_scenarios: scenarios in the shard.
        seconds: wall time of the task, s.
    """

    payload: bytes
    num_scenarios: int
    seconds: float


ShardTask = Callable[[Shard], ShardOutput]
"""A picklable callable computing one shard (frozen dataclasses below)."""


# ----------------------------------------------------------------------------- planning
def _files(sources: Sequence[str]) -> list[Path]:
    """Absolute paths of the files named by paths, globs and folders, in the loader's order
    (absolute: a worker may start elsewhere)."""
    from tbsim_env.data.loader import _plan

    return [p.resolve() for p in _plan(list(sources)) if isinstance(p, Path)]


def _items(path: Path, shard_size: int | None) -> list[tuple[ShardItem, bool]]:
    """Pieces of one file, at most ``shard_size`` records each (TFRecords), each with whether
    it is a single-scenario file (JSON, pickle) that may share a shard with others."""
    from tbsim_env.data.compressed import is_gzip
    from tbsim_env.data.loader import ScenarioFileFormat, detect_format
    from tbsim_env.data.womd import ScenarioFile

    fmt = detect_format(path)
    if fmt in (ScenarioFileFormat.SCENARIONET_PICKLE, ScenarioFileFormat.GPUDRIVE_JSON):
        return [(ShardItem(str(path)), True)]
    if shard_size is None or fmt is not ScenarioFileFormat.TFRECORD or is_gzip(path):
        return [(ShardItem(str(path)), False)]
    n = len(ScenarioFile(path, verify=False))
    return [
        (ShardItem(str(path), a, min(a + shard_size, n)), False) for a in range(0, n, shard_size)
    ]


def plan_shards(sources: Sequence[str], name: str, shard_size: int | None = None) -> list[Shard]:
    """Cut the input files into shards.

    Args:
        sources: scenario files, globs or folders.
        name: output file name pattern with ``{k}`` and ``{n}`` (shard index and count), e.g.
            ``"submission.binproto-{k:05d}-of-{n:05d}"``.
        shard_size: scenarios per shard; None = one shard per input file. Raw Scenario
            TFRecords are cut into record ranges, single-scenario files (JSON, pickles) are
            grouped; tf.Example files and gzip-compressed TFRecords stay whole.

    Raises:
        FileNotFoundError: a missing path, or a glob / folder without scenario files.
        ValueError: ``shard_size`` < 1.
    """
    if shard_size is not None and shard_size < 1:
        raise ValueError(f"shard_size must be >= 1, got {shard_size}")
    groups: list[list[ShardItem]] = []
    pending: list[ShardItem] = []
    for path in _files(sources):
        for item, single in _items(path, shard_size):
            if single and shard_size:
                pending.append(item)
                if len(pending) == shard_size:
                    groups.append(pending)
                    pending = []
                continue
            if pending:
                groups.append(pending)
                pending = []
            groups.append([item])
    if pending:
        groups.append(pending)
    n = len(groups)
    return [Shard(k, name.format(k=k, n=n), tuple(g)) for k, g in enumerate(groups)]


def load_shard(shard: Shard, skip_bad: bool = False) -> list[Scenario]:
    """The scenarios of a shard, in item and record order."""
    from tbsim_env.data import load_scenarios
    from tbsim_env.data.womd import ScenarioFile

    out: list[Scenario] = []
    for item in shard.items:
        if item.start is None:
            out += load_scenarios(item.path, skip_bad=skip_bad)
        else:
            f = ScenarioFile(item.path)
            out += [f.record(i) for i in range(item.start, item.stop)]
    return out


def load_by_id(sources: Sequence[str], wanted: set[str], skip_bad: bool = False) -> list[Scenario]:
    """The scenarios of ``sources`` whose ids are in ``wanted``, in file order.

    Uncompressed raw Scenario TFRecords are looked up by their id index (only the id field of
    the other records is decoded); other files (and every file with ``skip_bad``) are read whole.
    """
    from tbsim_env.data import load_scenarios
    from tbsim_env.data.compressed import is_gzip
    from tbsim_env.data.loader import ScenarioFileFormat, detect_format
    from tbsim_env.data.womd import ScenarioFile

    out: list[Scenario] = []
    for path in _files(sources):
        indexed = detect_format(path) is ScenarioFileFormat.TFRECORD and not is_gzip(path)
        if not skip_bad and indexed:
            f = ScenarioFile(path)
            out += [f[sid] for sid in f.ids() if sid in wanted]
        else:
            out += [s for s in load_scenarios(path, skip_bad=skip_bad) if s.scenario_id in wanted]
    return out


# ----------------------------------------------------------------------------- tasks
def _rollouts(scenarios: Sequence[Scenario], settings: RolloutSettings):
    """(scenario, Rollouts) pairs, no progress bar (the driver shows one over shards)."""
    from tbsim_env.evaluation import iter_rollouts

    return iter_rollouts(scenarios, settings, progress=False)


@dataclass(frozen=True)
class ExportTask:
    """Rollouts of a shard's scenarios -> one ``SimAgentsChallengeSubmission`` file."""

    settings: RolloutSettings
    skip_bad: bool = False

    def __call__(self, shard: Shard) -> ShardOutput:
        from tbsim_env.evaluation import check_logged_future, submission_metadata
        from tbsim_env.metrics.wosac import (
            build_submission,
            rollouts_to_proto,
            validate_scenario_rollouts,
        )

        t0 = time.perf_counter()
        scenarios = load_shard(shard, self.skip_bad)
        if self.settings.policy == "log_replay":
            check_logged_future(scenarios, "log replay")
        protos = []
        for sc, r in _rollouts(scenarios, self.settings):
            protos.append(rollouts_to_proto(r))
            validate_scenario_rollouts(protos[-1], sc, num_rollouts=self.settings.num_rollouts)
        sub = build_submission(protos, submission_metadata(self.settings.policy))
        payload = sub.SerializeToString(deterministic=True)
        return ShardOutput(payload, len(protos), time.perf_counter() - t0)


def _scores_payload(scores: Sequence) -> bytes:
    return json.dumps([dataclasses.asdict(s) for s in scores], indent=0).encode()


@dataclass(frozen=True)
class EvaluateTask:
    """Rollouts of a shard's scenarios, scored -> a JSON list of per-scenario scores."""

    settings: RolloutSettings
    version: str = "wosac2025"
    skip_bad: bool = False

    def __call__(self, shard: Shard) -> ShardOutput:
        from tbsim_env.evaluation import check_logged_future
        from tbsim_env.metrics.wosac import score_scenario

        t0 = time.perf_counter()
        scenarios = load_shard(shard, self.skip_bad)
        check_logged_future(scenarios, "WOSAC scoring")
        scores = [
            score_scenario(sc, r, self.version) for sc, r in _rollouts(scenarios, self.settings)
        ]
        return ShardOutput(_scores_payload(scores), len(scores), time.perf_counter() - t0)


@dataclass(frozen=True)
class ScoreTask:
    """Score one submission file (the shard's single item) against the logged scenarios.

    Every task reads from the data only the scenarios its file holds (``load_by_id``).
    """

    data: tuple[str, ...]
    version: str = "wosac2025"
    skip_bad: bool = False

    def __call__(self, shard: Shard) -> ShardOutput:
        from tbsim_env.metrics.wosac import read_submission, score_submission_file

        t0 = time.perf_counter()
        path = shard.items[0].path
        wanted = {r.scenario_id for r in read_submission(path).scenario_rollouts}
        scenarios = load_by_id(self.data, wanted, self.skip_bad)
        scores = score_submission_file(scenarios, path, self.version)
        return ShardOutput(_scores_payload(scores), len(scores), time.perf_counter() - t0)


@dataclass(frozen=True)
class BenchmarkTask:
    """The planner benchmark on a shard's scenarios -> a JSON list of per-episode results
    (``tbsim_env.benchmark``)."""

    settings: BenchmarkSettings
    skip_bad: bool = False

    def __call__(self, shard: Shard) -> ShardOutput:
        from tbsim_env.benchmark.runner import run_benchmark

        t0 = time.perf_counter()
        scenarios = load_shard(shard, self.skip_bad)
        results = run_benchmark(scenarios, self.settings, progress=False)
        payload = json.dumps([r.to_json() for r in results], indent=0).encode()
        return ShardOutput(payload, len(scenarios), time.perf_counter() - t0)


def merge_benchmark(work_dir: str | Path, shards: Sequence[Shard]) -> list:
    """The per-episode ``ScenarioResult`` of every benchmark shard, in shard order."""
    from tbsim_env.benchmark.score import ScenarioResult

    out = []
    for shard in shards:
        rows = json.loads((Path(work_dir) / shard.name).read_text())
        out += [ScenarioResult.from_json(r) for r in rows]
    return out


def run_task(task: ShardTask, shard: Shard) -> ShardOutput:
    """Run one task with one torch thread (what a worker process runs)."""
    import torch

    torch.set_num_threads(1)
    return task(shard)


# ----------------------------------------------------------------------------- executors
Outcome = tuple[Shard, ShardOutput | BaseException]


@dataclass(frozen=True)
class LocalExecutor:
    """Runs the shards one after the other in this process."""

    def run(self, task: ShardTask, shards: Sequence[Shard]) -> Iterator[Outcome]:
        for shard in shards:
            try:
                yield shard, run_task(task, shard)
            except Exception as err:  # reported per shard; the others go on
                yield shard, err


@dataclass(frozen=True)
class RayExecutor:
    """Runs the shards as Ray tasks, yielding each as it finishes.

    Attributes:
        address: a Ray cluster's address ("auto", "ray://host:10001", ...); None starts (or
            joins the already started) local instance.
        num_workers: CPUs of a local instance (each task takes one); None = all. Ignored when
            joining a cluster.
        max_retries: how often Ray reruns a task whose worker died.
    """

    address: str | None = None
    num_workers: int | None = None
    max_retries: int = 3

    def _init(self):
        import ray

        if not ray.is_initialized():
            local = self.address in (None, "", "local")
            ray.init(
                address=None if local else self.address,
                num_cpus=self.num_workers if local else None,
                include_dashboard=False,
                log_to_driver=False,
            )
        return ray

    def run(self, task: ShardTask, shards: Sequence[Shard]) -> Iterator[Outcome]:
        ray = self._init()
        remote = ray.remote(num_cpus=1, max_retries=self.max_retries)(run_task)
        pending = {remote.remote(task, shard): shard for shard in shards}
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                shard = pending.pop(ref)
                try:
                    yield shard, ray.get(ref)
                except Exception as err:  # a task error or a worker that died too often
                    yield shard, err


Executor = LocalExecutor | RayExecutor


# ----------------------------------------------------------------------------- runner
@dataclass(frozen=True)
class RunReport:
    """What one run of a sharded job did.

    Attributes:
        total: shards in the job.
        written: names of the shards computed and written by this run.
        skipped: names of the shards already in the work folder (not recomputed).
        failed: {shard name: one-line error} of the shards that failed in this run.
        scenarios: scenarios of the shards written by this run.
        seconds: wall time of this run, s.
        task_seconds: summed wall time of the tasks written by this run, s (over ``seconds``:
            how many ran at once).
    """

    total: int
    written: tuple[str, ...]
    skipped: tuple[str, ...]
    failed: dict[str, str]
    scenarios: int
    seconds: float
    task_seconds: float = 0.0

    @property
    def complete(self) -> bool:
        return not self.failed and len(self.written) + len(self.skipped) == self.total


def atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that ``path`` is either absent or complete: a temporary
    file in the same folder, flushed to disk, then renamed over ``path`` (``os.replace``)."""
    tmp = path.with_name(f"{path.name}{TMP_MARK}{os.getpid()}")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def describe(task: ShardTask) -> dict:
    """JSON-ready description of a task (its type and settings) for the run manifest."""
    fields = dataclasses.asdict(task) if dataclasses.is_dataclass(task) else {"repr": repr(task)}
    return {"task": type(task).__name__, **fields}


def _flat(tree: dict, prefix: str = "") -> dict:
    """{"a.b": leaf} of a nested dict."""
    out = {}
    for k, v in tree.items():
        key = f"{prefix}{k}"
        out.update(_flat(v, key + ".") if isinstance(v, dict) else {key: v})
    return out


def _claim(work_dir: Path, job: dict, shards: Sequence[Shard]) -> None:
    """Write the manifest, or check that the folder's one describes the same job."""
    manifest = json.loads(
        json.dumps({"job": job, "shards": [dataclasses.asdict(s) for s in shards]})
    )
    path = work_dir / MANIFEST
    if path.exists():
        held = json.loads(path.read_text())
        if held != manifest:
            old, new = _flat(held.get("job", {})), _flat(manifest["job"])
            diff = sorted(k for k in old.keys() | new.keys() if old.get(k) != new.get(k))
            what = ", ".join(f"{k} {old.get(k)!r} -> {new.get(k)!r}" for k in diff)
            raise ShardRunError(
                f"{work_dir} holds shards of another job ({what or 'another shard plan'}); "
                "use another work folder or empty this one"
            )
        return
    atomic_write(path, json.dumps(manifest, indent=1).encode())


def _one_line(err: BaseException) -> str:
    return f"{type(err).__name__}: " + " ".join(str(err).split())


def run_shards(
    task: ShardTask,
    shards: Sequence[Shard],
    work_dir: str | Path,
    executor: Executor | None = None,
    *,
    job: dict | None = None,
    progress: bool = True,
) -> RunReport:
    """Compute the shards not yet in ``work_dir`` and write each as it finishes.

    Args:
        task: computes one shard's file content.
        shards: the whole job (those already written are skipped).
        work_dir: where shard files (and the manifest) live; created if needed.
        executor: ``LocalExecutor()`` (default) or ``RayExecutor(...)``.
        job: the job's description for the manifest (default ``describe(task)``).
        progress: a tqdm bar over all shards (the finished ones counted from the start).

    Raises:
        ShardRunError: ``work_dir`` holds shards of another job. Failed shards do not raise:
            they are in the report (see ``require_complete``).
    """
    t0 = time.perf_counter()
    work_dir = Path(work_dir)
    work_dir.mkdir(parents=True, exist_ok=True)
    _claim(work_dir, describe(task) if job is None else job, shards)
    for stale in work_dir.glob(f"*{TMP_MARK}*"):  # writes a killed driver left unfinished
        stale.unlink()
    done = [s.name for s in shards if (work_dir / s.name).is_file()]
    todo = [s for s in shards if s.name not in set(done)]
    written, failed, count, busy = [], {}, 0, 0.0
    bar = tqdm(total=len(shards), initial=len(done), unit="shard", disable=not progress)
    for shard, out in (executor or LocalExecutor()).run(task, todo):
        if isinstance(out, BaseException):
            failed[shard.name] = _one_line(out)
        else:
            atomic_write(work_dir / shard.name, out.payload)
            written.append(shard.name)
            count += out.num_scenarios
            busy += out.seconds
            bar.set_postfix(scenarios_per_s=f"{count / (time.perf_counter() - t0):.2f}")
        bar.update(1)
    bar.close()
    wall = time.perf_counter() - t0
    return RunReport(len(shards), tuple(written), tuple(done), failed, count, wall, busy)


def require_complete(report: RunReport, work_dir: str | Path) -> None:
    """Raise ``ShardRunError`` naming the failed shards (a rerun computes only those)."""
    if report.complete:
        return
    first = next(iter(report.failed.items()), ("?", "missing"))
    raise ShardRunError(
        f"{len(report.failed)} of {report.total} shards failed (first: {first[0]}: {first[1]}); "
        f"the {len(report.written) + len(report.skipped)} finished ones are kept in "
        f"{work_dir}: rerun the same command to compute only the missing ones"
    )


# ----------------------------------------------------------------------------- merging
def merge_submissions(work_dir: str | Path, shards: Sequence[Shard], out: str | Path) -> int:
    """Concatenate the shards' submissions into one file (metadata of the first shard),
    written atomically; returns the scenario count.

    Raises:
        SubmissionError: a scenario in two shards, or an unreadable shard file.
    """
    from tbsim_env.metrics.protos import sim_agents_submission_pb2 as pb

    merged = pb.SimAgentsChallengeSubmission()
    for k, sub in enumerate(_read_shards(work_dir, shards)):
        if k == 0:
            merged.CopyFrom(sub)
        else:
            merged.scenario_rollouts.extend(sub.scenario_rollouts)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(out, merged.SerializeToString(deterministic=True))
    return len(merged.scenario_rollouts)


def _read_shards(work_dir: str | Path, shards: Sequence[Shard]):
    """Yield each shard's submission, refusing a scenario id seen in an earlier shard."""
    from tbsim_env.metrics.wosac import SubmissionError, read_submission

    seen: dict[str, str] = {}
    for shard in shards:
        sub = read_submission(Path(work_dir) / shard.name)
        for r in sub.scenario_rollouts:
            if r.scenario_id in seen:
                raise SubmissionError(
                    f"scenario {r.scenario_id} is in shards {seen[r.scenario_id]} and "
                    f"{shard.name}; each scenario may be submitted once"
                )
            seen[r.scenario_id] = shard.name
        yield sub


def check_submission_shards(work_dir: str | Path, shards: Sequence[Shard]) -> int:
    """Check that the shard files form one submission (each readable, every scenario once);
    returns the scenario count."""
    return sum(len(sub.scenario_rollouts) for sub in _read_shards(work_dir, shards))


def merge_scores(work_dir: str | Path, shards: Sequence[Shard]) -> list:
    """The per-scenario ``ScenarioScores`` of every shard, in shard order."""
    from tbsim_env.metrics.wosac import ScenarioScores

    out = []
    for shard in shards:
        rows = json.loads((Path(work_dir) / shard.name).read_text())
        out += [ScenarioScores(**row) for row in rows]
    return out


def dataset_table(scores: Sequence) -> str:
    """The dataset-level scores (means over scenarios, buckets recomputed), one per line."""
    from tbsim_env.metrics.wosac.scoring import aggregate

    mean = aggregate(scores)
    lines = [f"WOSAC {mean.version}: {mean.num_scenarios} scenarios"]
    for field in dataclasses.fields(mean):
        value = getattr(mean, field.name)
        if isinstance(value, float):
            lines.append(f"  {field.name:<40} {value:10.4f}")
    return "\n".join(lines)
