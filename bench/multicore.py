"""Both cores: agent steps/s of ``BatchedTrafficEnv`` in P worker processes (each its own batch,
one intra-op thread) against one process, and of one process with P intra-op threads.

The way to use several cores is one environment per process: each worker builds its own
``BatchedTrafficEnv`` (its own scenes, seed and batch) and steps it on one thread; the workers
share nothing, so they scale with the cores until memory bandwidth binds. Intra-op threads
split each operation instead, which pays only where operations are large. All workers start
together (a barrier) and each reports its agent steps and wall time; the aggregate rate is the
sum of the workers' rates. The figures are measured in one run, so the ratios hold on any
machine; the first line names the machine.

    python bench/multicore.py [--workers 2] [--batch 64] [--controlled all] [--steps 300]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import measure  # noqa: E402
from vector_env import DEFAULT_DATA, load  # noqa: E402

from tbsim_env.env.vector_env import BatchedTrafficEnv  # noqa: E402


def _run(args: argparse.Namespace, threads: int, seed: int) -> tuple[int, float]:
    """(active agent steps, seconds) of ``args.steps`` batched steps after a warm-up."""
    scenarios, _ = load(args.scenarios, str(args.data))
    env = BatchedTrafficEnv(
        scenarios,
        args.batch,
        controlled=args.controlled,
        npc_policy=args.npc_policy,
        seed=seed,
        torch_threads=threads,
        obs_layout="indexed",
    )
    env.reset(seed=seed)
    zeros = torch.zeros(args.batch, env.num_agents, 2)
    for _ in range(10):
        env.step(zeros)
    steps = 0
    start = time.perf_counter()
    for _ in range(args.steps):
        steps += int(env.agent_mask.sum())
        env.step(zeros)
    return steps, time.perf_counter() - start


def _worker(args: argparse.Namespace, seed: int, barrier, out) -> None:
    torch.set_num_threads(1)
    barrier.wait()
    out.put(_run(args, 1, seed))


def processes(args: argparse.Namespace, workers: int) -> float:
    """Summed agent steps/s of ``workers`` processes stepping at the same time."""
    ctx = mp.get_context("spawn")
    barrier, out = ctx.Barrier(workers), ctx.Queue()
    procs = [ctx.Process(target=_worker, args=(args, k, barrier, out)) for k in range(workers)]
    for p in procs:
        p.start()
    results = [out.get() for _ in procs]
    for p in procs:
        p.join()
    return sum(steps / seconds for steps, seconds in results)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", default=os.environ.get("TBSIM_WOMD_DIR", DEFAULT_DATA))
    p.add_argument("--scenarios", choices=["auto", "womd", "generated"], default="auto")
    p.add_argument("--workers", type=int, default=2)
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--controlled", default="all", help="sdc | tracks_to_predict | all")
    p.add_argument("--npc-policy", default="log_replay")
    p.add_argument("--steps", type=int, default=300, help="batched steps per worker")
    args = p.parse_args()
    scenarios, label = load(args.scenarios, str(args.data))
    print(measure(scenarios, 1).line())
    print(
        f"BatchedTrafficEnv B = {args.batch}, controlled={args.controlled}, "
        f"npc={args.npc_policy}, indexed, {label}; {os.cpu_count()} CPUs"
    )
    one = processes(args, 1)
    many = processes(args, args.workers)
    torch.set_num_threads(args.workers)
    steps, seconds = _run(args, args.workers, 0)
    threaded = steps / seconds
    print(f"{'layout':<34} {'agent steps/s':>14} {'x 1 process':>12}")
    print(f"{'1 process, 1 thread':<34} {one:>14,.0f} {1.0:>12.2f}")
    print(f"{f'{args.workers} processes, 1 thread each':<34} {many:>14,.0f} {many / one:>12.2f}")
    print(f"{f'1 process, {args.workers} threads':<34} {threaded:>14,.0f} {threaded / one:>12.2f}")


if __name__ == "__main__":
    main()
