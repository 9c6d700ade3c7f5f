"""The machine a figure was measured on, measured in the same run: the line every bench prints.

A rate measured on one machine says little about the next one (a tiny torch operation costs
1 us on one CPU and 5 us on another; a busy machine halves everything). Every bench therefore
prints, beside its figures, one line naming the machine and anchoring it:

* what it is: CPU model and its widest SIMD, cores, torch and numpy versions, intra-op
  threads, the load average when the bench started (other jobs on the cores);
* what it does, measured now on one thread: the cost of one tiny torch operation (an
  ``add_`` on a 10-element tensor: what bounds a step made of many small operations),
  dense float32 matmul GFLOP/s (compute) and ``copy_`` GB/s of a 64 MiB tensor (memory);
* the anchor: agent steps/s of log replay's bare core (``sim.core.step`` of a batch of 64
  scenes, every agent replayed from the log; no metrics, no observations).

Figures are then also given as ratios that travel between machines better than rates: a
rate over the anchor (``of_core``), and a step's time in tiny operations (``in_tiny_ops``).

    python bench/machine.py  # the line alone
"""

from __future__ import annotations

import os
import platform
import statistics
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

BARE_CORE_BATCH = 64
"""Scenes in the bare-core anchor's batch."""
BARE_CORE_STEPS = 80
"""Steps per round of the anchor (one episode of the default config)."""
COPY_MIB = 64
"""Size of the copy-bandwidth tensor: far beyond the caches."""
MATMUL_N = 512
"""Side of the square matmul of the GFLOP/s figure."""


@dataclass(frozen=True)
class Machine:
    """What the machine is and what it does now (one thread).

    Attributes:
        cpu: CPU model and widest SIMD.
        cores: logical CPUs.
        threads: torch intra-op threads of the bench.
        load: 1-minute load average at the start (0 where unknown).
        tiny_op_us: us per tiny torch operation (``add_`` on 10 floats).
        matmul_gflops: dense float32 matmul, one thread.
        copy_gbs: ``copy_`` of a 64 MiB float32 tensor, one thread (bytes written per s).
        core_rate: agent steps/s of log replay's bare core (batch 64); 0 when not measured.
    """

    cpu: str
    cores: int
    threads: int
    load: float
    tiny_op_us: float
    matmul_gflops: float
    copy_gbs: float
    core_rate: float

    def line(self) -> str:
        """The one-line description every bench prints."""
        core = f", bare core {self.core_rate:,.0f} agent steps/s" if self.core_rate else ""
        return (
            f"machine: {self.cpu}, {self.cores} cores, load {self.load:.1f}; torch "
            f"{torch.__version__}, numpy {np.__version__}, {self.threads} thread(s) | "
            f"tiny op {self.tiny_op_us:.2f} us, matmul {self.matmul_gflops:.0f} GFLOP/s, "
            f"copy {self.copy_gbs:.1f} GB/s{core}"
        )

    def of_core(self, agent_rate: float) -> str:
        """``agent_rate`` (agent steps/s) as a fraction of the bare core ("" unmeasured)."""
        return f"{agent_rate / self.core_rate:.3f}x core" if self.core_rate else ""

    def in_tiny_ops(self, seconds: float) -> str:
        """A time as a count of tiny operations of this machine."""
        return f"{seconds * 1e6 / self.tiny_op_us:,.0f} tiny ops"


def cpu_model() -> str:
    """CPU model name and its widest SIMD extension (Linux ``/proc/cpuinfo``; else platform)."""
    name, flags = platform.processor() or platform.machine(), set()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            key, _, value = line.partition(":")
            if key.strip() == "model name" and name in ("", platform.machine(), "x86_64"):
                name = value.strip()
            elif key.strip() == "flags" and not flags:
                flags = set(value.split())
    except OSError:
        pass
    simd = next((f for f in ("avx512f", "avx2", "avx", "sse4_2", "neon") if f in flags), "")
    return f"{name} ({simd.replace('avx512f', 'avx512')})" if simd else name


def _median_time(fn, rounds: int, inner: int) -> float:
    """Median over ``rounds`` of the seconds per call of ``fn`` called ``inner`` times."""
    fn()
    times = []
    for _ in range(rounds):
        start = time.perf_counter()
        for _ in range(inner):
            fn()
        times.append((time.perf_counter() - start) / inner)
    return statistics.median(times)


def tiny_op_us(rounds: int = 7, inner: int = 2000) -> float:
    """us per ``add_`` of a 10-element float32 tensor (median of rounds)."""
    x, y = torch.zeros(10), torch.ones(10)
    return 1e6 * _median_time(lambda: x.add_(y), rounds, inner)


def matmul_gflops(n: int = MATMUL_N, rounds: int = 5) -> float:
    """Dense float32 ``n`` x ``n`` matmul GFLOP/s (median of rounds)."""
    a, b = torch.randn(n, n), torch.randn(n, n)
    return 2 * n**3 / _median_time(lambda: a @ b, rounds, 3) / 1e9


def copy_gbs(mib: int = COPY_MIB, rounds: int = 5) -> float:
    """GB/s written by ``copy_`` of a ``mib`` MiB float32 tensor (median of rounds)."""
    n = mib * (1 << 20) // 4
    a, b = torch.empty(n), torch.ones(n)
    a.copy_(b)
    return mib * (1 << 20) / _median_time(lambda: a.copy_(b), rounds, 2) / 1e9


def bare_core_rate(
    scenarios: list, batch: int = BARE_CORE_BATCH, steps: int = BARE_CORE_STEPS, rounds: int = 3
) -> float:
    """Agent steps/s of ``sim.core.step`` over ``batch`` scenes (the ``scenarios`` cycled),
    every agent replayed from the log: the anchor of the benches' ratios (median of rounds)."""
    from tbsim_env.sim import core
    from tbsim_env.sim.build import build_sim_state

    with torch.inference_mode():
        state0 = build_sim_state([scenarios[i % len(scenarios)] for i in range(batch)])
        action = torch.zeros(*state0.pose.shape[:2], 2)
        agents = int(state0.agents.mask.sum())

        def episode() -> None:
            state = state0
            for _ in range(steps):
                state = core.step(state, action)

        return agents * steps / _median_time(episode, rounds, 1)


def measure(scenarios: list | None = None, threads: int = 1) -> Machine:
    """The ``Machine`` now: its probes run on one thread (restored afterwards); the bare core
    on ``scenarios`` (the bench's; None: the embedded generated scenes)."""
    if scenarios is None:
        from tbsim_env.data.generator import default_scenarios

        scenarios = default_scenarios(8)
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        load = os.getloadavg()[0] if hasattr(os, "getloadavg") else 0.0
        return Machine(
            cpu=cpu_model(),
            cores=os.cpu_count() or 0,
            threads=threads,
            load=load,
            tiny_op_us=tiny_op_us(),
            matmul_gflops=matmul_gflops(),
            copy_gbs=copy_gbs(),
            core_rate=bare_core_rate(scenarios),
        )
    finally:
        torch.set_num_threads(before)


if __name__ == "__main__":
    print(measure().line())
