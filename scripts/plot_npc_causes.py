"""Pictures of why the shipped NPC leaves real roads and collides (docs/MODEL_CARD.md).

Three real validation scenes (docs/model_card/real_splits.json), 16 TrafficBots rollouts each
(none dropped, seeds as ``tbsim evaluate``), map road edges in black and lane centres in grey:

1. parked vehicles (the spec's parked test) under the spec's inference: their 8 s paths, which
   creep and turn; under the shipped rule they stay on their boxes;
2. a vehicle that drives into a vehicle standing ahead of it (log: dashed blue; rollouts:
   orange, a dot where the first collision happens);
3. a vehicle whose rollouts turn another way than its log and cut across the kerb (red dots:
   first step of each rollout with a box corner past the road edge).

Also prints, over the whole validation split, how far parked vehicles move with each rule set.

    python scripts/plot_npc_causes.py --out docs/model_card/npc_causes.png [--data DIR]
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

import matplotlib
import numpy as np
import torch
from matplotlib.axes import Axes

from policies.trafficbots.batch import TokenBatch
from policies.trafficbots.config import InferenceConfig
from policies.trafficbots.model import TrafficBots
from policies.trafficbots.rules import parked_vehicles
from policies.trafficbots.wosac import load_default_model, trafficbots_rollouts
from tbsim_env.core.config import TokenConfig
from tbsim_env.core.constants import MapFeatureType
from tbsim_env.data.loader import load_scenarios
from tbsim_env.data.preprocess import preprocess_scenario
from tbsim_env.data.scenario import Scenario
from tbsim_env.evaluation import scenario_seed
from tbsim_env.metrics.wosac.rollouts import Rollouts
from tbsim_env.metrics.wosac.scoring import scenario_features
from tbsim_env.sim.horizon import wosac_scenario

REPO = Path(__file__).resolve().parents[1]
SPLITS = REPO / "docs" / "model_card" / "real_splits.json"
PARKED_SCENE = "4d320edc9cb801a3"
REAR_END = ("ab2a72c63f8fd589", 18)
KERB = ("tfrecord-00087-of-01000_252", 35)
ROLLOUTS = 16
VIEW = 35.0
"""m: half width of each panel's view."""


def scene(data: Path, scenario_id: str) -> Scenario:
    """A validation scene by id."""
    entry = next(
        e for e in json.loads(SPLITS.read_text())["validation"] if e["scenario_id"] == scenario_id
    )
    return load_scenarios(data / entry["file"])[0]


def rollouts_of(model: TrafficBots, sc: Scenario) -> Rollouts:
    """``ROLLOUTS`` rollouts, none dropped."""
    seed = scenario_seed(0, sc.scenario_id)
    return trafficbots_rollouts(model, sc, num_rollouts=ROLLOUTS, num_samples=ROLLOUTS, seed=seed)


def draw_map(ax: Axes, sc: Scenario, centre: np.ndarray) -> None:
    """Lane centres (grey) and road edges (black) around ``centre``, equal axes."""
    rm = sc.road_map
    for line, kind in zip(rm.polylines, rm.feature_type, strict=True):
        if kind == MapFeatureType.LANE:
            ax.plot(line[:, 0], line[:, 1], color="0.8", lw=0.6, zorder=1)
        elif kind == MapFeatureType.ROAD_EDGE:
            ax.plot(line[:, 0], line[:, 1], color="k", lw=1.0, zorder=2)
    ax.set_xlim(centre[0] - VIEW, centre[0] + VIEW)
    ax.set_ylim(centre[1] - VIEW, centre[1] + VIEW)
    ax.set_aspect("equal")
    ax.set_xticks([])
    ax.set_yticks([])


def draw_box(ax: Axes, xy: np.ndarray, yaw: float, size: np.ndarray, color: str) -> None:
    """An object's box (length, width) at ``xy`` heading ``yaw``."""
    c, s = np.cos(yaw), np.sin(yaw)
    half = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1], [1, 1]]) * size[:2] / 2
    pts = xy + half @ np.array([[c, s], [-s, c]])
    ax.plot(pts[:, 0], pts[:, 1], color=color, lw=1.2, zorder=4)


def column(r: Rollouts, sc: Scenario, track_id: int) -> int:
    """Index of a track in the rollouts."""
    return int(np.flatnonzero(r.object_id.numpy() == track_id)[0])


def parked_rows(sc: Scenario) -> list[int]:
    """Track rows of the vehicles the spec's parked test marks in ``sc`` (valid at the current
    step, so that the rollouts hold them)."""
    tok = preprocess_scenario(wosac_scenario(sc), TokenConfig())
    b = TokenBatch.from_tokens(tok)
    rules = InferenceConfig()
    parked = parked_vehicles(
        b.ag_valid[..., :11],
        b.ag_pose[..., :11, :],
        b.ag_motion[..., :11, 0],
        b.ag_type,
        (b.mp_pose, b.mp_valid, b.mp_cls),
        rules.still_displacement,
        rules.parked_lane_radius,
    )[0]
    rows = [int(tok.agent_track_index[n]) for n in np.flatnonzero(parked.numpy())]
    return [row for row in rows if sc.tracks.valid[row, sc.current_index]]


def parked_motion(models: dict[str, TrafficBots], sc: Scenario) -> dict[str, np.ndarray]:
    """Per rule set: [R, K, 2] (net displacement m, |heading change| rad) of the parked
    vehicles of ``sc`` over the 8 s."""
    rows = parked_rows(sc)
    t0, tr = sc.current_index, sc.tracks
    out = {}
    for name, model in models.items():
        r = rollouts_of(model, sc)
        cols = [column(r, sc, int(tr.id[row])) for row in rows]
        dx = r.x[:, cols, -1].numpy() - tr.xyz[rows, t0, 0]
        dy = r.y[:, cols, -1].numpy() - tr.xyz[rows, t0, 1]
        turn = np.abs(
            np.angle(np.exp(1j * (r.heading[:, cols, -1].numpy() - tr.heading[rows, t0])))
        )
        out[name] = np.stack([np.hypot(dx, dy), turn], -1)
    return out


