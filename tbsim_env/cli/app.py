"""``tbsim`` command line: demo, info, render, WOSAC export and scoring, viewer, training.

Examples::

    tbsim demo --out demo.mp4                 # embedded generated scenes, no data needed
    tbsim info path/to/shard.tfrecord         # one line per scenario
    tbsim render shard.tfrecord --scenario 637f20cafde22ff8 --out x.mp4
    tbsim view shard.tfrecord --policy constant_velocity --out view.html   # open in a browser
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from tbsim_env.cli import commands as cfg
from tbsim_env.cli.commands import COMMANDS
from tbsim_env.core import constants as C
from tbsim_env.core.config_cli import add_config_arguments, parse_config, summary
from tbsim_env.core.errors import TbsimError


def _cmd_info(args: cfg.Info) -> int:
    from tbsim_env.data import iter_scenarios

    head = ("scenario_id", "tracks", "veh/ped/cyc", "map", "signals", "sdc_id", "steps", "future")
    print(
        f"{head[0]:<20} {head[1]:>6} {head[2]:>12} {head[3]:>5} {head[4]:>7} {head[5]:>7} "
        f"{head[6]:>5} {head[7]:>6}"
    )
    for sc in iter_scenarios(args.files, skip_bad=args.skip_bad):
        # Logged steps, and logged steps after the current one ("none": history only).
        future = str(sc.num_future_steps) if sc.has_future else "none"
        t = sc.tracks.object_type
        kinds = "/".join(
            str(int((t == k).sum()))
            for k in (C.ObjectType.VEHICLE, C.ObjectType.PEDESTRIAN, C.ObjectType.CYCLIST)
        )
        print(
            f"{sc.scenario_id:<20} {sc.tracks.num_tracks:>6} {kinds:>12} "
            f"{sc.road_map.num_features:>5} {sc.signals.num_signals:>7} {sc.sdc_id:>7} "
            f"{sc.num_logged_steps:>5} {future:>6}"
        )
    return 0


def _video_config():
    """The env config of ``render`` and ``demo``: a video shows the whole scenario, so the
    SDC's collisions, off-road moments and goal do not end it (the frames mark them)."""
    from tbsim_env.core.config import EnvConfig, TerminationConfig

    return EnvConfig(termination=TerminationConfig(collision=False, offroad=False, goal=False))


def _episode_video(
    env, out: Path, fps: int, steps: int | None, desc: str, scenario_index: int = 0
) -> int:
    from tbsim_env.env.parallel_env import episode_length
    from tbsim_env.rendering import write_video

    env.reset(options={"scenario_index": scenario_index})
    frames = [env.render()]
    n = steps or episode_length(env)
    for _ in tqdm(range(n), desc=desc, unit="step"):
        if not env.agents:
            break
        env.step(env.expert_actions())
        frames.append(env.render())
    return write_video(frames, out, fps=fps)


def _cmd_demo(args: cfg.Demo) -> int:
    from tbsim_env.env import TrafficEnv

    env = TrafficEnv(
        None,
        controlled="sdc",
        npc_policy=args.npc_policy,
        config=_video_config(),
        render_mode="rgb_array",
        scenario_order="cycle",
    )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    stem, suffix = out.with_suffix(""), out.suffix or ".mp4"
    for k in range(min(args.scenarios, len(env.scenarios))):
        path = out if args.scenarios == 1 else Path(f"{stem}_{k}{suffix}")
        desc = f"demo {env.scenarios[k].scenario_id}"
        n = _episode_video(env, path, args.fps, args.steps, desc, scenario_index=k)
        print(
            f"wrote {path} ({n} frames): SDC follows its log via expert actions, "
            f"NPCs: {args.npc_policy}"
        )
    return 0


