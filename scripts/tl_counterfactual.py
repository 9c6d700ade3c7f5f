"""Does the NPC policy obey the traffic lights it sees? (docs/MODEL_CARD.md, yielding)

Runs ``TrafficEnv`` with TrafficBots NPCs (the SDC follows its log) on one generated scene three
times: with the logged lights, with every valid light forced to STOP and with every valid light
forced to GO, and prints how far the vehicles travel (mean over ``--seeds`` episodes). A policy
that ignores the lights gives the same figures in all three rows. ``--tracks`` also prints the
distance of each of those tracks in every episode and the first step at which it overlaps
another agent. ``--replay`` makes those tracks follow their logs too (like the SDC), which
tells a follower's fault from its leader's: does 320 still run into 326 when 326 stands where
its log stands?

    python scripts/tl_counterfactual.py intersection 10000 [--seeds 3] [--checkpoint P]
        [--tracks 320,326] [--replay 326]
"""

from __future__ import annotations

import argparse
import dataclasses

import numpy as np
import torch

from tbsim_env.core import constants as C
from tbsim_env.core.config import EnvConfig, TerminationConfig
from tbsim_env.data.generator import generate_scenario
from tbsim_env.data.scenario import Scenario
from tbsim_env.env import TrafficEnv
from tbsim_env.sim.collision import collided


def with_lights(sc: Scenario, state: C.SignalState | None) -> Scenario:
    """``sc`` with every valid signal state set to ``state`` (None: as logged)."""
    if state is None:
        return sc
    s = sc.signals
    forced = np.where(s.valid, np.int8(state), s.state).astype(np.int8)
    return dataclasses.replace(sc, signals=dataclasses.replace(s, state=forced))


_NO_TERMINATION = EnvConfig(
    termination=TerminationConfig(collision=False, offroad=False, goal=False)
)
"""The log followers run to the end of the episode whatever happens to them."""


def first_true(flags: torch.Tensor) -> torch.Tensor:
    """[N] int64 index of the first True of each column of ``flags`` [T, N] bool, -1 if none."""
    first = flags.int().argmax(0)
    return torch.where(flags.any(0), first, torch.full_like(first, -1))


def travel(
    sc: Scenario, seed: int, checkpoint: str | None, replay: tuple[int, ...] = ()
) -> tuple[np.ndarray, np.ndarray]:
    """One episode: ([N] metres each agent slot drives, [N] index of the step (0: the first) after
    which it first overlaps another agent, -1 if never). The SDC and the ``replay`` tracks
    follow their logs."""
    controlled = [sc.sdc_id, *[r for r in replay if r != sc.sdc_id]]
    env = TrafficEnv(
        [sc],
        controlled=controlled,
        npc_policy="trafficbots",
        npc_checkpoint=checkpoint,
        config=_NO_TERMINATION,
    )
    env.reset(seed=seed)
    prev = env.sim_state.pose[0, :, :2].clone()
    total = torch.zeros(prev.shape[0])
    hits = []
    while env.agents:
        env.step(env.expert_actions())
        s = env.sim_state
        cur = s.pose[0, :, :2].clone()
        total += torch.linalg.vector_norm(cur - prev, dim=-1) * s.valid[0]
        hits.append(collided(s.pose, s.agents.size[..., :2], s.valid)[0])
        prev = cur
    return total.numpy(), first_true(torch.stack(hits)).numpy()


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("layout")
    p.add_argument("seed", type=int)
    p.add_argument("--seeds", type=int, default=3, help="episodes (policy seeds) per variant")
    p.add_argument("--checkpoint", default=None)
    p.add_argument("--tracks", default="", help="comma-separated track ids to list per episode")
    p.add_argument("--replay", default="", help="comma-separated track ids that follow their log")
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
    replay = tuple(int(x) for x in args.replay.split(",") if x)
    unknown = sorted(set(tracks + list(replay)) - set(t.id.tolist()))
    if unknown:
        p.error(f"tracks {unknown} are not in {args.layout} {args.seed}")
    variants = (("as logged", None), ("all STOP", C.SignalState.STOP), ("all GO", C.SignalState.GO))
    per_track = []
    for name, state in variants:
        runs = [
            travel(with_lights(sc, state), k, args.checkpoint, replay) for k in range(args.seeds)
        ]
        assert len(runs[0][0]) == len(vehicle), "agent slots are the scenario's tracks"
        d = np.mean([r[0] for r in runs], axis=0)[vehicle & ok[:, 0]]
        print(f"| {name} | {d.mean():.1f} | {np.median(d):.1f} | {np.mean(d < 2.0):.2f} |")
        per_track.append((name, runs))
    for tid in tracks:
        row = int(np.flatnonzero(t.id == tid)[0])
        print(f"\ntrack {tid}, metres per episode (steps until it first overlaps another agent):")
        for name, runs in per_track:
            cells = (f"{m[row]:.1f} ({h[row] + 1 if h[row] >= 0 else '-'})" for m, h in runs)
            print(f"  {name}: " + ", ".join(cells))


if __name__ == "__main__":
    main()