def panel_parked(ax: Axes, sc: Scenario, spec: TrafficBots) -> None:
    """Parked vehicles' paths under the spec's inference; their boxes (held by the rule)."""
    r, t0, tr = rollouts_of(spec, sc), sc.current_index, sc.tracks
    rows = parked_rows(sc)
    centre = tr.xyz[rows, t0, :2].mean(0)
    draw_map(ax, sc, centre)
    for row in rows:
        j = column(r, sc, int(tr.id[row]))
        for k in range(ROLLOUTS):
            ax.plot(r.x[k, j], r.y[k, j], color="tab:red", lw=0.6, alpha=0.5, zorder=3)
        draw_box(ax, tr.xyz[row, t0, :2], float(tr.heading[row, t0]), tr.size[row, t0], "tab:green")
    ax.set_title(
        f"{sc.scenario_id}: parked vehicles (green boxes)\n"
        "spec inference: 8 s paths (red); shipped: held",
        fontsize=9,
    )


def panel_events(ax: Axes, sc: Scenario, track_id: int, model: TrafficBots, what: str) -> None:
    """One evaluated object's log (dashed blue) and rollouts (orange), its first collision or
    first off-road step in each rollout (``what``: "collision" / "offroad") as red dots."""
    r, t0, tr = rollouts_of(model, sc), sc.current_index, sc.tracks
    row = int(np.flatnonzero(tr.id == track_id)[0])
    f = scenario_features(sc, r)
    e = int(np.flatnonzero(f.objects.object_id == track_id)[0])
    flags = getattr(f.sim_features, f"{what}_per_step")[:, e] & f.log_valid[e]  # [R, S]
    j = column(r, sc, track_id)
    end = min(t0 + r.num_steps, tr.num_steps - 1)
    draw_map(ax, sc, tr.xyz[row, t0, :2])
    valid = tr.valid[row, t0 : end + 1]
    ax.plot(*tr.xyz[row, t0 : end + 1, :2][valid].T, "--", color="tab:blue", lw=1.5, zorder=5)
    hits = 0
    for k in range(ROLLOUTS):
        ax.plot(r.x[k, j], r.y[k, j], color="tab:orange", lw=0.7, alpha=0.6, zorder=3)
        if bool(flags[k].any()):
            s = int(flags[k].int().argmax())
            ax.plot(r.x[k, j, s], r.y[k, j, s], "o", color="tab:red", ms=3, zorder=6)
            hits += 1
    draw_box(ax, tr.xyz[row, t0, :2], float(tr.heading[row, t0]), tr.size[row, t0], "tab:blue")
    label = "collides" if what == "collision" else "leaves the road"
    ax.set_title(
        f"{sc.scenario_id}: vehicle {track_id} {label}\n"
        f"in {hits} of {ROLLOUTS} rollouts (red: first step)",
        fontsize=9,
    )
    if what == "collision":
        for other in range(tr.num_tracks):  # vehicles standing nearby at the current step
            if other != row and tr.valid[other, t0] and np.hypot(*tr.velocity[other, t0]) < 0.5:
                draw_box(
                    ax,
                    tr.xyz[other, t0, :2],
                    float(tr.heading[other, t0]),
                    tr.size[other, t0],
                    "0.3",
                )


def validation_parked(data: Path, models: dict[str, TrafficBots]) -> None:
    """Print how far the parked vehicles of every validation scene move under each rule set."""
    motion: dict[str, list[np.ndarray]] = {name: [] for name in models}
    for entry in json.loads(SPLITS.read_text())["validation"]:
        sc = load_scenarios(data / entry["file"])[0]
        for name, m in parked_motion(models, sc).items():
            motion[name].append(m.reshape(-1, 2))
    for name, parts in motion.items():
        m = np.concatenate(parts)
        print(
            f"{name}: {m.shape[0]} parked vehicle-rollouts, "
            f"mean displacement {m[:, 0].mean():.2f} m, "
            f"moved > 2 m {np.mean(m[:, 0] > 2):.3f}, turned > 0.5 rad {np.mean(m[:, 1] > 0.5):.3f}"
        )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--out", default=str(REPO / "docs" / "model_card" / "npc_causes.png"))
    p.add_argument("--data", default=os.environ.get("TBSIM_WOMD_DIR", "../shared/data/womd"))
    p.add_argument("--stats", action="store_true", help="also the parked-vehicle figures")
    args = p.parse_args()
    torch.set_num_threads(1)
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    data = Path(args.data)
    shipped, spec = load_default_model(), load_default_model()
    spec.inference = InferenceConfig.spec()
    fig, axes = plt.subplots(1, 3, figsize=(15, 5.4))
    panel_parked(axes[0], scene(data, PARKED_SCENE), spec)
    panel_events(axes[1], scene(data, REAR_END[0]), REAR_END[1], shipped, "collision")
    panel_events(axes[2], scene(data, KERB[0]), KERB[1], shipped, "offroad")
    fig.tight_layout()
    fig.subplots_adjust(top=0.88)
    fig.savefig(args.out, dpi=80)
    print(f"wrote {args.out}")
    if args.stats:
        validation_parked(data, {"spec": spec, "shipped": shipped})


if __name__ == "__main__":
    main()
