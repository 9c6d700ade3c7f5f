"""Sharded, resumable WOSAC jobs (tbsim_env.distributed): planning, resume, merging, CLI, Ray.

The resume logic runs on the in-process executor; the Ray tests (a local instance of 2 CPUs,
a worker killed mid-run, a rerun) skip without ray.
"""

from __future__ import annotations

import dataclasses
import os
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest

from tbsim_env import distributed as D
from tbsim_env.cli import main
from tbsim_env.data import load_scenarios
from tbsim_env.evaluation import evaluate_policy, export_submission

SETTINGS = D.RolloutSettings("constant_velocity", num_rollouts=2, seed=5)
NAME = "submission.binproto-{k:05d}-of-{n:05d}"


@pytest.fixture(scope="module")
def data(womd_dir: Path, tmp_path_factory, torch_one_thread) -> list[str]:
    """Four real scenes in four files: three GPUDrive JSONs and a 2-record TFRecord."""
    folder = tmp_path_factory.mktemp("data")
    for p in sorted((womd_dir / "gpudrive").glob("*.json")):
        shutil.copy(p, folder / p.name)
    wod = womd_dir / "waymo-open-dataset"
    two = folder / "two.tfrecord"  # TFRecord framing concatenates: two records
    two.write_bytes(
        (wod / "motion_data_one_scenario.tfrecord").read_bytes()
        + (wod / "womd_scenario_input.tfrecord").read_bytes()
    )
    return [str(folder)]


@dataclass(frozen=True)
class Flaky:
    """Wraps a task: logs every call; on shard ``fail`` it fails once (marker file), by
    raising or, with ``kill``, by ending its worker process at once (``os._exit``)."""

    inner: D.ShardTask
    log_dir: str
    fail: str = ""
    kill: bool = False

    def __call__(self, shard: D.Shard) -> D.ShardOutput:
        with open(Path(self.log_dir) / "calls.txt", "a") as fh:
            fh.write(shard.name + "\n")
        marker = Path(self.log_dir) / f"failed-{shard.name}"
        if shard.name == self.fail and not marker.exists():
            marker.touch()
            if self.kill:
                os._exit(3)
            raise RuntimeError(f"injected failure in {shard.name}")
        return self.inner(shard)


def _calls(log_dir: Path) -> list[str]:
    path = log_dir / "calls.txt"
    return path.read_text().split() if path.exists() else []


def _stamps(folder: Path) -> dict[str, tuple[int, int]]:
    """(inode, mtime ns) of every shard file: a rewrite changes the inode (os.replace)."""
    return {p.name: (p.stat().st_ino, p.stat().st_mtime_ns) for p in folder.glob("sub*")}


def test_plan_shards(data: list[str]) -> None:
    whole = D.plan_shards(data, NAME)
    assert [s.name for s in whole] == [NAME.format(k=k, n=4) for k in range(4)]
    assert [len(s.items) for s in whole] == [1, 1, 1, 1]
    assert [sc.scenario_id for s in whole for sc in D.load_shard(s)] == [
        sc.scenario_id for sc in load_scenarios(data)
    ]
    # shard_size 2: the three JSONs in groups of 2, the TFRecord in record ranges of 2 / 1.
    two = D.plan_shards(data, NAME, shard_size=2)
    assert [len(s.items) for s in two] == [2, 1, 1]
    one = D.plan_shards(data, NAME, shard_size=1)
    ranges = [(i.start, i.stop) for s in one for i in s.items if i.start is not None]
    assert ranges == [(0, 1), (1, 2)]
    assert [sc.scenario_id for s in one for sc in D.load_shard(s)] == [
        sc.scenario_id for sc in load_scenarios(data)
    ]
    with pytest.raises(ValueError, match="shard_size"):
        D.plan_shards(data, NAME, shard_size=0)


def test_load_by_id(data: list[str]) -> None:
    every = load_scenarios(data)
    wanted = {every[0].scenario_id, every[-1].scenario_id}  # a JSON, the TFRecord's 2nd record
    got = D.load_by_id(data, wanted)
    assert [s.scenario_id for s in got] == [every[0].scenario_id, every[-1].scenario_id]
    assert got[1].tracks.num_tracks == every[-1].tracks.num_tracks
    assert D.load_by_id(data, wanted, skip_bad=True)[1].scenario_id == every[-1].scenario_id