def _cmd_render(args: cfg.Render) -> int:
    from tbsim_env.data import load_scenarios
    from tbsim_env.env import TrafficEnv

    scenarios = load_scenarios(args.file)
    if args.scenario is not None:
        scenarios = [s for s in scenarios if s.scenario_id == args.scenario]
        if not scenarios:
            print(f"error: no scenario {args.scenario!r} in {args.file}", file=sys.stderr)
            return 2
    env = TrafficEnv(
        scenarios[:1],
        controlled="sdc",
        npc_policy=args.npc_policy,
        config=_video_config(),
        render_mode="rgb_array",
    )
    n = _episode_video(env, Path(args.out), args.fps, None, f"render {scenarios[0].scenario_id}")
    print(f"wrote {args.out} ({n} frames)")
    return 0


def _load(files: Sequence[str], skip_bad: bool = False):
    from tbsim_env.data import load_scenarios

    return load_scenarios(list(files), skip_bad=skip_bad)


def _sharded(args: cfg.ShardOptions) -> bool:
    """Whether to run as resumable shards (``--ray`` or ``--work-dir``)."""
    return args.ray is not None or args.work_dir is not None


def _executor(args: cfg.ShardOptions):
    from tbsim_env.distributed import LocalExecutor, RayExecutor

    if args.ray is None:
        return LocalExecutor()
    try:
        import ray  # noqa: F401
    except ImportError:
        raise ValueError("--ray needs the ray package: pip install ray (or the rl extra)") from None
    return RayExecutor(address=args.ray, num_workers=args.ray_workers)


def _settings(args: cfg.RolloutOptions):
    from tbsim_env.evaluation import RolloutSettings

    return RolloutSettings(
        policy=args.policy,
        num_rollouts=args.rollouts,
        seed=args.seed,
        checkpoint=args.checkpoint,
        road_edge_weight=args.road_edge_weight,
    )


def _print_run(report, work: Path) -> None:
    wall = max(report.seconds, 1e-9)
    print(
        f"{len(report.written)} shards computed ({report.scenarios} scenarios, "
        f"{report.scenarios / wall:.2f} scenarios/s, {report.task_seconds / wall:.1f} tasks "
        f"at once on average), {len(report.skipped)} already in {work}"
    )


def _export_sharded(args: cfg.ExportWosac) -> int:
    from tbsim_env import distributed as D

    out = Path(args.out)
    to_dir = args.out.endswith("/") or out.is_dir()
    if to_dir and args.work_dir and Path(args.work_dir).resolve() != out.resolve():
        raise ValueError("with --out DIR/ the shard files are the output: leave out --work-dir")
    work = out if to_dir else Path(args.work_dir or f"{out}.shards")
    shards = D.plan_shards(args.data, "submission.binproto-{k:05d}-of-{n:05d}", args.shard_size)
    report = D.run_shards(
        D.ExportTask(_settings(args), args.skip_bad), shards, work, _executor(args)
    )
    _print_run(report, work)
    D.require_complete(report, work)
    if to_dir:
        n = D.check_submission_shards(work, shards)
        print(f"{out}: a submission of {n} scenarios in {len(shards)} shard files")
    else:
        n = D.merge_submissions(work, shards, out)
        print(f"wrote {out}: {n} scenarios from {len(shards)} shards")
    return 0


def _cmd_export_wosac(args: cfg.ExportWosac) -> int:
    from tbsim_env.evaluation import check_logged_future, export_submission

    if _sharded(args):
        return _export_sharded(args)
    scenarios = _load(args.data, args.skip_bad)
    if args.policy == "log_replay":  # before any file is written
        check_logged_future(scenarios, "log replay")
    out = Path(args.out)
    if args.out.endswith("/") or out.is_dir():
        # One submission file per input file (WOSAC shards), named after it.
        out.mkdir(parents=True, exist_ok=True)
        by_source: dict[str, list] = {}
        for sc in scenarios:
            by_source.setdefault(sc.source.split("#")[0], []).append(sc)
        for k, (src, group) in enumerate(sorted(by_source.items())):
            name = f"submission.binproto-{k:05d}-of-{len(by_source):05d}"
            n = export_submission(group, _settings(args), out / name)
            print(f"wrote {out / name}: {n} scenarios from {src}")
        return 0
    n = export_submission(scenarios, _settings(args), out)
    print(f"wrote {out}: {n} scenarios, {args.rollouts} rollouts each, policy {args.policy}")
    return 0


