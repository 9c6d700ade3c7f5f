"""Does the NPC policy obey the traffic lights it sees? (docs/MODEL_CARD.md, yielding)

Runs ``TrafficEnv`` with TrafficBots NPCs (the SDC follows its log) on one generated scene three
times: with the logged lights, with every valid light forced to STOP and with every valid light
forced to GO, and prints how far the vehicles travel (mean over ``--seeds`` episodes). A policy
that ignores the lights gives the same figures in all three rows. ``--tracks`` also prints the
distance of each of those tracks in every episode.

    python scripts/tl_counterfactual.py intersection 10000 [--seeds 3] [--checkpoint P]
        [--tracks 320,326]
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np
import torch

from tbsim_env import constants as C
from tbsim_env.data.generator import generate_scenario
from tbsim_env.data.scenario import Scenario
from tbsim_env.env import TrafficEnv


def with_lights(sc: Scenario, state: C.SignalState | None) -> Scenario:
    """``sc`` with every valid signal state set to ``state`` (None: as logged)."""
    if state is None:
        return sc
    s = sc.signals
    forced = np.where(s.valid, np.int8(state), s.state).astype(np.int8)
    return dataclasses.replace(sc, signals=dataclasses.replace(s, state=forced))


def travel(sc: Scenario, seed: int, checkpoint: str | None) -> np.ndarray:
    """[N] metres each agent slot drives in one episode (the SDC follows its log)."""
    env = TrafficEnv([sc], controlled="sdc", npc_policy="trafficbots", npc_checkpoint=checkpoint)
    env.reset(seed=seed)
    prev = env.sim_state.pose[0, :, :2].clone()
    total = torch.zeros(prev.shape[0])
    while env.agents:
        env.step(env.expert_actions())
        cur = env.sim_state.pose[0, :, :2].clone()
        total += torch.linalg.vector_norm(cur - prev, dim=-1) * env.sim_state.valid[0]
        prev = cur
    return total.numpy()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("layout")
    p.add_argument("seed", type=int)
    p.add_argument("--seeds", type=int, default=3, help="episodes (policy seeds) per variant")
    p.add_argument("--checkpoint", default=None)
    p.add_argument("--tracks", default="", help="comma-separated track ids to list per episode")
    args = p.parse_args()
    torch.set_num_threads(1)
    sc = generate_scenario(args.layout, args.seed)
    vehicle = sc.tracks.object_type == int(C.ObjectType.VEHICLE)
    print("| lights | vehicles' mean travel (m) | median (m) | share under 2 m |")
    print("|---|---|---|---|")
    t = sc.tracks
    xy, ok = t.xyz[:, sc.current_index :, :2], t.valid[:, sc.current_index :]
    step = np.linalg.norm(np.diff(xy, axis=1), axis=-1) * (ok[:, 1:] & ok[:, :-1])
    logged = step.sum(1)[vehicle & ok[:, 0]]
    print(
        f"| the log itself | {logged.mean():.1f} | {np.median(logged):.1f} | "
        f"{np.mean(logged < 2.0):.2f} |"
    )
    tracks = [int(x) for x in args.tracks.split(",") if x]
    unknown = sorted(set(tracks) - set(t.id.tolist()))
    if unknown:
        p.error(f"tracks {unknown} are not in {args.layout} {args.seed}")
    variants = (("as logged", None), ("all STOP", C.SignalState.STOP), ("all GO", C.SignalState.GO))
    per_track = []
    for name, state in variants:
        runs = [travel(with_lights(sc, state), k, args.checkpoint) for k in range(args.seeds)]
        assert len(runs[0]) == len(vehicle), "agent slots are the scenario's tracks"
        d = np.mean(runs, axis=0)[vehicle & ok[:, 0]]
        print(f"| {name} | {d.mean():.1f} | {np.median(d):.1f} | {np.mean(d < 2.0):.2f} |")
        per_track.append((name, runs))
    for tid in tracks:
        row = int(np.flatnonzero(t.id == tid)[0])
        print(f"\ntrack {tid}, metres per episode:")
        for name, runs in per_track:
            print(f"  {name}: " + ", ".join(f"{r[row]:.1f}" for r in runs))


if __name__ == "__main__":
    main()
