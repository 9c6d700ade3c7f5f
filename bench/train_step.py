"""TrafficBots training throughput: scene samples per second and where a step spends its time.

Runs ``--steps`` optimiser steps of ``policies.trafficbots.losses.training_step`` (the spec's
losses, BPTT through the unicycle) on a token cache (``tbsim preprocess``), after one warm-up
step, and prints the samples per second and the split of the wall time: data (token batch),
prepare (scene encoders, latent, destinations), rollout forward (the closed-loop steps),
losses, backward, optimiser. ``--profile`` adds the top torch operators by self time.

    python bench/train_step.py --data CACHE [--batch-size 4] [--steps 5] [--threads 1]
        [--rollout-steps 91] [--profile]
"""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
from pathlib import Path

import torch

from policies.trafficbots import losses
from policies.trafficbots.batch import TokenBatch
from policies.trafficbots.checkpoint import load_state_into
from policies.trafficbots.config import TrafficBotsConfig
from policies.trafficbots.model import TrafficBots
from policies.trafficbots.wosac import DEFAULT_WEIGHTS
from tbsim_env.data.cache import open_training_data

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import measure  # noqa: E402

SPLIT = ("data", "prepare", "rollout", "losses", "backward", "optimiser")


@contextlib.contextmanager
def _timed_functions(totals: dict[str, float]):
    """Time ``model.prepare`` and ``rollout.rollout`` inside ``training_step`` (restored on
    exit); the rest of ``training_step`` counts as losses."""
    saved_prepare, saved_rollout = TrafficBots.prepare, losses.rollout

    def prepare(self, *a, **k):
        t = time.perf_counter()
        try:
            return saved_prepare(self, *a, **k)
        finally:
            totals["prepare"] += time.perf_counter() - t

    def roll(*a, **k):
        t = time.perf_counter()
        try:
            return saved_rollout(*a, **k)
        finally:
            totals["rollout"] += time.perf_counter() - t

    TrafficBots.prepare, losses.rollout = prepare, roll
    try:
        yield
    finally:
        TrafficBots.prepare, losses.rollout = saved_prepare, saved_rollout


def run(args: argparse.Namespace) -> dict[str, float]:
    """Train ``args.steps`` steps; returns the split (seconds) and ``samples_per_s``."""
    torch.set_num_threads(args.threads)
    data = open_training_data(str(args.data))
    model = TrafficBots(TrafficBotsConfig.small())
    load_state_into(model, DEFAULT_WEIGHTS)
    model.train()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-5)
    gen = torch.Generator().manual_seed(0)
    order = torch.randperm(len(data), generator=torch.Generator().manual_seed(1))
    totals = dict.fromkeys(SPLIT, 0.0)

    def one_step(k: int) -> None:
        t0 = time.perf_counter()
        rows = order[(k * args.batch_size + torch.arange(args.batch_size)) % len(data)]
        batch = TokenBatch.from_tokens([data[int(i)] for i in rows]).trim()
        t1 = time.perf_counter()
        loss, _ = losses.training_step(
            model, batch, teacher_forcing_p=0.0, generator=gen, n_steps=args.rollout_steps
        )
        t2 = time.perf_counter()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        t3 = time.perf_counter()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
        opt.step()
        t4 = time.perf_counter()
        for name, dt in zip(
            ("data", "forward", "backward", "optimiser"), (t1 - t0, t2 - t1, t3 - t2, t4 - t3)
        ):
            totals[name] = totals.get(name, 0.0) + dt

    one_step(0)  # warm-up (allocator, first-call costs)
    totals = dict.fromkeys(SPLIT, 0.0)
    profiler = (
        torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU])
        if args.profile
        else contextlib.nullcontext()
    )
    start = time.perf_counter()
    with _timed_functions(totals), profiler as prof:
        for k in range(1, args.steps + 1):
            one_step(k)
    wall = time.perf_counter() - start
    forward = totals.pop("forward")
    totals["losses"] = forward - totals["prepare"] - totals["rollout"]
    totals["samples_per_s"] = args.steps * args.batch_size / wall
    totals["wall"] = wall
    if args.profile:
        print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))
    return totals


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--data", type=Path, required=True, help="token cache folder")
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument("--steps", type=int, default=5)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--rollout-steps", type=int, default=None)
    p.add_argument("--profile", action="store_true")
    args = p.parse_args()
    print(measure(threads=args.threads).line())
    t = run(args)
    wall = t["wall"]
    print(
        f"batch {args.batch_size}, {args.steps} steps, {args.threads} thread(s): "
        f"{t['samples_per_s']:.2f} scene samples/s ({wall / args.steps:.2f} s per step)"
    )
    print("| part | s per step | share |\n|---|---|---|")
    for name in SPLIT:
        print(f"| {name} | {t[name] / args.steps:.3f} | {t[name] / wall:.1%} |")


if __name__ == "__main__":
    main()
