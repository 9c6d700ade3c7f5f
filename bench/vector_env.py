"""Throughput of ``BatchedTrafficEnv``: controlled-agent steps per second at several batch sizes.

Each measurement steps B scenario slots with zero actions for a fixed number of batched
steps (autoreset included: finished slots restart from the scenario bank), full observations
and metrics, and reports agent steps/s = (active controlled agents summed over steps) / s and
batched env steps/s. Scenarios are the real WOMD samples when found, else the embedded
generated scenes.

    python bench/vector_env.py [--npc-policy log_replay constant_velocity idm] \
        [--batch-sizes 1 16 64] [--controlled sdc] [--steps 200] [--threads N] [--device cpu]
    python bench/vector_env.py --npc-policy trafficbots [--npc-checkpoint PATH]
    python bench/vector_env.py --npc-policy log_replay idm --batch-sizes 64 --obs-layout dense

With ``trafficbots`` it also measures the policy on the padded token limits (``trim=False``)
and prints the speed-up of running on the rows the scenario bank uses. Each row also gives
the observation bytes per agent step of its layout (``--obs-layout dense indexed``), and the
ratio of its batched steps/s to the first row of the same policy and B ("x first") and of its
agent steps/s to the first policy's row of the same B and layout ("x 1st policy": e.g. ``idm``
against ``log_replay``, measured in the same run). ``--stages`` adds,
under each eager row, the share of the step spent per stage (NPC policy, dynamics, collision,
off-road, the rest of the metrics, rewards, history, observations, densify, autoreset, glue).

The first line names the machine (``bench/machine.py``: CPU, versions, threads, the cost of a
tiny operation, matmul GFLOP/s, copy GB/s, log replay's bare core, measured in this run); each
row gives its agent steps/s against that bare core ("x core") and the ATen operations of one
eager batched step ("ops/step", a profiler count: the same on every machine).
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import measure  # noqa: E402
from stages import format_split, stage_times  # noqa: E402

from tbsim_env.core.torch_utils import aten_op_count  # noqa: E402
from tbsim_env.env.vector_env import BatchedTrafficEnv  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "womd"


def load(source: str, data: str) -> tuple[list, str]:
    """Scenarios for the benchmark and a label."""
    if source in ("auto", "womd"):
        from tbsim_env.data import load_scenarios

        wod = Path(data) / "waymo-open-dataset"
        files = [wod / "motion_data_one_scenario.tfrecord", wod / "womd_scenario_input.tfrecord"]
        found = [f for f in files if f.exists()]
        if found:
            scenarios = [s for f in found for s in load_scenarios(f)]
            return scenarios, f"real WOMD ({len(scenarios)} scenarios)"
        if source == "womd":
            raise SystemExit(f"no WOMD samples under {wod}")
    from tbsim_env.data.generator import default_scenarios

    return default_scenarios(8), "generated scenes (8)"


@dataclass(frozen=True)
class Case:
    """One measurement: the env's settings and how long to run."""

    batch: int
    npc_policy: str
    controlled: str
    steps: int
    device: str
    threads: int
    npc_kwargs: dict | None = None
    obs_layout: str = "dense"
    compile: bool = False


@dataclass(frozen=True)
class Result:
    """One measurement's figures.

    Attributes:
        agent_rate: active controlled-agent steps per second.
        env_rate: batched steps per second.
        obs_bytes: observation bytes per agent step.
        ops: ATen operations per batched step (0 for a compiled step: one graph).
        split: the stage split ("" unless asked for).
    """

    agent_rate: float
    env_rate: float
    obs_bytes: float
    ops: float
    split: str


def bench(scenarios: list, case: Case, stages: bool = False) -> Result:
    """The figures of ``case.steps`` batched steps after a warm-up; the split ("" unless
    ``stages``) and the operation count are measured in further runs (the timers and the
    profiler cost time of their own)."""
    env = BatchedTrafficEnv(
        scenarios,
        case.batch,
        controlled=case.controlled,
        npc_policy=case.npc_policy,
        npc_kwargs=case.npc_kwargs,
        device=case.device,
        seed=0,
        torch_threads=case.threads,
        obs_layout=case.obs_layout,
        compile="always" if case.compile else False,  # the graph itself, at every B
    )
    obs, _ = env.reset(seed=0)
    obs_bytes = sum(v.numel() * v.element_size() for v in obs.values()) / max(
        1, int(env.agent_mask.sum())
    )
    zeros = torch.zeros(case.batch, env.num_agents, 2, device=env.device)
    for _ in range(5):
        env.step(zeros)
    agent_steps, dt = _run(env, zeros, case.steps)
    split = ""
    if stages and not case.compile:
        totals: dict[str, float] = {}
        with stage_times(totals):
            _, wall = _run(env, zeros, case.steps)
        split = format_split(totals, wall)
    ops = 0.0 if case.compile else aten_op_count(lambda: env.step(zeros), 10)
    return Result(agent_steps / dt, case.steps / dt, obs_bytes, ops, split)


