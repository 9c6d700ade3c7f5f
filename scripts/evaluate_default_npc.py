"""Measure the shipped TrafficBots NPC against the baselines for docs/MODEL_CARD.md.

Sets (``--sets``), none of them in the training cache (see scripts/train_default_npc.sh; the
shipped weights trained on generated seeds 0-1759):
  * ``real``, held out: 637f20cafde22ff8 (motion_data_one_scenario.tfrecord) and
    db4edc9bd0c9d18c (gpudrive/tfrecord-00000-of-01000_4.json);
  * ``generated``, held out: seeds 10000-10007, two of each layout; the shipped weights were
    chosen among candidates on this set and ``real``;
  * ``more``, held out: seeds 10008-10039, eight of each layout, on which no training run and
    no choice of weights was made;
  * ``validation``: seeds 20000-20023, six of each layout, for choosing between checkpoints, so
    that the held-out sets stay untouched by that choice;
  * ``permissive``: seeds 30000-30007 of the permissive intersection, a layout the shipped
    weights never trained on; it probes the failure the model card describes (queues behind a
    vehicle that waits at a green light).

Prints markdown tables (wosac2025 and wosac2024, 32 rollouts each) and writes a JSON of every
per-scenario field, plus a rollout picture.

    python scripts/evaluate_default_npc.py --out docs/model_card [--checkpoint PATH]
        [--samples 64] [--road-edge-weight 0] [--gap-keeping off] [--road-keeping ""]
        [--sets real,generated]
        [--policies log_replay,trafficbots] [--keep] [--workers 2]

With ``--keep``, the sets and policies not evaluated in this run keep their results from the
``results.json`` already in ``--out`` (e.g. re-evaluate a new checkpoint, keep the baselines);
``--sets '' --keep`` only rewrites ``results.md`` from it.
"""

from __future__ import annotations

import argparse
import functools
import json
import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import torch

from tbsim_env.data import load_scenarios
from tbsim_env.data.generator import generate_scenario
from tbsim_env.evaluation import make_rollout_fn, scenario_seed
from tbsim_env.metrics.wosac import score_scenario, scores_to_json

HELD_OUT_REAL = (
    "waymo-open-dataset/motion_data_one_scenario.tfrecord",
    "gpudrive/tfrecord-00000-of-01000_4.json",
)
EVAL_LAYOUTS = ("intersection", "merge", "stop_intersection", "t_junction")
"""The layouts of the held-out and validation sets (the permissive intersection has its own
probe set)."""
HELD_OUT_GENERATED = tuple((EVAL_LAYOUTS[s % len(EVAL_LAYOUTS)], 10000 + s) for s in range(8))
VALIDATION_GENERATED = tuple((EVAL_LAYOUTS[s % len(EVAL_LAYOUTS)], 20000 + s) for s in range(24))
MORE_HELD_OUT_GENERATED = tuple(
    (EVAL_LAYOUTS[s % len(EVAL_LAYOUTS)], 10000 + s) for s in range(8, 40)
)
PERMISSIVE_PROBE = tuple(("permissive_intersection", 30000 + s) for s in range(8))
SETS = ("real", "generated", "more", "validation", "permissive")
VERSIONS = ("wosac2025", "wosac2024")
POLICIES = ("log_replay", "constant_velocity", "linear_extrapolation", "trafficbots")
COLUMNS = (
    ("realism_meta_metric", "meta"),
    ("kinematic_metrics", "kinematic"),
    ("interactive_metrics", "interactive"),
    ("map_based_metrics", "map"),
    ("min_average_displacement_error", "minADE"),
    ("simulated_collision_rate", "collision rate"),
    ("simulated_offroad_rate", "off-road rate"),
)


