"""Render a real WOMD scenario to MP4: the logged scene, or a closed-loop simulation of it.

``--mode log`` draws the log itself (every track replayed, the SDC highlighted).
``--mode sim`` simulates the scenario in ``TrafficEnv``: the controlled agents follow their
expert actions, the other agents are NPCs of ``--npc-policy``; agents are coloured by
controller.

The default input is the WOMD sample ``motion_data_one_scenario.tfrecord`` under
``$TBSIM_WOMD_DIR`` (default ``../shared/data/womd``, beside the repository).

    python examples/render_video.py [PATH] --out scenario.mp4 [--mode sim]
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from tbsim_env.data import load_scenarios
from tbsim_env.env import TrafficEnv
from tbsim_env.rendering import render_log_video, write_video

REPO = Path(__file__).resolve().parents[1]


def default_path() -> Path:
    """The one-scenario WOMD sample under ``$TBSIM_WOMD_DIR``."""
    root = Path(os.environ.get("TBSIM_WOMD_DIR", REPO.parent / "shared" / "data" / "womd"))
    return root / "waymo-open-dataset" / "motion_data_one_scenario.tfrecord"


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("path", nargs="?", default=None, help="WOMD Scenario TFRecord (or folder)")
    p.add_argument("--scenario", default=None, help="scenario id (default: the first)")
    p.add_argument("--mode", choices=("log", "sim"), default="log")
    p.add_argument("--controlled", default="sdc", help="sim mode: sdc | tracks_to_predict | all")
    p.add_argument("--npc-policy", default="log_replay", help="sim mode: NPC policy")
    p.add_argument("--max-steps", type=int, default=80, help="sim mode: steps to simulate")
    p.add_argument("--out", default="scenario.mp4", help="MP4 or GIF path")
    args = p.parse_args()

    path = Path(args.path) if args.path else default_path()
    if not path.exists():
        raise SystemExit(f"{path} not found: pass a WOMD file or set TBSIM_WOMD_DIR")
    scenarios = load_scenarios(path)
    if args.scenario is not None:
        scenarios = [s for s in scenarios if s.scenario_id == args.scenario]
        if not scenarios:
            raise SystemExit(f"no scenario {args.scenario!r} in {path}")
    scenario = scenarios[0]
    print(
        f"scenario {scenario.scenario_id}: {scenario.tracks.num_tracks} tracks, "
        f"{scenario.num_steps} steps, SDC track {scenario.sdc_id}"
    )
    if args.mode == "log":
        out = render_log_video(scenario, args.out, progress=False)
        print(f"wrote the logged scenario to {out}")
        return
    env = TrafficEnv(
        [scenario],
        controlled=args.controlled,
        npc_policy=args.npc_policy,
        render_mode="rgb_array",
    )
    env.reset(seed=0)
    frames = [env.render()]
    steps = 0
    while env.agents and steps < args.max_steps:
        env.step(env.expert_actions())
        frames.append(env.render())
        steps += 1
    n = write_video(frames, args.out, fps=10)
    print(f"wrote {n} simulated frames to {args.out}")


if __name__ == "__main__":
    main()
