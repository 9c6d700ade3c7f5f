"""Where do the shipped NPC's off-road and collision events happen? (docs/MODEL_CARD.md)

Samples TrafficBots rollouts on one generated scene and prints, per evaluated object, its logged
turn, its off-road and collision rates over the rollouts, where the first off-road step of a
rollout lies (layout frame: the junction is at the origin) next to the logged position, and
whom the object hits first in the first rollout where it collides: where that partner is in
the object's frame, both speeds, how far each has turned since the current step (left
positive), and where the object is.

    python scripts/diagnose_npc_events.py intersection 10000 [--rollouts 16] [--checkpoint P]
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

from policies.trafficbots.wosac import trafficbots_rollout_fn
from tbsim_env.core import constants as C
from tbsim_env.data.generator import frame_offset, generate_scenario
from tbsim_env.metrics.wosac import scenario_features
from tbsim_env.metrics.wosac.features_interactive import rectangle_signed_distance
from tbsim_env.metrics.wosac.trajectories import ObjectTrajectories
from tbsim_env.sim.geometry import wrap_angle


def collision_partner(sim: ObjectTrajectories, r: int, e: int, t: int) -> tuple[int, float]:
    """(index, signed distance m) of the object whose box is deepest into object ``e``'s box
    in rollout ``r`` at step ``t`` (2-D boxes; -1 and inf when no other object is valid)."""
    centre = torch.stack([sim.x[r, :, t], sim.y[r, :, t]], -1)  # [N, 2]
    half = torch.stack([sim.length, sim.width], -1) * 0.5
    heading = sim.heading[r, :, t]
    d = rectangle_signed_distance(centre[e], heading[e], half[e], centre, heading, half)
    d = torch.where(sim.valid[r, :, t], d, torch.full_like(d, float("inf")))
    d[e] = float("inf")
    j = int(d.argmin())
    return (j, float(d[j])) if torch.isfinite(d[j]) else (-1, float("inf"))


def collision_geometry(
    sim: ObjectTrajectories, r: int, e: int, j: int, t: int, offset: tuple[float, float]
) -> str:
    """Where object ``j`` is in object ``e``'s frame at step ``t`` of rollout ``r`` (ahead /
    left, m), their speeds (m/s, from the step before) and ``e``'s layout-frame position."""
    x, y, h = sim.x[r, :, t], sim.y[r, :, t], sim.heading[r, e, t]
    ddx, ddy = float(x[j] - x[e]), float(y[j] - y[e])
    c, s = float(torch.cos(h)), float(torch.sin(h))
    ahead, left = c * ddx + s * ddy, -s * ddx + c * ddy
    speed = torch.hypot(x - sim.x[r, :, t - 1], y - sim.y[r, :, t - 1]) / C.DT
    turned = torch.rad2deg(wrap_angle(sim.heading[r, :, t] - sim.heading[r, :, C.CURRENT_INDEX]))
    return (
        f"partner {ahead:.1f} m ahead, {left:.1f} m left; speeds {float(speed[e]):.1f} and "
        f"{float(speed[j]):.1f} m/s; turned {float(turned[e]):.0f} and {float(turned[j]):.0f} "
        f"deg since the current step; at ({float(x[e]) - offset[0]:.1f}, "
        f"{float(y[e]) - offset[1]:.1f})"
    )


def first_event(flags: torch.Tensor) -> tuple[int, int] | None:
    """(rollout, future step) of the first event in the first rollout that has one, from
    ``flags`` [R, T] bool; None without any."""
    rows = flags.any(-1).nonzero()
    if rows.numel() == 0:
        return None
    r = int(rows[0, 0])
    return r, int(flags[r].int().argmax())


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("layout")
    p.add_argument("seed", type=int)
    p.add_argument("--rollouts", type=int, default=16)
    p.add_argument("--checkpoint", default=None)
    args = p.parse_args()
    torch.set_num_threads(1)
    sc = generate_scenario(args.layout, args.seed)
    fn = trafficbots_rollout_fn(checkpoint=args.checkpoint, num_samples=args.rollouts)
    rollouts = fn(sc, args.rollouts, 0)
    f = scenario_features(sc, rollouts)
    obj, log, sim, feats, valid = f.objects, f.log, f.sim, f.sim_features, f.log_valid
    first = sc.current_index + 1
    off = feats.offroad_per_step & valid  # [R, E, T]
    coll = feats.collision_per_step & valid
    dx, dy = frame_offset(args.layout, args.seed)
    t = sc.tracks
    for e in range(obj.num_eval):
        idx = int(np.flatnonzero(t.id == obj.object_id[e])[0])
        head = t.heading[idx][t.valid[idx]]
        turn = np.degrees(np.angle(np.exp(1j * (head[-1] - head[0]))))
        line = (
            f"object {int(obj.object_id[e]):4d}: logged turn {turn:6.1f} deg, "
            f"off-road {off[:, e].any(-1).float().mean():.2f}, "
            f"collision {coll[:, e].any(-1).float().mean():.2f}"
        )
        hit = first_event(off[:, e])
        if hit is not None:
            r, k = hit
            line += (
                f"; rollout {r} leaves the road at step {first + k}: sim "
                f"({float(sim.x[r, e, first + k]) - dx:.1f}, "
                f"{float(sim.y[r, e, first + k]) - dy:.1f}), log "
                f"({float(log.x[0, e, first + k]) - dx:.1f}, "
                f"{float(log.y[0, e, first + k]) - dy:.1f}), "
                f"{float(feats.distance_to_road_edge[r, e, k]):.2f} m past the edge"
            )
        hit = first_event(coll[:, e])
        if hit is not None:
            r, k = hit
            j, depth = collision_partner(sim, r, e, first + k)
            whom = (
                "no valid box"
                if j < 0
                else (
                    f"object {int(obj.object_id[j])} "
                    f"({C.ObjectType(int(sim.object_type[j])).name.lower()}, {depth:.2f} m)"
                )
            )
            line += f"; rollout {r} collides at step {first + k} with {whom}"
            if j >= 0:
                line += "; " + collision_geometry(sim, r, e, j, first + k, (dx, dy))
        print(line)


if __name__ == "__main__":
    main()