@functools.cache
def rollout_fn(
    policy: str,
    checkpoint: str | None,
    samples: int,
    road_edge_weight: float | None,
    rules: tuple[str | None, str | None],
):
    """The ``(scenario, num_rollouts, seed) -> Rollouts`` of ``policy``, built once per process
    (``rules``: TrafficBots' gap- and road-keeping flags, ``InferenceConfig.with_rule_flags``)."""
    if policy == "trafficbots":
        from policies.trafficbots.config import InferenceConfig
        from policies.trafficbots.wosac import trafficbots_rollout_fn

        return trafficbots_rollout_fn(
            checkpoint=checkpoint,
            num_samples=samples,
            road_edge_weight=road_edge_weight,
            inference=InferenceConfig().with_rule_flags(*rules),
        )
    return make_rollout_fn(policy)


def score_scene(policy: str, checkpoint: str | None, samples: int, trafficbots: tuple, sc) -> dict:
    """{version: ``ScenarioScore``} of 32 rollouts of ``policy`` on ``sc``, seeded by its id;
    ``trafficbots``: (road-edge weight, (gap-keeping flag, road-keeping flag)) of that
    policy."""
    fn = rollout_fn(policy, checkpoint, samples, *trafficbots)
    r = fn(sc, 32, scenario_seed(0, sc.scenario_id))
    return {v: score_scenario(sc, r, v) for v in VERSIONS}


def table(rows: dict[str, dict], version: str) -> str:
    head = "| policy | " + " | ".join(c[1] for c in COLUMNS) + " |"
    sep = "|---" * (len(COLUMNS) + 1) + "|"
    lines = [f"**{version}**", "", head, sep]
    for pol, agg in rows.items():
        lines.append(f"| {pol} | " + " | ".join(f"{agg[c[0]]:.4f}" for c in COLUMNS) + " |")
    return "\n".join(lines)


INTERVAL_FIELDS = (
    ("realism_meta_metric", "meta"),
    ("simulated_collision_rate", "collision rate"),
    ("simulated_offroad_rate", "off-road rate"),
)


def bootstrap_interval(
    values: list[float], level: float = 0.9, draws: int = 10_000, seed: int = 0
) -> tuple[float, float]:
    """Percentile bootstrap interval of the mean of ``values`` (scenes resampled with
    replacement, a fixed seed so that the report is reproducible)."""
    x = np.asarray(values, dtype=np.float64)
    means = np.random.default_rng(seed).choice(x, (draws, len(x))).mean(1)
    tail = 100 * (1 - level) / 2
    lo, hi = np.percentile(means, [tail, 100 - tail])
    return float(lo), float(hi)


