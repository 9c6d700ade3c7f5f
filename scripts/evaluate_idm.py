"""Realism of the ``idm`` policy beside the baselines on the real scenes of a split
(``docs/model_card/real_splits.json``), for ``docs/idm.md``.

Each policy is rolled out and scored by ``tbsim_env.evaluation.evaluate_policy`` (WOSAC
metrics, per-scenario seeds). Prints a markdown table of the means (meta-metric, its buckets,
minADE, collision and off-road rates) and how many scenes each policy scores above constant
velocity, and writes every per-scene score as JSON.

    python scripts/evaluate_idm.py --split held_out --rollouts 32 --out idm_held_out.json
        [--policies log_replay constant_velocity linear_extrapolation idm idm_lanes]
        [--limit K] [--version wosac2025]
"""

from __future__ import annotations

import argparse
import json
import os
import time
import warnings
from pathlib import Path

import numpy as np
import torch

from tbsim_env.data import load_scenarios
from tbsim_env.evaluation import evaluate_policy
from tbsim_env.metrics.wosac import scores_to_json

REPO = Path(__file__).resolve().parents[1]
SPLITS = REPO / "docs" / "model_card" / "real_splits.json"
DEFAULT_DATA = REPO.parent / "shared" / "data" / "womd"
POLICIES = ("log_replay", "constant_velocity", "linear_extrapolation", "idm", "idm_lanes")
COLUMNS = (
    ("meta", "realism_meta_metric", 3),
    ("kinematic", "kinematic_metrics", 3),
    ("interactive", "interactive_metrics", 3),
    ("map", "map_based_metrics", 3),
    ("minADE", "min_average_displacement_error", 2),
    ("collision", "simulated_collision_rate", 3),
    ("off-road", "simulated_offroad_rate", 3),
)


def split_scenes(split: str, data: Path, limit: int | None) -> list:
    """The scenes of a split (the first ``limit`` in file order), as ``Scenario`` objects."""
    entries = json.loads(SPLITS.read_text())[split][:limit]
    scenes = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for e in entries:
            found = [
                s for s in load_scenarios(data / e["file"]) if s.scenario_id == e["scenario_id"]
            ]
            scenes += found[:1]
    return scenes


def table(results: dict[str, list[dict]]) -> str:
    """Markdown table of the per-policy means and the scenes above constant velocity."""
    head = "| policy | " + " | ".join(c[0] for c in COLUMNS) + " | scenes > const. vel. |"
    lines = [head, "|" + "---|" * (len(COLUMNS) + 2)]
    cv = {r["scenario_id"]: r["realism_meta_metric"] for r in results.get("constant_velocity", [])}
    for policy, rows in results.items():
        cells = [f"{np.mean([r[key] for r in rows]):.{nd}f}" for _, key, nd in COLUMNS]
        above = sum(r["realism_meta_metric"] > cv.get(r["scenario_id"], np.inf) for r in rows)
        lines.append(f"| {policy} | " + " | ".join(cells) + f" | {above} / {len(rows)} |")
    return "\n".join(lines)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--split", default="held_out", help="train | validation | held_out")
    p.add_argument("--data", default=os.environ.get("TBSIM_WOMD_DIR", DEFAULT_DATA))
    p.add_argument("--policies", nargs="+", default=list(POLICIES))
    p.add_argument("--rollouts", type=int, default=32)
    p.add_argument("--limit", type=int, default=None, help="only the first K scenes")
    p.add_argument("--version", default="wosac2025")
    p.add_argument("--out", default=None, help="JSON of every per-scene score")
    args = p.parse_args()
    torch.set_num_threads(1)
    scenes = split_scenes(args.split, Path(args.data), args.limit)
    print(f"{len(scenes)} scenes of split {args.split}, {args.rollouts} rollouts, {args.version}")
    results: dict[str, list[dict]] = {}
    for policy in args.policies:
        start = time.perf_counter()
        scores, _ = evaluate_policy(
            scenes, policy, num_rollouts=args.rollouts, version=args.version
        )
        results[policy] = scores_to_json(scores)["scenarios"]
        print(f"{policy}: {time.perf_counter() - start:.0f} s", flush=True)
    print(table(results))
    if args.out:
        Path(args.out).write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
