"""Baselines on the WOSAC realism metrics: log replay, constant velocity, (TrafficBots).

Every policy drives every sim agent of each scenario in the closed-loop simulator for the
80 future steps, R times (``tbsim_env.evaluation``), and the rollouts are scored with the
WOSAC metrics (``tbsim_env.metrics.wosac``). One table is printed: realism meta-metric, its
three buckets, ADE / minADE, and the simulated collision, off-road and red-light rates.

Log replay is the upper reference (its realism is the log's own); constant velocity and the
official linear-extrapolation formula are the simple baselines. ``trafficbots`` runs once its
rollout function and a checkpoint (``--checkpoint``) are available; otherwise it is reported
as skipped with the reason.

    python examples/log_replay_baseline.py [FILES...] [--policies log_replay constant_velocity]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

from policies import policy_names
from tbsim_env.data import load_scenarios
from tbsim_env.evaluation import evaluate_policy
from tbsim_env.metrics.wosac.scoring import aggregate

REPO = Path(__file__).resolve().parents[1]
COLUMNS = (
    ("realism_meta_metric", "realism", "{:.4f}"),
    ("kinematic_metrics", "kinematic", "{:.4f}"),
    ("interactive_metrics", "interactive", "{:.4f}"),
    ("map_based_metrics", "map", "{:.4f}"),
    ("average_displacement_error", "ADE m", "{:.2f}"),
    ("min_average_displacement_error", "minADE m", "{:.2f}"),
    ("simulated_collision_rate", "collision", "{:.3f}"),
    ("simulated_offroad_rate", "offroad", "{:.3f}"),
    ("simulated_traffic_light_violation_rate", "red light", "{:.3f}"),
)


def default_inputs() -> list[Path]:
    """The WOMD sample with full 9.1 s logs under ``$TBSIM_WOMD_DIR``, if present."""
    root = Path(os.environ.get("TBSIM_WOMD_DIR", REPO.parent / "shared" / "data" / "womd"))
    path = root / "waymo-open-dataset" / "motion_data_one_scenario.tfrecord"
    return [path] if path.exists() else []


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("files", nargs="*", help="WOMD Scenario TFRecords (default: the WOMD sample)")
    p.add_argument(
        "--generated", type=int, default=0, help="also evaluate N embedded generated scenes"
    )
    p.add_argument(
        "--policies",
        nargs="+",
        default=["log_replay", "constant_velocity", "linear_extrapolation", "trafficbots"],
        choices=policy_names(),
    )
    p.add_argument("--num-rollouts", type=int, default=32, help="rollouts per scenario (32)")
    p.add_argument("--version", default="wosac2025", choices=["wosac2025", "wosac2024"])
    p.add_argument("--checkpoint", default=None, help="TrafficBots checkpoint")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()

    scenarios = []
    for f in [Path(x) for x in args.files] or default_inputs():
        scenarios += load_scenarios(f)
    if args.generated:
        from tbsim_env.data.generator import default_scenarios

        scenarios += default_scenarios(args.generated)
    if not scenarios:
        raise SystemExit("no scenarios: pass WOMD files, set TBSIM_WOMD_DIR or use --generated N")
    print(
        f"{len(scenarios)} scenarios, {args.num_rollouts} rollouts each, metrics {args.version}\n"
    )

    header = f"{'policy':<22}" + "".join(f"{label:>12}" for _, label, _ in COLUMNS) + "      time"
    lines, skipped = [header, "-" * len(header)], []
    for policy in args.policies:
        start = time.perf_counter()
        try:
            scores, _ = evaluate_policy(
                scenarios,
                policy,
                num_rollouts=args.num_rollouts,
                seed=args.seed,
                version=args.version,
                checkpoint=args.checkpoint if policy == "trafficbots" else None,
            )
        except (ImportError, FileNotFoundError, ValueError, TypeError) as e:
            skipped.append(f"{policy}: skipped ({type(e).__name__}: {e})")
            continue
        total = aggregate(scores)
        cells = "".join(f"{fmt.format(getattr(total, key)):>12}" for key, _, fmt in COLUMNS)
        lines.append(f"{policy:<22}{cells}{time.perf_counter() - start:>9.1f}s")
    print("\n".join(lines))
    for s in skipped:
        print(s)


if __name__ == "__main__":
    main()
