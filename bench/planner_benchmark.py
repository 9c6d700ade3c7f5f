"""Planner benchmark throughput: scenes per second of ``run_benchmark``, one thread.

Prints the machine line (``bench/machine.py``), then, for each planner (default: the built-in
``constant_velocity``, ``expert`` and ``idm``) and each traffic mode (default:
``log_replay``), the scenes per second of whole benchmark episodes on the held-out real scenes
(files read and parsed beforehand; a warm-up apart) at each ``--batch-sizes`` value (scenes
stepped together where the episodes stay the same: ``tbsim_env.benchmark.batch``), and where
a scene's time goes: building the simulation (reset), the 80 steps, the planner, scoring (the
rate: the median of ``--rounds`` timed runs, the batch sizes interleaved, with their range).
The default scene set is the 17 held-out scenes of ``docs/model_card/real_splits.json``
outside ``gpudrive_codec/`` (the held-out set before the splits grew); ``--all-held-out``
takes all 59.

Target (issue 41): at least 5 scenes/s for a planner as cheap as IDM with log-replayed
traffic.

    python bench/planner_benchmark.py [--planners constant_velocity expert idm]
        [--traffic log_replay] [--batch-sizes 1 16] [--all-held-out] [--rounds 3]
        [--womd-dir DIR]
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
from tbsim_env.sim.edge_grid import forget_grids  # noqa: E402

REPO = Path(__file__).resolve().parents[1]
SPLITS = REPO / "docs" / "model_card" / "real_splits.json"
DEFAULT_DATA = Path(os.environ.get("TBSIM_WOMD_DIR", REPO.parent / "shared" / "data" / "womd"))

STAGES = {
    "reset": [("reset", "parallel_env.py"), ("_start", "batch.py")],
    "step": [("step", "parallel_env.py"), ("advance", "batch.py")],
    "act": [("act", "planner.py"), ("act_batch", "planner.py")],
    "score": [("score_record", "score.py")],
}
"""Per stage, the functions whose cumulative time the split reports, in order of preference
(the first one the run called: one scene at a time, or a batch), and the file of each."""


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
    """ms per scene of each ``STAGES`` entry (cumulative, from a cProfile run)."""
    found = {
        (name, file.rsplit("/", 1)[-1]): row[3]
        for (file, _, name), row in stats.stats.items()  # type: ignore[attr-defined]
    }
    out = []
    for label, candidates in STAGES.items():
        hit = next((found[c] for c in candidates if c in found), None)
        if hit is not None:
            out.append(f"{label} {hit / scenes * 1e3:.0f}")
    return ", ".join(out) + " ms/scene (profiled)"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--planners", nargs="+", default=["constant_velocity", "expert", "idm"])
    p.add_argument("--traffic", nargs="+", default=["log_replay"])
    p.add_argument("--all-held-out", action="store_true")
    p.add_argument("--womd-dir", type=Path, default=DEFAULT_DATA)
    p.add_argument("--rounds", type=int, default=3, help="timed runs per row (min/median/max)")
    p.add_argument(
        "--batch-sizes", type=int, nargs="+", default=[1, 16],
        help="BenchmarkSettings.batch_size values (ratios against the first)",
    )  # fmt: skip
    args = p.parse_args()
    torch.set_num_threads(1)
    scenes = held_out_scenes(args.womd_dir, args.all_held_out)
    print(measure(scenes[:4]).line())
    print(f"{len(scenes)} held-out scenes")
    for planner in args.planners:
        for traffic in args.traffic:
            rates: dict[int, list[float]] = {b: [] for b in args.batch_sizes}
            for batch in args.batch_sizes:  # warm-up
                settings = BenchmarkSettings(planner, (traffic,), batch_size=batch)
                run_benchmark(scenes[:2], settings, progress=False)
            for _ in range(args.rounds):  # the batch sizes interleaved in every round
                for batch in args.batch_sizes:
                    settings = BenchmarkSettings(planner, (traffic,), batch_size=batch)
                    forget_grids()  # each round builds its road-edge grids, as a fresh run does
                    start = time.perf_counter()
                    run_benchmark(scenes, settings, progress=False)
                    rates[batch].append(len(scenes) / (time.perf_counter() - start))
            for batch in args.batch_sizes:
                settings = BenchmarkSettings(planner, (traffic,), batch_size=batch)
                prof = cProfile.Profile()
                forget_grids()
                prof.runcall(run_benchmark, scenes, settings, progress=False)
                split = stage_split(pstats.Stats(prof), len(scenes))
                r = rates[batch]
                lo, mid, hi = min(r), statistics.median(r), max(r)
                ratio = mid / statistics.median(rates[args.batch_sizes[0]])
                print(
                    f"{planner:>18} / {traffic:<11} batch {batch:>3} {mid:6.2f} scenes/s "
                    f"(median of {len(r)}; {lo:.2f}-{hi:.2f}; {ratio:.2f}x) | {split}"
                )


if __name__ == "__main__":
    main()
