"""Throughput of ``BatchedTrafficEnv``: controlled-agent steps per second at several batch sizes.

Each measurement steps B scenario slots with zero actions (``--actions random``: actions
drawn at random, acceleration ~ N(0, 4 m/s^2) and yaw rate ~ N(0, 0.6 rad/s), clipped by the
env, the same draws for every row of a round: controlled agents then crash and leave the
road, and their episodes end and restart early, as with a learner at the start of training)
for a fixed number of batched steps (autoreset included: finished slots restart from the
scenario bank), full observations and metrics, and reports agent steps/s = (active
controlled agents summed over steps) / s and batched env steps/s. The rows of one B are
timed in interleaved rounds (``--rounds``, each rate the median over rounds), so that a
machine whose speed drifts between runs (a shared one) slows every row alike and the ratios
between rows hold. Scenarios are the real WOMD samples when found, else the embedded
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
against ``log_replay``, measured in the same rounds). ``--stages`` adds,
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
import statistics
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
    actions: str = "zero"


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


def make_env(scenarios: list, case: Case) -> tuple[BatchedTrafficEnv, float]:
    """The case's environment, reset and warmed up (5 steps), and the observation bytes per
    agent step of its first observation."""
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
    for _ in range(5):
        env.step(_zeros(env))
    return env, obs_bytes


def bench(
    envs: list[tuple[BatchedTrafficEnv, float]], cases: list[Case], rounds: int, stages: bool
) -> list:
    """The figures of every case (``envs``: ``make_env``'s (env, observation bytes) of each):
    ``rounds`` rounds that each time ``case.steps`` batched steps of every env in turn (the
    rates are the medians over rounds, so that a machine whose speed drifts slows every case
    alike); the split ("" unless ``stages``) and the operation count are measured in further
    runs (the timers and the profiler cost time of their own)."""
    timed: list[list[tuple[int, float]]] = [[] for _ in envs]
    for r in range(rounds):
        for k, ((env, _), case) in enumerate(zip(envs, cases)):
            timed[k].append(_run(env, _actions(env, case, seed=r), case.steps))
    results = []
    for (env, obs_bytes), case, runs in zip(envs, cases, timed):
        agent_rate = statistics.median(a / dt for a, dt in runs)
        env_rate = statistics.median(case.steps / dt for _, dt in runs)
        split = ""
        if stages and not case.compile:
            totals: dict[str, float] = {}
            with stage_times(totals):
                _, wall = _run(env, _actions(env, case, seed=rounds), case.steps)
            split = format_split(totals, wall)
        ops = 0.0 if case.compile else aten_op_count(lambda e=env: e.step(_zeros(e)), 10)
        results.append(Result(agent_rate, env_rate, obs_bytes, ops, split))
    return results


def _zeros(env: BatchedTrafficEnv) -> torch.Tensor:
    """[B, N, 2] zero actions of ``env``."""
    return torch.zeros(env.batch_size, env.num_agents, 2, device=env.device)


ACTION_SCALE = (4.0, 0.6)
"""Standard deviations of ``--actions random``: acceleration m/s^2, yaw rate rad/s."""


def _actions(env: BatchedTrafficEnv, case: Case, seed: int) -> list[torch.Tensor]:
    """``case.steps`` [B, Q, 2] actions: zeros, or (``case.actions == "random"``) normal draws
    scaled by ``ACTION_SCALE``, from ``seed`` (the same for every row of a round)."""
    if case.actions != "random":
        return [_zeros(env)] * case.steps
    g = torch.Generator().manual_seed(seed)
    scale = torch.tensor(ACTION_SCALE)
    shape = (env.batch_size, env.num_agents, 2)
    return [(torch.randn(shape, generator=g) * scale).to(env.device) for _ in range(case.steps)]


def _run(env: BatchedTrafficEnv, actions: list[torch.Tensor], steps: int) -> tuple[int, float]:
    """(active agent steps, seconds) of ``steps`` batched steps with ``actions`` [steps]."""
    agent_steps = 0
    if env.device.type == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    for a in actions[:steps]:
        agent_steps += int(env.agent_mask.sum())
        env.step(a)
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
    p.add_argument("--steps", type=int, default=200, help="batched steps per round")
    p.add_argument(
        "--rounds",
        type=int,
        default=3,
        help="interleaved rounds of every row at a B (each rate: the median over rounds)",
    )
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
        "--actions",
        choices=["zero", "random"],
        default="zero",
        help="controlled agents' actions: zero, or random draws (early episode ends, restarts)",
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
    print(
        f"device {args.device}, controlled={args.controlled}, actions {args.actions}, "
        f"scenarios: {label}"
    )
    print(
        f"{'npc policy':<20} {'obs':<8} {'B':>4} {'agent steps/s':>14} {'x core':>8} "
        f"{'env steps/s':>12} {'ops/step':>9} {'obs B/agent':>12} {'x first':>8} "
        f"{'x 1st policy':>13}"
    )
    for b in args.batch_sizes:
        rows, cases, envs = [], [], []
        for policy in args.npc_policy:
            for label, kw, layout, compiled in _variants(policy, args):
                fields = (args.controlled, args.steps, args.device, args.threads, kw)
                case = Case(b, policy, *fields, layout, compiled, args.actions)
                try:
                    envs.append(make_env(scenarios, case))
                except FileNotFoundError as e:  # e.g. TrafficBots without weights
                    print(f"{label:<20} skipped: {e}")
                    break
                rows.append(label)
                cases.append(case)
        results = bench(envs, cases, args.rounds, args.stages)
        del envs
        _print_rows(rows, cases, results, machine.core_rate)


def _variants(policy: str, args: argparse.Namespace) -> list[tuple[str, dict, str, bool]]:
    """(row label, NPC keyword arguments, layout, compiled) of each row of ``policy``."""
    kwargs = {"checkpoint": args.npc_checkpoint} if args.npc_checkpoint else {}
    # TrafficBots runs on the token rows the bank uses; its padded run is the reference.
    variants = [(policy, kwargs, layout, False) for layout in args.obs_layout]
    if args.compile:
        variants += [(f"{policy} (compiled)", kwargs, lay, True) for lay in args.obs_layout]
    if policy == "trafficbots":
        variants.append(("trafficbots (padded)", {**kwargs, "trim": False}, "dense", False))
    return variants


def _print_rows(rows: list[str], cases: list[Case], results: list[Result], core: float) -> None:
    """One line per measurement: "x first" against the policy's first row, "x 1st policy"
    against the first policy's row of the same layout."""
    first_env: dict[str, float] = {}
    first_agent: dict[str, float] = {}
    for label, case, r in zip(rows, cases, results):
        later = case.npc_policy in first_env
        own = first_env.setdefault(case.npc_policy, r.env_rate)
        ratio = f"{r.env_rate / own:>8.2f}" if later else " " * 8
        ops = f"{r.ops:>9,.0f}" if r.ops else f"{'graph':>9}"
        first = first_agent.setdefault(case.obs_layout, r.agent_rate)
        print(
            f"{label:<20} {case.obs_layout:<8} {case.batch:>4} {r.agent_rate:>14,.0f} "
            f"{r.agent_rate / core:>8.4f} {r.env_rate:>12,.1f} "
            f"{ops} {r.obs_bytes:>12,.0f} {ratio} {r.agent_rate / first:>13.2f}",
            flush=True,
        )
        if r.split:
            print(f"    stages: {r.split}", flush=True)


if __name__ == "__main__":
    main()
