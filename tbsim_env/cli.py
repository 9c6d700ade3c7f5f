"""``tbsim`` command line: demo, info, render.

Examples::

    tbsim demo --out demo.mp4                 # embedded generated scenes, no data needed
    tbsim info path/to/shard.tfrecord         # one line per scenario
    tbsim render shard.tfrecord --scenario 637f20cafde22ff8 --out x.mp4
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from tqdm import tqdm

from tbsim_env import constants as C
from tbsim_env.errors import TbsimError


def _cmd_info(args: argparse.Namespace) -> int:
    from tbsim_env.data import iter_scenarios

    head = ("scenario_id", "tracks", "veh/ped/cyc", "map", "signals", "sdc_id")
    print(f"{head[0]:<20} {head[1]:>6} {head[2]:>12} {head[3]:>5} {head[4]:>7} {head[5]:>7}")
    for sc in iter_scenarios(args.files, skip_bad=args.skip_bad):
        t = sc.tracks.object_type
        kinds = "/".join(
            str(int((t == k).sum()))
            for k in (C.ObjectType.VEHICLE, C.ObjectType.PEDESTRIAN, C.ObjectType.CYCLIST)
        )
        print(
            f"{sc.scenario_id:<20} {sc.tracks.num_tracks:>6} {kinds:>12} "
            f"{sc.road_map.num_features:>5} {sc.signals.num_signals:>7} {sc.sdc_id:>7}"
        )
    return 0


def _episode_video(env, out: Path, fps: int, steps: int | None, desc: str) -> int:
    from tbsim_env.rendering import write_video

    env.reset()
    frames = [env.render()]
    n = steps or (env.scenario.num_steps - 1 - env.config.start_step)
    for _ in tqdm(range(n), desc=desc, unit="step"):
        if not env.agents:
            break
        env.step(env.expert_actions())
        frames.append(env.render())
    return write_video(frames, out, fps=fps)


def _cmd_demo(args: argparse.Namespace) -> int:
    from tbsim_env.env import TrafficEnv

    env = TrafficEnv(
        None,
        controlled="sdc",
        npc_policy=args.npc_policy,
        render_mode="rgb_array",
        scenario_order="cycle",
    )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    stem, suffix = out.with_suffix(""), out.suffix or ".mp4"
    for k in range(min(args.scenarios, len(env.scenarios))):
        env._episode = k - 1  # cycle to scenario k on the next reset
        path = out if args.scenarios == 1 else Path(f"{stem}_{k}{suffix}")
        n = _episode_video(env, path, args.fps, args.steps, f"demo {env.scenarios[k].scenario_id}")
        print(
            f"wrote {path} ({n} frames): SDC follows its log via expert actions, "
            f"NPCs: {args.npc_policy}"
        )
    return 0


def _cmd_render(args: argparse.Namespace) -> int:
    from tbsim_env.data import load_scenarios
    from tbsim_env.env import TrafficEnv

    scenarios = load_scenarios(args.file)
    if args.scenario is not None:
        scenarios = [s for s in scenarios if s.scenario_id == args.scenario]
        if not scenarios:
            print(f"error: no scenario {args.scenario!r} in {args.file}", file=sys.stderr)
            return 2
    env = TrafficEnv(
        scenarios[:1], controlled="sdc", npc_policy=args.npc_policy, render_mode="rgb_array"
    )
    n = _episode_video(env, Path(args.out), args.fps, None, f"render {scenarios[0].scenario_id}")
    print(f"wrote {args.out} ({n} frames)")
    return 0


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="tbsim", description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="command", required=True)

    d = sub.add_parser("demo", help="simulate the embedded generated scenes and write a video")
    d.add_argument("--out", default="tbsim_demo.mp4", help="video path (.mp4 or .gif)")
    d.add_argument("--scenarios", type=int, default=1, help="how many default scenes to render")
    d.add_argument("--npc-policy", default="log_replay", help="NPC policy name")
    d.add_argument("--steps", type=int, default=None, help="steps to simulate (default: all)")
    d.add_argument("--fps", type=int, default=10)
    d.set_defaults(func=_cmd_demo)

    i = sub.add_parser("info", help="one line per scenario of TFRecord / GPUDrive JSON files")
    i.add_argument("files", nargs="+")
    i.add_argument("--skip-bad", action="store_true", help="warn and skip corrupt records")
    i.set_defaults(func=_cmd_info)

    r = sub.add_parser("render", help="simulate one scenario and write a video")
    r.add_argument("file")
    r.add_argument("--scenario", default=None, help="scenario id (default: the first)")
    r.add_argument("--out", required=True)
    r.add_argument("--npc-policy", default="log_replay")
    r.add_argument("--fps", type=int, default=10)
    r.set_defaults(func=_cmd_render)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    np.set_printoptions(precision=3)
    try:
        return int(args.func(args) or 0)
    except (TbsimError, FileNotFoundError, ValueError) as err:
        print(f"tbsim {args.command}: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