def _run(env: BatchedTrafficEnv, actions: torch.Tensor, steps: int) -> tuple[int, float]:
    """(active agent steps, seconds) of ``steps`` batched steps."""
    agent_steps = 0
    if env.device.type == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    for _ in range(steps):
        agent_steps += int(env.agent_mask.sum())
        env.step(actions)
    if env.device.type == "cuda":
        torch.cuda.synchronize()
    return agent_steps, time.perf_counter() - start


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", default=os.environ.get("TBSIM_WOMD_DIR", DEFAULT_DATA))
    p.add_argument("--scenarios", choices=["auto", "womd", "generated"], default="auto")
    p.add_argument(
        "--npc-policy",
        nargs="+",
        default=["log_replay", "constant_velocity", "idm"],
        help="registered NPC policy names",
    )
    p.add_argument("--npc-checkpoint", default=None, help="TrafficBots checkpoint (optional)")
    p.add_argument("--batch-sizes", type=int, nargs="+", default=[1, 16, 64])
    p.add_argument("--controlled", default="sdc", help="sdc | tracks_to_predict | all")
    p.add_argument("--steps", type=int, default=200, help="batched steps per measurement")
    p.add_argument("--threads", type=int, default=1, help="torch intra-op threads of the env")
    p.add_argument("--device", default="cpu")
    p.add_argument(
        "--obs-layout",
        nargs="+",
        choices=["dense", "indexed"],
        default=["dense", "indexed"],
        help="observation layouts to measure (ratio printed against the first)",
    )
    p.add_argument(
        "--compile",
        action="store_true",
        help="also measure each layout with the compiled graph (compile='always': at every B, "
        "also where compile=True would step eagerly)",
    )
    p.add_argument(
        "--stages",
        action="store_true",
        help="also print each eager row's time split per stage (bench/stages.py)",
    )
    args = p.parse_args()
    scenarios, label = load(args.scenarios, str(args.data))
    machine = measure(scenarios, args.threads)
    print(machine.line())
    print(f"device {args.device}, controlled={args.controlled}, scenarios: {label}")
    print(
        f"{'npc policy':<20} {'obs':<8} {'B':>4} {'agent steps/s':>14} {'x core':>8} "
        f"{'env steps/s':>12} {'ops/step':>9} {'obs B/agent':>12} {'x first':>8} "
        f"{'x 1st policy':>13}"
    )
    base: dict[tuple[int, str], float] = {}  # the first policy's agent steps/s per (B, layout)
    for policy in args.npc_policy:
        kwargs = {"checkpoint": args.npc_checkpoint} if args.npc_checkpoint else {}
        # TrafficBots runs on the token rows the bank uses; its padded run is the reference.
        variants = [(policy, kwargs, layout, False) for layout in args.obs_layout]
        if args.compile:
            variants += [(f"{policy} (compiled)", kwargs, lay, True) for lay in args.obs_layout]
        if policy == "trafficbots":
            variants.append(("trafficbots (padded)", {**kwargs, "trim": False}, "dense", False))
        try:
            for b in args.batch_sizes:
                rates = []
                for label, kw, layout, compiled in variants:
                    case = Case(
                        b,
                        policy,
                        args.controlled,
                        args.steps,
                        args.device,
                        args.threads,
                        kw,
                        layout,
                        compiled,
                    )
                    r = bench(scenarios, case, args.stages)
                    rates.append(r.env_rate)
                    ratio = f"{r.env_rate / rates[0]:>8.2f}" if len(rates) > 1 else " " * 8
                    ops = f"{r.ops:>9,.0f}" if r.ops else f"{'graph':>9}"
                    first = base.setdefault((b, layout), r.agent_rate)
                    print(
                        f"{label:<20} {layout:<8} {b:>4} {r.agent_rate:>14,.0f} "
                        f"{r.agent_rate / machine.core_rate:>8.4f} {r.env_rate:>12,.1f} "
                        f"{ops} {r.obs_bytes:>12,.0f} {ratio} {r.agent_rate / first:>13.2f}",
                        flush=True,
                    )
                    if r.split:
                        print(f"    stages: {r.split}", flush=True)
        except FileNotFoundError as e:  # e.g. TrafficBots without weights: the next policy
            print(f"{policy:<20} skipped: {e}")


if __name__ == "__main__":
    main()
