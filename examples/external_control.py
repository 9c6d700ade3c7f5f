"""External control: a script takes over selected agents mid-episode while NPCs drive on.

The controlled agents (the SDC by default) follow their expert (log-following) actions until
``--takeover-s`` seconds, then the script takes over: ``brake`` (full braking, straight),
``swerve`` (keep speed, steer left) or ``accelerate``. Every other agent is an NPC of
``--npc-policy`` (``log_replay`` and ``constant_velocity`` do not react to the ego; a
reactive policy such as ``trafficbots`` can be named once it is registered). The episode is
written as a video and a per-second summary is printed.

    python examples/external_control.py --out external_control.mp4
    python examples/external_control.py --scenario $TBSIM_WOMD_DIR/waymo-open-dataset/\
motion_data_one_scenario.tfrecord --controlled tracks_to_predict --npc-policy log_replay
"""

from __future__ import annotations

import argparse

import numpy as np

from tbsim_env.core import constants as C
from tbsim_env.env import TrafficEnv
from tbsim_env.rendering import write_video

MANOEUVRES = ("brake", "swerve", "accelerate")


def scripted_action(manoeuvre: str, action_high: np.ndarray, speed: float) -> np.ndarray:
    """The takeover action (acceleration m/s^2, yaw rate rad/s) of a manoeuvre.

    Args:
        manoeuvre: one of ``MANOEUVRES``.
        action_high: [2] the agent's action limits.
        speed: m/s, the agent's current signed speed (braking stops at 0, never reverses).
    """
    acc, yaw = float(action_high[0]), float(action_high[1])
    if manoeuvre == "brake":
        return np.array([-np.clip(speed / C.DT, -acc, acc), 0.0], np.float32)
    if manoeuvre == "swerve":
        return np.array([0.0, 0.3 * yaw], np.float32)
    if manoeuvre == "accelerate":
        return np.array([acc, 0.0], np.float32)
    raise ValueError(f"unknown manoeuvre {manoeuvre!r}; choose from {MANOEUVRES}")


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--scenario", default=None, help="WOMD file (default: embedded scenes)")
    p.add_argument("--scenario-index", type=int, default=0, help="which scenario of the file")
    p.add_argument("--controlled", default="sdc", help="sdc | tracks_to_predict | all | ids")
    p.add_argument("--npc-policy", default="constant_velocity", help="e.g. log_replay")
    p.add_argument("--npc-checkpoint", default=None, help="TrafficBots checkpoint")
    p.add_argument("--takeover-s", type=float, default=3.0, help="seconds of expert driving")
    p.add_argument("--manoeuvre", choices=MANOEUVRES, default="brake")
    p.add_argument("--max-steps", type=int, default=80, help="steps to simulate (0.1 s each)")
    p.add_argument("--out", default="external_control.mp4", help="MP4 or GIF path")
    args = p.parse_args()

    controlled: str | list[int] = args.controlled
    if args.controlled not in ("sdc", "tracks_to_predict", "all"):
        controlled = [int(t) for t in args.controlled.split(",")]
    env = TrafficEnv(
        args.scenario,
        controlled=controlled,
        npc_policy=args.npc_policy,
        npc_checkpoint=args.npc_checkpoint,
        render_mode="rgb_array",
    )
    _, infos = env.reset(seed=0, options={"scenario_index": args.scenario_index})
    speed = {a: float(info["speed"]) for a, info in infos.items()}
    print(
        f"scenario {env.scenario.scenario_id}: controlling {env.agents} "
        f"({args.manoeuvre} after {args.takeover_s:.1f} s), NPCs: {args.npc_policy}"
    )
    takeover_step = round(args.takeover_s / C.DT)
    frames = [env.render()]
    events: list[str] = []
    step = 0
    while env.agents and step < args.max_steps:
        mode = "expert" if step < takeover_step else args.manoeuvre
        if mode == "expert":
            actions = env.expert_actions()
        else:
            actions = {
                a: scripted_action(args.manoeuvre, env.action_space(a).high, speed[a])
                for a in env.agents
            }
        _, rewards, terms, truncs, infos = env.step(actions)
        step += 1
        frames.append(env.render())
        speed.update({a: float(info["speed"]) for a, info in infos.items()})
        for a, info in infos.items():
            if info["collision"]:
                events.append(f"t={step * C.DT:.1f}s {a} collided")
            if info["goal_reached"] and terms[a]:
                events.append(f"t={step * C.DT:.1f}s {a} reached its goal")
        if step == 1 or step % 10 == 0 or step == takeover_step + 1:
            speeds = ", ".join(f"{a} {infos[a]['speed']:.1f} m/s" for a in infos)
            print(f"t={step * C.DT:4.1f}s [{mode:>10}] {speeds}")
    write_video(frames, args.out, fps=10)
    print("\n".join(events) if events else "no collision, no goal reached")
    print(f"wrote {len(frames)} frames to {args.out}")


if __name__ == "__main__":
    main()