def _report(scores, json_path: str | None, dataset: bool = False) -> None:
    """Print the score table (per scenario, or the dataset means of a sharded run) and write
    every per-scenario field to ``json_path`` when given."""
    import json

    from tbsim_env.metrics.wosac import scores_table, scores_to_json

    if dataset:
        from tbsim_env.distributed import dataset_table

        print(dataset_table(scores))
    else:
        print(scores_table(scores))
    if json_path:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        Path(json_path).write_text(json.dumps(scores_to_json(scores), indent=1))
        print(f"wrote {json_path}")


def _score_shards(task, shards: list, work: Path, args: cfg.WosacScore | cfg.Evaluate) -> int:
    """Run scoring shards (resumable, Ray with --ray), then print the dataset table."""
    from tbsim_env import distributed as D

    report = D.run_shards(task, shards, work, _executor(args))
    _print_run(report, work)
    D.require_complete(report, work)
    _report(D.merge_scores(work, shards), args.json, dataset=True)
    return 0


def _score_sharded(args: cfg.WosacScore, paths: list[Path]) -> int:
    from tbsim_env import distributed as D

    shards = [
        D.Shard(k, f"scores-{p.name}.json", (D.ShardItem(str(p.resolve())),))
        for k, p in enumerate(paths)
    ]
    work = Path(args.work_dir or f"{args.submission.rstrip('/')}.scores")
    data = tuple(os.path.abspath(d) for d in args.data)
    return _score_shards(D.ScoreTask(data, args.version, args.skip_bad), shards, work, args)


def _cmd_wosac_score(args: cfg.WosacScore) -> int:
    from tbsim_env.metrics.wosac import score_submission_file

    paths = (
        sorted(Path(args.submission).glob("*binproto*"))
        if Path(args.submission).is_dir()
        else [Path(args.submission)]
    )
    if _sharded(args):
        return _score_sharded(args, paths)
    scenarios = _load(args.data, args.skip_bad)
    scores = []
    for path in paths:
        scores += score_submission_file(scenarios, path, args.version)
    _report(scores, args.json)
    return 0


def _evaluate_sharded(args: cfg.Evaluate) -> int:
    from tbsim_env import distributed as D

    if args.plot:
        raise ValueError("--plot needs every rollout in one process: not with --ray / --work-dir")
    work = Path(args.work_dir or f"tbsim-evaluate-{args.policy}.shards")
    shards = D.plan_shards(args.data, "scores-{k:05d}-of-{n:05d}.json", args.shard_size)
    task = D.EvaluateTask(_settings(args), args.version, args.skip_bad)
    return _score_shards(task, shards, work, args)


def _cmd_evaluate(args: cfg.Evaluate) -> int:
    from tbsim_env.evaluation import evaluate_policy, feature_samples, plot_histograms

    if _sharded(args):
        return _evaluate_sharded(args)
    scenarios = _load(args.data, args.skip_bad)
    scores, rollouts = evaluate_policy(
        scenarios, _settings(args), version=args.version, keep_rollouts=bool(args.plot)
    )
    _report(scores, args.json)
    if args.plot:
        samples: dict[str, list] = {}
        for sc, r in zip(scenarios, rollouts):
            for name, pair in feature_samples(sc, r).items():
                samples.setdefault(name, []).append(pair)
        plot_histograms(samples, args.plot, title=f"{args.policy}: log vs simulation")
        print(f"wrote {args.plot}")
    return 0


def _pick_scenario(scenarios: list, scenario_id: str | None, where: str):
    """The scenario named ``scenario_id`` (default: the first), or a one-line error."""
    if scenario_id is None:
        return scenarios[0]
    for sc in scenarios:
        if sc.scenario_id == scenario_id:
            return sc
    raise ValueError(f"no scenario {scenario_id!r} in {where}")


