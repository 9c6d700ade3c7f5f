"""The IDM controller as a baseline planner: a script drives the SDC with ``policies.idm``.

The SDC is an externally controlled agent of ``TrafficEnv``; every step the script asks an
``IDMPolicy`` (its own, apart from the env's NPC policy) for the action of the SDC's slot and
sends it as the SDC's action. The planner follows a lane route (``--route lanes``; ``log``:
the SDC's logged path), keeps its gap to whatever is ahead, stops for red lights, stop signs
and pedestrians on crosswalks. A per-second summary is printed, optionally a video written.

    python examples/idm_planner.py [--scenario FILE] [--npc-policy log_replay] [--out v.mp4]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from policies.idm import IDMPolicy
from tbsim_env.core import constants as C
from tbsim_env.env import TrafficEnv
from tbsim_env.rendering import write_video


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenario", default=None, help="WOMD file (default: embedded scenes)")
    p.add_argument("--scenario-index", type=int, default=0, help="which scenario of the file")
    p.add_argument("--route", choices=["lanes", "log"], default="lanes", help="planner's route")
    p.add_argument("--npc-policy", default="idm", help="the other agents: idm, log_replay, ...")
    p.add_argument("--max-steps", type=int, default=80, help="steps to simulate (0.1 s each)")
    p.add_argument("--out", default=None, help="MP4 or GIF path (default: no video)")
    args = p.parse_args()

    env = TrafficEnv(
        args.scenario,
        controlled="sdc",
        npc_policy=args.npc_policy,
        render_mode="rgb_array" if args.out else None,
    )
    env.reset(seed=0, options={"scenario_index": args.scenario_index})
    planner = IDMPolicy(route=args.route)
    generator = torch.Generator().manual_seed(0)
    plan = planner.initial_state(env.sim_state, [env.scenario], generator)
    (agent,) = env.agents
    slot = env.scenario.sdc_index  # agent slots follow the scenario's track order
    print(f"scenario {env.scenario.scenario_id}: IDM plans for {agent}, NPCs {args.npc_policy}")
    frames = [env.render()] if args.out else []
    step = 0
    while env.agents and step < args.max_steps:
        action, plan = planner.act(env.sim_state, plan, generator)
        sdc_action = action[0, slot].numpy().astype(np.float32)
        _, _, terms, _, infos = env.step({agent: sdc_action})
        step += 1
        if args.out:
            frames.append(env.render())
        info = infos[agent]
        if step % 10 == 0 or terms[agent]:
            print(
                f"t={step * C.DT:4.1f}s speed {info['speed']:5.2f} m/s  action "
                f"({sdc_action[0]:+.2f} m/s^2, {sdc_action[1]:+.3f} rad/s)"
                + ("  collided" if info["collision"] else "")
                + ("  goal reached" if info["goal_reached"] else "")
            )
    if args.out:
        write_video(frames, args.out, fps=10)
        print(f"wrote {len(frames)} frames to {args.out}")
    print(f"planned {step} steps")


if __name__ == "__main__":
    main()
