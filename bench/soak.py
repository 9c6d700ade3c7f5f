"""Soak: thousands of episodes in one process, random controlled agents among TrafficBots NPCs,
watching for leaks (resident memory), non-finite outputs and errors.

``BatchedTrafficEnv`` (same-step autoreset) over the real scenes of the shared data and the
embedded generated ones; the controlled agents (the SDC of each slot) act uniformly at random
within their limits; every other agent is a shipped TrafficBots NPC. Resident memory is read
from ``/proc/self/statm`` after each round of episodes; its growth is measured from the end
of the warm-up (the first tenth of the episodes), when caches and allocator pools are full.
Prints episodes, steps, resident memory (start of measure, end, growth) and the machine.

    python bench/soak.py [--episodes 10000] [--batch 32] [--data DIR]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

sys.path.insert(0, str(Path(__file__).resolve().parent))
from machine import measure  # noqa: E402

from tbsim_env.data import load_scenarios  # noqa: E402
from tbsim_env.data.generator import default_scenarios  # noqa: E402
from tbsim_env.env import BatchedTrafficEnv  # noqa: E402

REPO = Path(__file__).resolve().parents[1]


def resident_mb() -> float:
    """This process's resident memory, MB (Linux)."""
    with open("/proc/self/statm") as fh:
        pages = int(fh.read().split()[1])
    return pages * os.sysconf("SC_PAGE_SIZE") / 2**20


def scenes(data: Path) -> list:
    """The real scenes with a logged future of the shared folder's sample files plus the
    embedded generated scenes."""
    files = [
        data / "waymo-open-dataset" / "motion_data_one_scenario.tfrecord",
        data / "waymo-open-dataset" / "womd_scenario_input.tfrecord",
        *sorted((data / "gpudrive").glob("*.json")),
    ]
    real = [s for s in load_scenarios([f for f in files if f.exists()]) if s.has_future]
    return real + list(default_scenarios(8))


def finite(x) -> bool:
    if isinstance(x, torch.Tensor):
        return not x.is_floating_point() or bool(torch.isfinite(x).all())
    if isinstance(x, dict):
        return all(finite(v) for v in x.values())
    return True


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--episodes", type=int, default=10_000)
    p.add_argument("--batch", type=int, default=32)
    p.add_argument("--seed", type=int, default=0)
    default = os.environ.get("TBSIM_WOMD_DIR", str(REPO.parent / "shared" / "data" / "womd"))
    p.add_argument("--data", type=Path, default=Path(default))
    args = p.parse_args()
    torch.set_num_threads(1)
    env = BatchedTrafficEnv(scenes(args.data), args.batch, controlled="sdc",
                            npc_policy="trafficbots", seed=args.seed)  # fmt: skip
    rng = np.random.default_rng(args.seed)
    high = torch.from_numpy(env.action_high)
    env.reset(seed=args.seed)
    done_eps, steps, warm, mem0, bad = 0, 0, args.episodes // 10, None, 0
    t0 = time.perf_counter()
    bar = tqdm(total=args.episodes, unit="episode")
    while done_eps < args.episodes:
        u = rng.uniform(-1.0, 1.0, (args.batch, env.num_agents, 2)).astype(np.float32)
        obs, reward, term, trunc, info = env.step(torch.from_numpy(u) * high)
        steps += 1
        bad += not (finite(obs) and finite(reward))
        ended = int(info["done"].sum())
        done_eps += ended
        bar.update(ended)
        if mem0 is None and done_eps >= warm:
            mem0 = resident_mb()
    bar.close()
    wall = time.perf_counter() - t0
    mem1 = resident_mb()
    print(f"{done_eps} episodes, {steps} batched steps of {args.batch} in {wall:.0f} s; "
          f"non-finite steps {bad}")  # fmt: skip
    print(f"resident memory after warm-up {mem0:.0f} MB, at the end {mem1:.0f} MB, "
          f"growth {mem1 - mem0:+.1f} MB over {done_eps - warm} episodes")  # fmt: skip
    print(measure().line())
    sys.exit(1 if bad or mem1 - mem0 > 50 else 0)


if __name__ == "__main__":
    main()
