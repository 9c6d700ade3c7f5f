"""Why does the shipped NPC leave real roads and collide? Measurements on the real split scenes.

Samples TrafficBots rollouts on the scenes of one split of ``docs/model_card/real_splits.json``
(WOSAC protocol: ``--samples`` sampled, the ``--keep`` with the fewest collided relevant agents
kept; seeds as ``tbsim evaluate``), with the shipped inference rules or the spec's
(``policies.trafficbots.config.InferenceConfig``), and writes to ``--out``:

* ``scores.json``: the WOSAC scores (wosac2025, as ``tbsim wosac-score``) of every scene;
* ``events.json``: counts behind the model card's causes table: off-road (evaluated object,
  rollout) pairs by agent type and by whether the log itself is off-road; the first collision
  of each pair by geometry (rear-end, crossing, head-on, ...) and whether the partner was among
  the agent's 12 nearest agents 0.5 s before; parked vehicles' motion (net displacement and
  heading change over the 8 s);
* ``histograms.png``: log vs simulation feature histograms (``tbsim evaluate --plot``).

    python scripts/diagnose_npc_real.py --split validation --rules spec --out /tmp/spec
        [--samples 16 --keep 16] [--data ../shared/data/womd] [--checkpoint runs/x/ema]
    python scripts/diagnose_npc_real.py --compare /tmp/spec /tmp/shipped

``--compare A B`` prints the means over scenes of both runs' ``scores.json`` with 90% bootstrap
intervals over scenes, and the paired difference B - A with its interval.
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import json
import os
import time
from pathlib import Path

import numpy as np
import torch

from policies.trafficbots.checkpoint import load_checkpoint
from policies.trafficbots.config import InferenceConfig
from policies.trafficbots.rules import still_agents
from policies.trafficbots.wosac import load_default_model, trafficbots_rollouts
from tbsim_env.core import constants as C
from tbsim_env.data.loader import load_scenarios
from tbsim_env.data.scenario import Scenario
from tbsim_env.evaluation import feature_samples, plot_histograms, scenario_seed
from tbsim_env.metrics.wosac.rollouts import Rollouts
from tbsim_env.metrics.wosac.scoring import ScenarioFeatures, scenario_features, score_scenario
from tbsim_env.sim.geometry import wrap_angle

REPO = Path(__file__).resolve().parents[1]
SPLITS = REPO / "docs" / "model_card" / "real_splits.json"
TYPES = {1: "vehicle", 2: "pedestrian", 3: "cyclist"}
SAME_DIRECTION = 0.5
"""rad: heading difference below which two vehicles drive the same way."""
OPPOSITE = 2.6
"""rad: heading difference above which two vehicles drive against each other."""
LANE_HALF_WIDTH = 2.0
"""m: lateral offset within which a partner counts as ahead of / behind the agent."""


def first_collision_kind(f: ScenarioFeatures, r: int, e: int, t: int) -> tuple[str, int]:
    """(geometry of the first collision of evaluated object ``e`` in rollout ``r`` at step t,
    rank of the partner among e's nearest valid agents 5 steps before)."""
    sim = f.sim
    x, y, h = sim.x[r, :, t], sim.y[r, :, t], sim.heading[r, :, t]
    d = torch.hypot(x - x[e], y - y[e])
    d = torch.where(sim.valid[r, :, t], d, torch.inf)
    d[e] = torch.inf
    j = int(d.argmin())
    t5 = max(t - 5, 0)
    d5 = torch.hypot(sim.x[r, :, t5] - sim.x[r, e, t5], sim.y[r, :, t5] - sim.y[r, e, t5])
    d5 = torch.where(sim.valid[r, :, t5], d5, torch.inf)
    d5[e] = torch.inf
    rank = int((d5 < d5[j]).sum())
    te, tj = (TYPES.get(int(sim.object_type[i]), "other") for i in (e, j))
    if te != "vehicle" or tj != "vehicle":
        return f"{te} with {tj}", rank
    c, s = torch.cos(h[e]), torch.sin(h[e])
    ahead = float(c * (x[j] - x[e]) + s * (y[j] - y[e]))
    left = float(-s * (x[j] - x[e]) + c * (y[j] - y[e]))
    dyaw = abs(float(wrap_angle(h[j] - h[e])))
    if dyaw < SAME_DIRECTION and abs(left) < LANE_HALF_WIDTH:
        speed_j = float(torch.hypot(x[j] - sim.x[r, j, t - 1], y[j] - sim.y[r, j, t - 1])) / C.DT
        if ahead > 0:
            return "rear-ends a vehicle ahead" + (" (< 1 m/s)" if speed_j < 1.0 else ""), rank
        return "rear-ended by a vehicle behind", rank
    if dyaw < SAME_DIRECTION:
        return "side-swipe, same direction", rank
    if dyaw > OPPOSITE:
        return "head-on", rank
    return "crossing paths", rank


def count_events(sc: Scenario, f: ScenarioFeatures, out: collections.Counter) -> None:
    """Add the off-road and collision counts of one scene to ``out``."""
    lv, first = f.log_valid, sc.current_index + 1
    off = (f.sim_features.offroad_per_step & lv).any(-1)  # [R, E]
    coll = f.sim_features.collision_per_step & lv
    log_off = (f.log_features.offroad_per_step[0] & lv).any(-1)
    log_coll = (f.log_features.collision_per_step[0] & lv).any(-1)
    for e in range(f.objects.num_eval):
        kind = TYPES.get(int(f.sim.object_type[e]), "other")
        where = "off-road in the log too" if bool(log_off[e]) else "on the road in the log"
        out[f"pairs: {kind}"] += off.shape[0]
        out[f"off-road: {kind}"] += int(off[:, e].sum())
        out[f"off-road: {kind}, {where}"] += int(off[:, e].sum())
        out[f"pairs: {kind}, {where}"] += off.shape[0]
        for r in range(coll.shape[0]):
            if not bool(coll[r, e].any()):
                continue
            if bool(log_coll[e]):
                out["collision: also collides in the log"] += 1
                continue
            t = first + int(coll[r, e].int().argmax())
            geometry, rank = first_collision_kind(f, r, e, t)
            out[f"collision: {geometry}"] += 1
            out["collision partner among the 12 nearest 0.5 s before"] += int(rank < 12)


def parked_motion(sc: Scenario, rollouts: Rollouts, out: dict[str, list[float]]) -> None:
    """Net displacement (m) and |heading change| (rad) over the rollout of every vehicle that
    is still over its history and stays within 1 m in the log (rollouts and log, all kept)."""
    t0, tr = sc.current_index, sc.tracks
    hist = slice(0, t0 + 1)
    speed = np.hypot(tr.velocity[:, hist, 0], tr.velocity[:, hist, 1])
    still = still_agents(
        torch.as_tensor(tr.valid[:, hist]), torch.as_tensor(speed), 0.5
    ).numpy() & (tr.object_type == int(C.ObjectType.VEHICLE))
    ids = rollouts.object_id.numpy()
    for j, row in enumerate(np.flatnonzero(tr.valid[:, t0])):
        end = min(t0 + rollouts.num_steps, tr.valid.shape[1] - 1)
        if not still[row] or not tr.valid[row, end] or ids[j] != tr.id[row]:
            continue
        if np.hypot(*(tr.xyz[row, end, :2] - tr.xyz[row, t0, :2])) > 1.0:
            continue
        dx = rollouts.x[:, j, -1].numpy() - tr.xyz[row, t0, 0]
        dy = rollouts.y[:, j, -1].numpy() - tr.xyz[row, t0, 1]
        dyaw = wrap_angle(rollouts.heading[:, j, -1] - float(tr.heading[row, t0])).abs()
        out["displacement"] += np.hypot(dx, dy).tolist()
        out["heading_change"] += dyaw.tolist()


def run_split(args: argparse.Namespace) -> tuple[list[dict], dict]:
    """Roll out, score and count every scene of the split."""
    model = load_checkpoint(args.checkpoint) if args.checkpoint else load_default_model()
    if args.rules == "spec":
        model.inference = InferenceConfig.spec()
    model.inference = model.inference.with_rule_flags(args.gap_keeping, args.road_keeping)
    entries = json.loads(SPLITS.read_text())[args.split]
    scores, events, parked = [], collections.Counter(), {"displacement": [], "heading_change": []}
    samples: dict[str, list] = {}
    for entry in entries:
        t = time.time()
        sc = load_scenarios(Path(args.data) / entry["file"])[0]
        seed = scenario_seed(args.seed, sc.scenario_id)
        r = trafficbots_rollouts(
            model,
            sc,
            num_rollouts=args.keep,
            num_samples=args.samples,
            seed=seed,
            road_edge_weight=args.road_edge_weight,
        )
        s = score_scenario(sc, r, "wosac2025")
        scores.append(dataclasses.asdict(s))
        f = scenario_features(sc, r)
        count_events(sc, f, events)
        parked_motion(sc, r, parked)
        for name, pair in feature_samples(sc, r).items():
            samples.setdefault(name, []).append(pair)
        print(
            f"{sc.scenario_id}: meta {s.realism_meta_metric:.3f} collision "
            f"{s.simulated_collision_rate:.3f} off-road {s.simulated_offroad_rate:.3f} "
            f"({time.time() - t:.0f} s)",
            flush=True,
        )
    os.makedirs(args.out, exist_ok=True)
    title = f"TrafficBots ({args.rules} rules), {len(entries)} real {args.split} scenes"
    plot_histograms(samples, Path(args.out) / "histograms.png", title=title)
    d, h = np.asarray(parked["displacement"]), np.asarray(parked["heading_change"])
    summary = dict(sorted(events.items()))
    if d.size:
        summary["parked vehicle-rollouts"] = int(d.size)
        summary["parked: median displacement m"] = float(np.median(d))
        summary["parked: share moved > 2 m"] = float((d > 2.0).mean())
        summary["parked: share turned > 0.5 rad"] = float((h > 0.5).mean())
    return scores, summary


COMPARED = (
    "realism_meta_metric",
    "kinematic_metrics",
    "interactive_metrics",
    "map_based_metrics",
    "min_average_displacement_error",
    "simulated_collision_rate",
    "simulated_offroad_rate",
)
BOOTSTRAP = 4000


def interval(values: np.ndarray, rng: np.random.Generator) -> tuple[float, float]:
    """90% bootstrap interval of the mean over scenes of ``values`` [S]."""
    means = values[rng.integers(0, len(values), (BOOTSTRAP, len(values)))].mean(1)
    return float(np.percentile(means, 5)), float(np.percentile(means, 95))


def compare(first: Path, second: Path) -> None:
    """Means with 90% intervals of two runs on the same scenes and their paired difference."""
    runs = [
        {s["scenario_id"]: s for s in json.loads(Path(d, "scores.json").read_text())}
        for d in (first, second)
    ]
    ids = sorted(set(runs[0]) & set(runs[1]))
    rng = np.random.default_rng(0)
    print(f"{len(ids)} scenes: {first} -> {second}")
    for key in COMPARED:
        a, b = (np.array([r[i][key] for i in ids]) for r in runs)
        text = [
            f"{x.mean():.4f} [{lo:.3f}, {hi:.3f}]" for x in (a, b) for lo, hi in [interval(x, rng)]
        ]
        lo, hi = interval(b - a, rng)
        print(
            f"{key:32s} {text[0]:>24s} {text[1]:>24s}  "
            f"diff {(b - a).mean():+.4f} [{lo:+.4f}, {hi:+.4f}]"
        )


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--split", default="validation", choices=("validation", "held_out", "train"))
    p.add_argument("--rules", default="shipped", choices=("shipped", "spec"))
    p.add_argument(
        "--gap-keeping",
        metavar="off|NAME=VALUE,...",
        help='the gap-keeping rule: "off", or GapKeeping fields to change ("" for the shipped)',
    )
    p.add_argument(
        "--road-keeping",
        metavar="off|NAME=VALUE,...",
        help='the road-keeping rule (off when shipped): "off", or RoadKeeping fields to change '
        '("" for its defaults)',
    )
    p.add_argument("--samples", type=int, default=16)
    p.add_argument("--keep", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument(
        "--road-edge-weight",
        type=float,
        default=None,
        help="rank the sampled rollouts by collided + this x road-departing agents (default: "
        "the inference rules', shipped 1, spec 0)",
    )
    p.add_argument("--data", default=os.environ.get("TBSIM_WOMD_DIR", "../shared/data/womd"))
    p.add_argument("--out")
    p.add_argument("--checkpoint", help="checkpoint base path (default: the shipped weights)")
    p.add_argument("--compare", nargs=2, metavar=("A", "B"), help="compare two output folders")
    args = p.parse_args()
    if args.compare:
        compare(*map(Path, args.compare))
        return
    if not args.out:
        p.error("--out is required unless --compare is given")
    torch.set_num_threads(1)
    scores, summary = run_split(args)
    Path(args.out, "scores.json").write_text(json.dumps(scores, indent=1))
    Path(args.out, "events.json").write_text(json.dumps(summary, indent=1))
    for k, v in summary.items():
        print(f"{k}: {v}")


if __name__ == "__main__":
    main()
