"""Environment and simulation-core throughput.

Prints the machine line (``bench/machine.py``: CPU, versions, threads, the cost of a tiny
operation, matmul GFLOP/s, copy GB/s and log replay's bare core, all measured in this run),
then (a) PettingZoo ``TrafficEnv`` steps/s on a real WOMD scenario with one controlled agent,
log-replayed NPCs and full observations, eager and with ``compile=True`` (the step as one
``torch.compile`` graph; its compile time is printed apart), with the ATen operations of an
eager step (profiler count: the same on every machine) and the step's time in tiny
operations; and (b) batched-core agent steps/s (dynamics + log replay merge, every agent
integrating actions) at batch 1, 16 and 64. Each rate is also given against the bare core.

Targets (the promise is the ratios, not the rates): (a) at most 400 ATen operations per eager
step (``tests/test_op_count.py`` guards it), (b) the batched core at batch 64 within 2x of the
bare core.

    python bench/env_step.py [--data DIR] [--threads N]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import measure  # noqa: E402
from stages import format_split, stage_times  # noqa: E402

from tbsim_env.core.torch_utils import aten_op_count  # noqa: E402
from tbsim_env.data import load_scenarios  # noqa: E402
from tbsim_env.env import TrafficEnv  # noqa: E402
from tbsim_env.sim import core  # noqa: E402
from tbsim_env.sim.build import build_sim_state  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "womd"


def make_env(scenarios, compile: bool = False) -> TrafficEnv:
    env = TrafficEnv(scenarios, controlled="sdc", npc_policy="log_replay", compile=compile)
    env.reset(seed=0)
    return env


def bench_env(env: TrafficEnv, episodes: int) -> tuple[float, float, int]:
    """(env steps/s, agent steps/s, steps) of ``episodes`` log-replay episodes (resets included)."""
    n_agents = int(env.sim_state.agents.mask.sum())
    steps = 0
    start = time.perf_counter()
    for _ in range(episodes):
        env.reset()
        zero = {a: np.zeros(2, np.float32) for a in env.agents}
        while env.agents:
            env.step({a: zero[a] for a in env.agents})
            steps += 1
    dt = time.perf_counter() - start
    return steps / dt, steps * n_agents / dt, steps


def step_ops(env: TrafficEnv, steps: int = 20) -> float:
    """ATen operations per eager step of ``env`` (torch profiler, ``steps`` steps)."""
    env.reset()
    zero = {a: np.zeros(2, np.float32) for a in env.agents}

    def one() -> None:
        if not env.agents:
            env.reset()
        env.step({a: zero[a] for a in env.agents})

    return aten_op_count(one, steps)


def bench_core(scenarios, batch: int, steps: int) -> float:
    batch_sc = [scenarios[i % len(scenarios)] for i in range(batch)]
    state0 = build_sim_state(batch_sc)
    # Every agent integrates actions (the expensive path); none is replayed.
    state0 = state0.replace(controlled=state0.agents.mask.clone())
    action = torch.zeros(*state0.pose.shape[:2], 2)
    n_agents = int(state0.agents.mask.sum())
    done = 0
    start = time.perf_counter()
    while done < steps:
        state = state0
        for _ in range(min(80, steps - done)):
            state = core.step(state, action)
            done += 1
    dt = time.perf_counter() - start
    return done * n_agents / dt


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", default=os.environ.get("TBSIM_WOMD_DIR", DEFAULT_DATA))
    p.add_argument(
        "--threads", type=int, default=1, help="torch intra-op threads (1 is fastest here)"
    )
    p.add_argument("--episodes", type=int, default=5)
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    path = Path(args.data) / "waymo-open-dataset" / "motion_data_one_scenario.tfrecord"
    if path.exists():
        scenarios, label = load_scenarios(path), f"real WOMD {path.name}"
    else:
        from tbsim_env.data.generator import default_scenarios

        scenarios, label = default_scenarios(2), "generated scenes (no WOMD data found)"
    machine = measure(scenarios, args.threads)
    print(machine.line())
    print(f"scenario: {label}")
    eager = make_env(scenarios)
    env_sps, env_asps, _ = bench_env(eager, args.episodes)
    ops = step_ops(eager)
    print(
        f"(a) TrafficEnv, 1 controlled + log replay, obs: {env_sps:8.0f} env steps/s "
        f"({env_asps:,.0f} agent steps/s, {machine.of_core(env_asps)}); "
        f"{ops:.0f} ATen ops per step (target <= 400), a step = "
        f"{machine.in_tiny_ops(1 / env_sps)}"
    )
    compiled = make_env(scenarios, compile=True)
    start = time.perf_counter()
    bench_env(compiled, 1)  # compiles on the first step
    warm = time.perf_counter() - start
    c_sps, c_asps, _ = bench_env(compiled, args.episodes)
    print(
        f"    the same with compile=True:                 {c_sps:8.0f} env steps/s "
        f"({c_asps:,.0f} agent steps/s; {c_sps / env_sps:.2f}x eager; first episode, "
        f"compile included, {warm:.1f} s; {compiled.step_function.eager_redos} steps redone "
        "eagerly)"
    )
    totals: dict[str, float] = {}
    with stage_times(totals):
        start = time.perf_counter()
        sps, _, steps = bench_env(eager, args.episodes)
        wall = time.perf_counter() - start
    print(
        f"    eager stages (separate timed run, {1e3 * wall / steps:.3f} ms per step): "
        + format_split(totals, wall)
    )
    for b in (1, 16, 64):
        asps = bench_core(scenarios, b, 400)
        print(
            f"(b) batched core, batch {b:3d}: {asps:14,.0f} agent steps/s "
            f"({machine.of_core(asps)})" + ("   target >= 0.5x core" if b == 64 else "")
        )


if __name__ == "__main__":
    main()
