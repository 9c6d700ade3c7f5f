"""TrafficBots V1.5 closed-loop step cost.

For a config (``paper`` by default) on a real WOMD scenario (or a generated one without data),
prints milliseconds per closed-loop step for 1 rollout and for R rollouts batched, the FLOPs of
one step (counted by ``torch.utils.flop_counter``: matrix products, the bulk of the work), the
achieved GFLOP/s, and a dense float32 matmul GFLOP/s measured in the same run as the machine's
reference. Target on CPU: at least 30% of that reference.

The policy runs on the scene's used rows (``TokenBatch.trim``, as ``sample_rollouts`` and the
``TrafficEnv``'s NPC policy do). Each figure is also measured, in the same run, (a) on the batch
padded to the token limits (64 agents, 1024 map pieces, 128 TL tokens), as the policy ran
before it trimmed, and (b) with the attention computed in the spec's order
(``knarpe_reference``: gather the neighbours, then project every pair), the formulation this
package used before the factored ``KnarpeAttention``; the speed-ups are the ratios. The
factored form does far fewer FLOPs, so compare milliseconds, not efficiencies.

    python bench/policy_step.py [--config paper|small] [--rollouts 32] [--threads N]
"""

from __future__ import annotations

import argparse
import contextlib
import os
import sys
import time
from collections.abc import Iterator
from contextlib import nullcontext
from pathlib import Path
from unittest import mock

import torch
from torch.utils.flop_counter import FlopCounterMode

from policies.trafficbots import TokenBatch, TrafficBots, TrafficBotsConfig
from policies.trafficbots.attention import KnarpeAttention, knarpe_reference
from tbsim_env.data.preprocess import preprocess_scenario

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import matmul_gflops, measure  # noqa: E402

DEFAULT_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "womd"


def step_cost(model: TrafficBots, batch: TokenBatch, rollouts: int, steps: int):
    """(seconds per step, FLOPs per step) of ``model.step`` with ``rollouts`` rollouts."""
    gen = torch.Generator().manual_seed(0)
    with torch.no_grad():
        ctx = model.prepare(batch, rollouts, gen)
        state = model.initial_state(ctx)
        t = model.cfg.n_history - 1
        pose = batch.ag_pose[:, :, t].repeat_interleave(rollouts, 0)
        speed = batch.ag_motion[:, :, t, 0].repeat_interleave(rollouts, 0)
        valid = batch.ag_valid[:, :, t].repeat_interleave(rollouts, 0)
        tl = batch.tl_state[:, :, t].repeat_interleave(rollouts, 0)
        for _ in range(model.cfg.n_history):  # fill the history window
            _, state = model.step(ctx, state, pose, speed, valid, tl)
        counter = FlopCounterMode(display=False)
        with counter:
            model.step(ctx, state, pose, speed, valid, tl)
        flops = counter.get_total_flops()
        t0 = time.perf_counter()
        for _ in range(steps):
            _, state = model.step(ctx, state, pose, speed, valid, tl)
        return (time.perf_counter() - t0) / steps, flops


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--config", default="paper", choices=("paper", "small"))
    p.add_argument("--rollouts", type=int, default=32)
    p.add_argument("--steps", type=int, default=3)
    p.add_argument("--threads", type=int, default=torch.get_num_threads())
    p.add_argument("--data", default=os.environ.get("TBSIM_WOMD_DIR", DEFAULT_DATA))
    args = p.parse_args()
    torch.set_num_threads(args.threads)
    path = Path(args.data) / "waymo-open-dataset" / "motion_data_one_scenario.tfrecord"
    if path.exists():
        from tbsim_env.data import load_scenarios

        scenario, label = load_scenarios(path)[0], f"real {path.name}"
    else:
        from tbsim_env.data.generator import generate_scenario

        scenario, label = generate_scenario("intersection", 0), "generated intersection"
    tokens = preprocess_scenario(scenario)
    batch = TokenBatch.from_tokens(tokens)
    cfg = TrafficBotsConfig.paper() if args.config == "paper" else TrafficBotsConfig.small()
    model = TrafficBots(cfg).eval()
    n_ag = int(batch.ag_valid.any(-1).sum())
    n_mp = int(batch.mp_valid[..., 0].sum())
    n_tl = int((batch.tl_piece >= 0).sum())
    print(measure([scenario], args.threads).line())
    print(
        f"{label}: {n_ag} agents, "
        f"{n_mp} map pieces, {n_tl} TL tokens (padded to {batch.ag_type.shape[1]}, "
        f"{batch.mp_cls.shape[1]}, {batch.tl_piece.shape[1]}); config {args.config} "
        f"({model.num_parameters():,} parameters)"
    )
    ref = matmul_gflops(1024)
    print(f"reference dense fp32 matmul (1024^3, {args.threads} threads): {ref:8.1f} GFLOP/s")
    trimmed = batch.trim()
    runs = (
        ("factored", trimmed, nullcontext),
        ("padded", batch, nullcontext),
        ("spec order", trimmed, _spec_order),
    )
    for r in (1, args.rollouts):
        secs = []
        for label, run_batch, ctx in runs:
            with ctx():
                sec, flops = step_cost(model, run_batch, r, args.steps)
            secs.append(sec)
            achieved = flops / sec / 1e9
            print(
                f"{r:3d} rollout(s), {label:10s}: {sec * 1e3:9.1f} ms/step, "
                f"{flops / 1e9:7.2f} GFLOP/step, {achieved:6.1f} GFLOP/s = "
                f"{100 * achieved / ref:5.1f}% of the matmul reference (target >= 30%)"
            )
        print(
            f"{r:3d} rollout(s): trimming the padding is {secs[1] / secs[0]:.2f}x faster per "
            f"step, the factored attention {secs[2] / secs[0]:.2f}x"
        )


@contextlib.contextmanager
def _spec_order() -> Iterator[None]:
    """Every KNARPE attention in the spec's order while open: the source rows are not
    projected ahead (``project_source`` passes them through) and ``attend`` gathers, then
    projects each pair."""

    def attend(self, x, src, idx, rpe, mask, dense=None):
        return knarpe_reference(self, x, src, idx, rpe, mask)

    with (
        mock.patch.object(KnarpeAttention, "project_source", lambda _, s: s),
        mock.patch.object(KnarpeAttention, "attend", attend),
    ):
        yield


if __name__ == "__main__":
    main()
