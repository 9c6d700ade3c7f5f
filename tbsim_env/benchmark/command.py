"""``tbsim benchmark``: run, print the tables, write the JSON, the plot and the viewer pages."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from tbsim_env.benchmark.episode import EpisodeSpec, run_episode
from tbsim_env.benchmark.planner import load_planner
from tbsim_env.benchmark.report import (
    episode_rollout,
    plot_scores,
    scenario_table,
    summary_table,
    worst,
    write_json,
    write_pages,
)
from tbsim_env.benchmark.runner import BenchmarkSettings, run_benchmark
from tbsim_env.benchmark.score import ScenarioResult
from tbsim_env.data import load_scenarios
from tbsim_env.data.scenario import Scenario
from tbsim_env.evaluation import scenario_seed


def parse_traffic(text: str) -> tuple[str, ...]:
    """Comma-separated NPC policy names, each one the registry can drive agents with.

    Raises:
        ValueError: an empty list or an unknown name.
    """
    from policies import policy_names

    names = tuple(x.strip() for x in text.split(",") if x.strip())
    known = policy_names(agents=True)
    unknown = [n for n in names if n not in known]
    if not names or unknown:
        raise ValueError(f"--traffic {text!r}: unknown {unknown or 'none given'}; use {known}")
    return names


def settings_of(args: Any) -> BenchmarkSettings:
    """The run's settings from the command's config (``tbsim_env.cli.commands.Benchmark``)."""
    return BenchmarkSettings(
        planner=args.planner,
        traffic=parse_traffic(args.traffic),
        controlled=args.controlled,
        seed=args.seed,
        npc_checkpoint=args.npc_checkpoint,
        batch_size=args.batch_size,
    )


def _results(args: Any, settings: BenchmarkSettings, sharded: bool, executor) -> list:
    """Run (sharded and resumable when asked) and return every episode's result."""
    if not sharded:
        return run_benchmark(load_scenarios(list(args.data), skip_bad=args.skip_bad), settings)
    from tbsim_env import distributed as D

    work = Path(args.work_dir or f"tbsim-benchmark-{Path(settings.planner).name}.shards")
    shards = D.plan_shards(args.data, "benchmark-{k:05d}-of-{n:05d}.json", args.shard_size)
    report = D.run_shards(D.BenchmarkTask(settings, args.skip_bad), shards, work, executor)
    D.require_complete(report, work)
    print(f"{len(report.written)} shards computed, {len(report.skipped)} already in {work}")
    return D.merge_benchmark(work, shards)


def pages(
    out_dir: str, picks: Sequence[ScenarioResult], data: Sequence[str], settings: BenchmarkSettings
) -> list[Path]:
    """Viewer pages of ``picks``: each episode is run again (same seed, same planner)."""
    wanted = {r.scenario_id for r in picks}
    scenarios: dict[str, Scenario] = {
        s.scenario_id: s for s in load_scenarios(list(data)) if s.scenario_id in wanted
    }

    def render(sc: Scenario, r: ScenarioResult):
        seed = scenario_seed(settings.seed, sc.scenario_id)
        spec = EpisodeSpec(sc, r.traffic, settings.controlled, seed, settings.npc_checkpoint)
        records = run_episode(spec, lambda: load_planner(settings.planner))
        (record,) = [x for x in records if x.agent == r.agent]
        return episode_rollout(sc, record, r, settings.config.drivable_violation)

    return write_pages(out_dir, picks, scenarios, render)


def run_command(args: Any, sharded: bool = False, executor=None) -> int:
    """Run ``tbsim benchmark`` with ``args`` (``tbsim_env.cli.commands.Benchmark``)."""
    load_planner(args.planner)  # a bad spec fails before any scene runs
    settings = settings_of(args)
    results = _results(args, settings, sharded, executor)
    title = f"planner {settings.planner}, controlled {settings.controlled}, seed {settings.seed}"
    print(summary_table(results, title))
    print(scenario_table(worst(results, args.worst)))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        meta = {"planner": settings.planner, "traffic": list(settings.traffic),
                "controlled": settings.controlled, "seed": settings.seed,
                "data": list(args.data)}  # fmt: skip
        write_json(args.json, results, meta)
        print(f"wrote {args.json}")
    if args.plot:
        plot_scores(args.plot, results, title)
        print(f"wrote {args.plot}")
    if args.html:
        written = pages(args.html, worst(results, args.worst), args.data, settings)
        print(f"wrote {len(written)} viewer pages to {args.html}")
    return 0