def test_local_run_merges_to_the_plain_export(data: list[str], tmp_path: Path) -> None:
    shards = D.plan_shards(data, NAME)
    task = D.ExportTask(SETTINGS)
    report = D.run_shards(task, shards, tmp_path / "w", progress=False)
    assert report.complete and len(report.written) == 4 and report.scenarios == 5
    D.merge_submissions(tmp_path / "w", shards, tmp_path / "merged.binproto")
    export_submission(
        load_scenarios(data), "constant_velocity", tmp_path / "plain.binproto",
        num_rollouts=2, seed=5,
    )  # fmt: skip
    assert (tmp_path / "merged.binproto").read_bytes() == (tmp_path / "plain.binproto").read_bytes()
    assert D.check_submission_shards(tmp_path / "w", shards) == 5
    before = _stamps(tmp_path / "w")
    again = D.run_shards(task, shards, tmp_path / "w", progress=False)
    assert again.written == () and len(again.skipped) == 4 and again.complete
    assert _stamps(tmp_path / "w") == before


def test_failed_shard_is_the_only_one_recomputed(data: list[str], tmp_path: Path) -> None:
    shards = D.plan_shards(data, NAME)
    work, logs = tmp_path / "w", tmp_path / "logs"
    logs.mkdir()
    task = Flaky(D.ExportTask(SETTINGS), str(logs), fail=shards[1].name)
    job = D.describe(task.inner)
    first = D.run_shards(task, shards, work, job=job, progress=False)
    assert (
        list(first.failed) == [shards[1].name]
        and "injected failure" in first.failed[shards[1].name]
    )
    assert sorted(first.written) == sorted(s.name for s in shards if s is not shards[1])
    assert not (work / shards[1].name).exists()
    with pytest.raises(D.ShardRunError, match="1 of 4 shards failed.*rerun"):
        D.require_complete(first, work)
    before = _stamps(work)
    second = D.run_shards(task, shards, work, job=job, progress=False)
    assert second.written == (shards[1].name,) and second.complete
    assert _calls(logs) == [s.name for s in shards] + [shards[1].name]
    after = _stamps(work)
    assert {k: v for k, v in after.items() if k in before} == before
    D.merge_submissions(work, shards, tmp_path / "merged.binproto")
    export_submission(
        load_scenarios(data), "constant_velocity", tmp_path / "plain.binproto",
        num_rollouts=2, seed=5,
    )  # fmt: skip
    assert (tmp_path / "merged.binproto").read_bytes() == (tmp_path / "plain.binproto").read_bytes()


def test_unfinished_writes_and_other_jobs(data: list[str], tmp_path: Path, monkeypatch) -> None:
    shards = D.plan_shards(data, NAME)[:1]
    work = tmp_path / "w"
    work.mkdir()
    # A write killed before its rename leaves only a temporary file: never taken as done.
    (work / f"{shards[0].name}{D.TMP_MARK}123").write_bytes(b"partial")
    report = D.run_shards(D.ExportTask(SETTINGS), shards, work, progress=False)
    assert report.written == (shards[0].name,)
    assert not list(work.glob(f"*{D.TMP_MARK}*"))
    other = D.ExportTask(dataclasses.replace(SETTINGS, seed=6))
    with pytest.raises(D.ShardRunError, match="settings.seed 5 -> 6"):
        D.run_shards(other, shards, work, progress=False)

    def crash(fd: int) -> None:
        raise OSError("disk gone")

    monkeypatch.setattr(os, "fsync", crash)
    with pytest.raises(OSError, match="disk gone"):
        D.atomic_write(tmp_path / "x.bin", b"data")
    assert not (tmp_path / "x.bin").exists()


def test_sharded_evaluate_equals_evaluate_policy(data: list[str], tmp_path: Path) -> None:
    shards = D.plan_shards(data, "scores-{k:05d}-of-{n:05d}.json")
    task = D.EvaluateTask(SETTINGS, "wosac2025")
    assert D.run_shards(task, shards, tmp_path, progress=False).complete
    merged = D.merge_scores(tmp_path, shards)
    plain, _ = evaluate_policy(load_scenarios(data), "constant_velocity", num_rollouts=2, seed=5)
    assert merged == plain
    table = D.dataset_table(merged)
    assert "5 scenarios" in table and "realism_meta_metric" in table


