"""WOSAC metric throughput: seconds per scenario for 32 rollouts of 50+ agents on CPU.

Uses the real pair (``motion_data_one_scenario.tfrecord`` + ``test_submission.binproto``, 50
sim agents, 4 evaluated) when the WOMD sample data is present, else a synthetic 60-agent
scenario. Prints the time of ``score_scenario`` (best and median of the repeats) for each thread
count, plus the submission parse + validation time. Target: < 1 s per scenario on 2 cores.
On a loaded shared machine 1 thread can beat 2 (each parallel op then waits for a busy core).

    python bench/wosac_metrics.py [--data DIR] [--repeats N] [--threads 2 1] [--version V]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import torch

from tbsim_env.metrics.wosac.scoring import score_scenario
from tbsim_env.metrics.wosac.submission import (
    read_submission,
    rollouts_from_proto,
    validate_scenario_rollouts,
)
from tbsim_env.metrics.wosac.synthetic import noisy_rollouts, synthetic_scenario

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import measure  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "womd"


def load_case(data: Path):
    """(label, scenario, rollouts, parse seconds) for the real pair, or a synthetic case."""
    womd = data / "waymo-open-dataset"
    sub_path = womd / "sim_agents" / "test_submission.binproto"
    if sub_path.is_file():
        from tbsim_env.data.womd import read_scenarios

        scenario = next(iter(read_scenarios(womd / "motion_data_one_scenario.tfrecord")))
        start = time.perf_counter()
        proto = read_submission(sub_path).scenario_rollouts[0]
        validate_scenario_rollouts(proto, scenario)
        rollouts = rollouts_from_proto(proto)
        parse = time.perf_counter() - start
        return f"real {scenario.scenario_id}", scenario, rollouts, parse
    scenario = synthetic_scenario(num_agents=60)
    return "synthetic (no WOMD data found)", scenario, noisy_rollouts(scenario), 0.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--data", type=Path, default=Path(os.environ.get("TBSIM_WOMD_DIR", DEFAULT_DATA))
    )
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, nargs="+", default=[2, 1])
    parser.add_argument("--version", default="wosac2025")
    args = parser.parse_args()
    label, scenario, rollouts, parse = load_case(args.data)
    print(measure(threads=max(args.threads)).line())
    print(
        f"case: {label}; {rollouts.num_rollouts} rollouts x {rollouts.num_objects} agents x "
        f"{rollouts.num_steps} steps; metric {args.version}"
    )
    if parse:
        print(f"submission read + validate + convert: {parse:.3f} s")
    for threads in args.threads:
        torch.set_num_threads(threads)
        score_scenario(scenario, rollouts, args.version)  # warm-up
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            scores = score_scenario(scenario, rollouts, args.version)
            times.append(time.perf_counter() - start)
        print(
            f"threads={threads}: {min(times):.3f} s/scenario best, "
            f"{statistics.median(times):.3f} s median over {args.repeats} "
            f"(meta-metric {scores.realism_meta_metric:.4f})"
        )


if __name__ == "__main__":
    main()