def _cmd_view(args: cfg.View) -> int:
    from tbsim_env.rendering import viewer

    scenarios = _load([args.scenario])
    if args.submission and args.scenario_id is None:  # the first scenario the file holds
        from tbsim_env.metrics.wosac import read_submission

        held = {r.scenario_id for r in read_submission(args.submission).scenario_rollouts}
        scenarios = [s for s in scenarios if s.scenario_id in held] or scenarios
    sc = _pick_scenario(scenarios, args.scenario_id, args.scenario)
    if args.submission:
        shown = viewer.submission_rollouts(sc, args.submission)
        title = f"submission {args.submission}"
    elif args.policy:
        shown = viewer.policy_rollouts(
            sc, args.policy, num_rollouts=args.rollouts, seed=args.seed, checkpoint=args.checkpoint
        )
        title = f"policy {args.policy}, seed {args.seed}"
    else:
        shown, title = [], "logged scene"
    n = viewer.write_viewer(args.out, sc, [*shown, viewer.log_rollout(sc)], title)
    print(f"wrote {args.out} ({n / 1e6:.1f} MB): scenario {sc.scenario_id}, {len(shown)} rollouts")
    return 0


def _cmd_preprocess(args: cfg.Preprocess) -> int:
    from tbsim_env.core.config import TokenConfig
    from tbsim_env.data.cache import build_cache

    cfg = TokenConfig(
        max_map_pieces=args.max_map_pieces,
        max_traffic_lights=args.max_traffic_lights,
        max_agents=args.max_agents,
        training=not args.eval_split,
    )
    m = build_cache(
        args.sources,
        args.out,
        cfg=cfg,
        workers=args.workers,
        shard_size=args.shard_size,
        exclude_ids=args.exclude or (),
    )
    print(
        f"wrote {len(m['scenario_ids'])} scenarios in {len(m['shards'])} shards to {args.out}"
        + (f"; skipped {len(m['skipped'])}" if m["skipped"] else "")
    )
    return 0


def _cmd_average(args: cfg.Average) -> int:
    from policies.trafficbots.checkpoint import average_checkpoints

    w_path, _ = average_checkpoints(args.checkpoints, args.out)
    print(f"wrote the mean of {len(args.checkpoints)} checkpoints to {w_path}")
    return 0


def _cmd_benchmark(args: cfg.Benchmark) -> int:
    from tbsim_env.benchmark.command import run_command

    return run_command(args, _sharded(args), _executor(args) if _sharded(args) else None)


_HANDLERS = {
    "demo": _cmd_demo,
    "info": _cmd_info,
    "render": _cmd_render,
    "export-wosac": _cmd_export_wosac,
    "wosac-score": _cmd_wosac_score,
    "evaluate": _cmd_evaluate,
    "view": _cmd_view,
    "preprocess": _cmd_preprocess,
    "average": _cmd_average,
    "benchmark": _cmd_benchmark,
}


def build_parser() -> argparse.ArgumentParser:
    """The ``tbsim`` parser: one subcommand per config of ``cli_configs.COMMANDS`` (their
    fields are the options, their docstrings the help)."""
    p = argparse.ArgumentParser(prog="tbsim", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True)
    for name, cls in COMMANDS.items():
        sp = sub.add_parser(name, help=summary(cls), description=summary(cls))
        add_config_arguments(sp, cls)
    sub.add_parser(
        "train",
        help="train TrafficBots V1.5 on a token cache (tbsim train --help)",
        add_help=False,
    )
    return p


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv[:1] == ["train"]:  # the trainer owns its own argument parser
        from policies.trafficbots.train import main as train_main

        return train_main(argv[1:])
    ns = build_parser().parse_args(argv)
    np.set_printoptions(precision=3)
    # Small tensor work: extra intra-op threads only add wake-up latency.
    import torch

    torch.set_num_threads(1)
    try:
        config = parse_config(COMMANDS[ns.command], ns)
        return int(_HANDLERS[ns.command](config) or 0)
    except (TbsimError, FileNotFoundError, ValueError) as err:
        message = " ".join(str(err).split())  # one line, whatever the message holds
        print(f"tbsim {ns.command}: error: {message}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