def test_cli_sharded_commands(data: list[str], tmp_path: Path, capsys) -> None:
    # 32 rollouts: wosac-score checks the challenge's joint-scene count.
    common = ["--data", *data, "--policy", "constant_velocity", "--rollouts", "32", "--seed", "5"]
    out = tmp_path / "subs"
    assert main(["export-wosac", *common, "--work-dir", str(out), "--out", f"{out}/"]) == 0
    assert "a submission of 5 scenarios in 4 shard files" in capsys.readouterr().out
    assert main(["export-wosac", *common, "--work-dir", str(out), "--out", f"{out}/"]) == 0
    assert "0 shards computed (0 scenarios" in capsys.readouterr().out
    j = tmp_path / "s.json"
    score = ["wosac-score", "--data", *data, "--submission", str(out), "--json", str(j)]
    assert main([*score, "--work-dir", str(tmp_path / "scores")]) == 0
    printed = capsys.readouterr().out
    assert "WOSAC wosac2025: 5 scenarios" in printed and j.exists()
    ev = ["evaluate", *common, "--work-dir", str(tmp_path / "ev"), "--shard-size", "2"]
    assert main(ev) == 0

    def metric_lines(text: str) -> list[str]:
        return [line for line in text.splitlines() if line.startswith("  ")]

    # Scoring the exported submission = evaluating in one go (same seeds, same rollouts).
    assert metric_lines(capsys.readouterr().out) == metric_lines(printed)
    assert len(metric_lines(printed)) == 19
    assert main([*ev, "--plot", str(tmp_path / "p.png")]) == 2
    assert "--plot" in capsys.readouterr().err


def test_cli_ray_missing(data: list[str], tmp_path: Path, monkeypatch, capsys) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    args = ["--data", *data, "--policy", "constant_velocity", "--ray", "--out", f"{tmp_path}/"]
    assert main(["export-wosac", *args]) == 2
    assert "--ray needs the ray package" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


# ----------------------------------------------------------------------------- Ray
@pytest.fixture(scope="module")
def ray_local():
    ray = pytest.importorskip("ray", reason="ray is not installed (pip install ray)")
    # Tasks defined in this test module travel by value: workers need not import tests/.
    ray.cloudpickle.register_pickle_by_value(sys.modules[__name__])
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


def test_ray_worker_killed_then_retried(ray_local, data: list[str], tmp_path: Path) -> None:
    shards = D.plan_shards(data, NAME)
    logs = tmp_path / "logs"
    logs.mkdir()
    task = Flaky(D.ExportTask(SETTINGS), str(logs), fail=shards[2].name, kill=True)
    report = D.run_shards(
        task, shards, tmp_path / "w", D.RayExecutor(max_retries=1), job={"t": 1}, progress=False
    )
    assert report.complete and sorted(report.written) == [s.name for s in shards]
    assert sorted(_calls(logs)) == sorted([s.name for s in shards] + [shards[2].name])
    D.merge_submissions(tmp_path / "w", shards, tmp_path / "merged.binproto")
    export_submission(
        load_scenarios(data), "constant_velocity", tmp_path / "plain.binproto",
        num_rollouts=2, seed=5,
    )  # fmt: skip
    assert (tmp_path / "merged.binproto").read_bytes() == (tmp_path / "plain.binproto").read_bytes()


def test_ray_killed_worker_then_rerun_completes_the_rest(
    ray_local, data: list[str], tmp_path: Path
) -> None:
    shards = D.plan_shards(data, NAME)
    work, logs = tmp_path / "w", tmp_path / "logs"
    logs.mkdir()
    task = Flaky(D.ExportTask(SETTINGS), str(logs), fail=shards[0].name, kill=True)
    ray_exec = D.RayExecutor(max_retries=0)
    first = D.run_shards(task, shards, work, ray_exec, job={"t": 1}, progress=False)
    assert list(first.failed) == [shards[0].name] and len(first.written) == 3
    assert "WorkerCrashedError" in first.failed[shards[0].name]  # the process died
    assert not (work / shards[0].name).exists()
    before = _stamps(work)
    second = D.run_shards(task, shards, work, ray_exec, job={"t": 1}, progress=False)
    assert second.written == (shards[0].name,) and second.complete
    assert sorted(_calls(logs)) == sorted([s.name for s in shards] + [shards[0].name])
    assert {k: v for k, v in _stamps(work).items() if k in before} == before
    assert D.check_submission_shards(work, shards) == 5


def test_cli_ray(ray_local, data: list[str], tmp_path: Path, capsys) -> None:
    common = ["--data", *data, "--policy", "constant_velocity", "--rollouts", "2", "--seed", "5"]
    out = tmp_path / "sub.binproto"
    assert main(["export-wosac", *common, "--ray", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "4 shards computed (5 scenarios" in printed and f"wrote {out}: 5 scenarios" in printed
    assert len(list(Path(f"{out}.shards").glob("submission.binproto-*"))) == 4
    export_submission(
        load_scenarios(data), "constant_velocity", tmp_path / "plain.binproto",
        num_rollouts=2, seed=5,
    )  # fmt: skip
    assert out.read_bytes() == (tmp_path / "plain.binproto").read_bytes()