def interval_table(per_policy: dict[str, list[dict]]) -> str:
    """Markdown: mean [90% bootstrap interval over scenes] of the headline fields."""
    head = "| policy | " + " | ".join(c[1] for c in INTERVAL_FIELDS) + " |"
    lines = ["90% bootstrap intervals over scenes (wosac2025)", "", head]
    lines.append("|---" * (len(INTERVAL_FIELDS) + 1) + "|")
    for pol, scenes in per_policy.items():
        cells = []
        for field, _ in INTERVAL_FIELDS:
            values = [sc[field] for sc in scenes]
            lo, hi = bootstrap_interval(values)
            cells.append(f"{np.mean(values):.4f} [{lo:.4f}, {hi:.4f}]")
        lines.append(f"| {pol} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default="docs/model_card")
    p.add_argument("--checkpoint", default=None)
    p.add_argument("--samples", type=int, default=32, help="TrafficBots rollouts sampled (>=32)")
    p.add_argument(
        "--road-edge-weight",
        type=float,
        default=None,
        help="TrafficBots: keep the rollouts with fewest collided + this x road-departing "
        "agents (default: the inference rules', shipped 1)",
    )
    p.add_argument(
        "--gap-keeping",
        metavar="off|NAME=VALUE,...",
        help='TrafficBots\' gap-keeping rule: "off", or GapKeeping fields to change (default: '
        "the shipped rule)",
    )
    p.add_argument(
        "--road-keeping",
        metavar="off|NAME=VALUE,...",
        help="TrafficBots' road-keeping rule (off when shipped): RoadKeeping fields to change "
        '("" for its defaults)',
    )
    p.add_argument("--data", default=os.environ.get("TBSIM_WOMD_DIR", "../shared/data/womd"))
    p.add_argument(
        "--sets",
        default="real,generated",
        help="comma-separated sets: real, generated (held out), more (32 more held-out "
        "generated scenes), validation (for choosing), permissive (probe of queues at a green "
        "light)",
    )
    p.add_argument("--policies", default=",".join(POLICIES), help="comma-separated policies")
    p.add_argument(
        "--keep",
        action="store_true",
        help="keep the results of other sets / policies from OUT/results.json",
    )
    p.add_argument(
        "--workers",
        type=int,
        default=1,
        help="processes scoring scenes in parallel, 1 thread each",
    )
    args = p.parse_args()
    torch.set_num_threads(1)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    wanted = set(args.sets.split(",")) - {""}
    if args.workers < 1:
        p.error(f"--workers must be at least 1, got {args.workers}")
    if wanted - set(SETS):
        p.error(f"unknown sets {sorted(wanted - set(SETS))}; choose from {', '.join(SETS)}")
    policies = [pol for pol in POLICIES if pol in args.policies.split(",")]
    sets = {}
    if "real" in wanted:
        sets["held-out real WOMD"] = [load_scenarios(Path(args.data) / f)[0] for f in HELD_OUT_REAL]
    if "generated" in wanted:
        sets["held-out generated"] = [
            generate_scenario(lay, seed) for lay, seed in HELD_OUT_GENERATED
        ]
    if "more" in wanted:
        sets["more held-out generated"] = [
            generate_scenario(lay, seed) for lay, seed in MORE_HELD_OUT_GENERATED
        ]
    if "validation" in wanted:
        sets["validation generated"] = [
            generate_scenario(lay, seed) for lay, seed in VALIDATION_GENERATED
        ]
    if "permissive" in wanted:
        sets["permissive probe"] = [generate_scenario(lay, seed) for lay, seed in PERMISSIVE_PROBE]
    dump = {}
    if args.keep and (out / "results.json").exists():
        dump = json.loads((out / "results.json").read_text())
    pool = (
        ProcessPoolExecutor(args.workers, mp.get_context("spawn"), torch.set_num_threads, (1,))
        if args.workers > 1
        else None
    )
    for set_name, scenarios in sets.items():
        for pol in policies:
            weight = args.road_edge_weight if pol == "trafficbots" else None
            options = (weight, (args.gap_keeping, args.road_keeping))
            job = functools.partial(score_scene, pol, args.checkpoint, args.samples, options)
            # In scene order either way; each scene's seed comes from its id, so the scores do
            # not depend on the number of workers.
            results = pool.map(job, scenarios) if pool else map(job, scenarios)
            scores = {v: [] for v in VERSIONS}
            for sc, per_version in zip(scenarios, results):
                for v in VERSIONS:
                    scores[v].append(per_version[v])
                print(
                    f"{set_name} {pol} {sc.scenario_id}: "
                    f"{per_version['wosac2025'].realism_meta_metric:.4f}",
                    flush=True,
                )
            for v in scores:
                dump[f"{set_name}/{pol}/{v}"] = scores_to_json(scores[v])
    if pool:
        pool.shutdown()
    report = []
    for set_name in dict.fromkeys(k.split("/")[0] for k in dump):
        ids = next(
            [s["scenario_id"] for s in d["scenarios"]]
            for k, d in dump.items()
            if k.startswith(set_name + "/")
        )
        report.append(f"### {set_name} ({', '.join(ids)})\n")
        for v in VERSIONS:
            rows = {
                pol: dump[f"{set_name}/{pol}/{v}"]["mean"]
                for pol in POLICIES
                if f"{set_name}/{pol}/{v}" in dump
            }
            report.append(table(rows, v) + "\n")
        per_policy = {
            pol: dump[f"{set_name}/{pol}/wosac2025"]["scenarios"]
            for pol in POLICIES
            if f"{set_name}/{pol}/wosac2025" in dump
        }
        report.append(interval_table(per_policy) + "\n")
    text = "\n".join(report)
    print(text)
    (out / "results.md").write_text(text)
    (out / "results.json").write_text(json.dumps(dump, indent=1, default=float))


if __name__ == "__main__":
    main()
