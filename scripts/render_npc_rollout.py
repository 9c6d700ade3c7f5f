"""Picture of a closed-loop rollout with TrafficBots NPCs (for docs/MODEL_CARD.md), or with
another registered NPC policy (``--npc-policy idm`` for docs/idm.md).

Draws the scene at a few times side by side, with 2 s trails.

    python scripts/render_npc_rollout.py --out docs/model_card/rollout.png [--checkpoint P]
    python scripts/render_npc_rollout.py --npc-policy idm --out docs/idm_rollout.png
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from tbsim_env.core.config import EnvConfig, TerminationConfig
from tbsim_env.data import load_scenarios
from tbsim_env.data.generator import generate_scenario
from tbsim_env.env import TrafficEnv
from tbsim_env.rendering import AgentGroup, MapLayer, render_state, view_for


def frames_of(
    scenario, checkpoint: str | None, times: tuple[int, ...], npc_policy: str = "trafficbots"
) -> list[np.ndarray]:
    never = EnvConfig(termination=TerminationConfig(collision=False, goal=False))
    env = TrafficEnv([scenario], npc_policy=npc_policy, npc_checkpoint=checkpoint, config=never)
    env.reset(seed=0)
    layer = MapLayer.build(scenario, view_for(scenario, size=(420, 420)))
    groups = np.full(env.sim_state.num_agents, int(AgentGroup.POLICY), np.int64)
    groups[env.episode.setup.external[0].numpy()] = int(AgentGroup.EXTERNAL)
    out, trail = [], []
    a = env.agents[0]
    for step in range(1, max(times) + 1):
        env.step({a: env.expert_actions()[a]})
        s = env.sim_state
        trail.append((s.pose[0, :, :2].numpy() + s.origin[0].numpy(), s.valid[0].numpy()))
        if step in times:
            tr = np.stack([p for p, _ in trail[-20:]], axis=1)
            tv = np.stack([v for _, v in trail[-20:]], axis=1)
            title = f"{scenario.scenario_id}  t = {1.0 + 0.1 * step:.1f} s"
            out.append(render_state(layer, s, 0, groups, trails=(tr, tv), title=title))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default="docs/model_card/rollout.png")
    p.add_argument("--checkpoint", default=None)
    p.add_argument("--npc-policy", default="trafficbots", help="a registered policy name")
    p.add_argument("--data", default=os.environ.get("TBSIM_WOMD_DIR", "../shared/data/womd"))
    args = p.parse_args()
    torch.set_num_threads(1)
    real = load_scenarios(Path(args.data) / "waymo-open-dataset/motion_data_one_scenario.tfrecord")
    rows = []
    for sc in (generate_scenario("intersection", 10000), real[0]):
        frames = frames_of(sc, args.checkpoint, (20, 50, 80), args.npc_policy)
        rows.append(np.concatenate(frames, axis=1))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.concatenate(rows, axis=0)).save(args.out)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
