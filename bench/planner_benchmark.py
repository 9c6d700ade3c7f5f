"""Planner benchmark throughput: scenes per second of ``run_benchmark``, one thread.

Prints the machine line (``bench/machine.py``), then, for each planner (default: the built-in
``constant_velocity``, ``expert`` and ``idm``) and each traffic mode (default:
``log_replay``), the scenes per second of whole benchmark episodes on the held-out real scenes
(files read and parsed beforehand; one warm-up scene apart), and where a scene's time goes:
building the environment (reset), the 80 steps, the planner, scoring (the rate: the median of
``--rounds`` timed runs, with their range). The default scene set is the 17 held-out scenes of
``docs/model_card/real_splits.json`` outside ``gpudrive_codec/`` (the held-out set before the
splits grew); ``--all-held-out`` takes all 59.

Target (issue 41): at least 5 scenes/s for a planner as cheap as IDM with log-replayed
traffic.

    python bench/planner_benchmark.py [--planners constant_velocity expert idm]
        [--traffic log_replay] [--all-held-out] [--rounds 3] [--womd-dir DIR]
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import pstats
import statistics
import sys
import time
import warnings
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import measure  # noqa: E402

from tbsim_env.benchmark.runner import BenchmarkSettings, run_benchmark  # noqa: E402
from tbsim_env.data import load_scenarios  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SPLITS = REPO / "docs" / "model_card" / "real_splits.json"
DEFAULT_DATA = Path(os.environ.get("TBSIM_WOMD_DIR", REPO.parent / "shared" / "data" / "womd"))

STAGES = {
    "reset": "parallel_env.py", "step": "parallel_env.py", "act": "planner.py",
    "score_record": "score.py",
}  # fmt: skip
"""Functions whose cumulative time the split reports, and the file each lives in."""


def held_out_scenes(womd_dir: Path, everything: bool) -> list:
    """The held-out scenes (the 17 outside ``gpudrive_codec/`` unless ``everything``)."""
    entries = json.loads(SPLITS.read_text())["held_out"]
    files = [
        e["file"] for e in entries if everything or not e["file"].startswith("gpudrive_codec/")
    ]
    scenes = []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for f in dict.fromkeys(files):
            scenes += list(load_scenarios(womd_dir / f))
    return scenes


def stage_split(stats: pstats.Stats, scenes: int) -> str:
    """ms per scene of each ``STAGES`` function (cumulative, from a cProfile run)."""
    out = []
    for (file, _, name), row in stats.stats.items():  # type: ignore[attr-defined]
        if name in STAGES and file.endswith(STAGES[name]):
            out.append(f"{name} {row[3] / scenes * 1e3:.0f}")
    return ", ".join(sorted(out)) + " ms/scene (profiled)"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--planners", nargs="+", default=["constant_velocity", "expert", "idm"])
    p.add_argument("--traffic", nargs="+", default=["log_replay"])
    p.add_argument("--all-held-out", action="store_true")
    p.add_argument("--womd-dir", type=Path, default=DEFAULT_DATA)
    p.add_argument("--rounds", type=int, default=3, help="timed runs per row (min/median/max)")
    args = p.parse_args()
    torch.set_num_threads(1)
    scenes = held_out_scenes(args.womd_dir, args.all_held_out)
    print(measure(scenes[:4]).line())
    print(f"{len(scenes)} held-out scenes")
    for planner in args.planners:
        for traffic in args.traffic:
            settings = BenchmarkSettings(planner=planner, traffic=(traffic,))
            run_benchmark(scenes[:1], settings, progress=False)  # warm-up
            rates = []
            for _ in range(args.rounds):
                start = time.perf_counter()
                run_benchmark(scenes, settings, progress=False)
                rates.append(len(scenes) / (time.perf_counter() - start))
            lo, mid, hi = min(rates), statistics.median(rates), max(rates)
            prof = cProfile.Profile()
            prof.runcall(run_benchmark, scenes, settings, progress=False)
            split = stage_split(pstats.Stats(prof), len(scenes))
            print(
                f"{planner:>18} / {traffic:<11} {mid:5.2f} scenes/s (median of "
                f"{len(rates)}; {lo:.2f}-{hi:.2f}) | {split}"
            )


if __name__ == "__main__":
    main()
