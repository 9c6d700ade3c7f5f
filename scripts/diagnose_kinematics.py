"""Why the NPC's kinematic WOSAC bucket lies below the log's: per-feature likelihoods by agent
type and speed band, sim-vs-log histograms, action-step statistics and inference ablations.

``run`` rolls out the scenes of one split of ``docs/model_card/real_splits.json`` under each
named variant (the shipped inference, log replay, one rule or sampling choice changed; seeds as
``tbsim evaluate``, so every variant sees the same scenes and draws) and appends one JSON line
per (variant, scene) to ``OUT/VARIANT.jsonl`` (a rerun skips the pairs already there).
Everything is computed by the project's WOSAC code (``scenario_features``,
``histogram_log_likelihood``, the scoring masks), grouped by the evaluated agent's type and
its logged speed at the current step. ``report`` prints the tables and draws the histograms.

    python scripts/diagnose_kinematics.py run --split validation --out /tmp/kin \\
        --variants log,shipped,sampled,zero_latent [--scenes 0::3] [--samples 128 --keep 32]
    python scripts/diagnose_kinematics.py report /tmp/kin --baseline shipped \\
        --png /tmp/kin/histograms.png [--png-variants shipped,recorded]
    python scripts/diagnose_kinematics.py variants        # the named variants

A variant is a name of ``VARIANTS`` or ``LABEL:FIELD=VALUE+FIELD=VALUE`` (``InferenceConfig``
fields over the shipped ones: numbers, true/false, none; ``recording=recorded`` for the
fitted jitter, ``recording=tracker`` for the measured one).
"""

from __future__ import annotations

import argparse
import dataclasses
import hashlib
import json
import math
import os
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from tqdm import tqdm

from policies.trafficbots.config import InferenceConfig, RoadKeeping
from policies.trafficbots.wosac import (
    load_default_model,
    record_rollouts,
    trafficbots_rollouts,
)
from tbsim_env.core import constants as C
from tbsim_env.data.generator.recording import RECORDED, TRACKER
from tbsim_env.data.loader import load_scenarios
from tbsim_env.data.scenario import Scenario
from tbsim_env.evaluation import scenario_seed
from tbsim_env.metrics.wosac.config import HistogramSpec, get_config
from tbsim_env.metrics.wosac.estimators import histogram_bin_index, histogram_log_likelihood
from tbsim_env.metrics.wosac.features_kinematic import acceleration_validity, speed_validity
from tbsim_env.metrics.wosac.rollouts import Rollouts, log_replay_rollouts
from tbsim_env.metrics.wosac.scoring import ScenarioFeatures, scenario_features, score_scenario
from tbsim_env.sim.geometry import wrap_angle
from tbsim_env.sim.horizon import wosac_scenario

REPO = Path(__file__).resolve().parents[1]
SPLITS = REPO / "docs" / "model_card" / "real_splits.json"
VERSION = "wosac2025"
FEATURES = ("linear_speed", "linear_acceleration", "angular_speed", "angular_acceleration")
SPEED_MASKED = ("linear_speed", "angular_speed")
TYPES = {1: "vehicle", 2: "pedestrian", 3: "cyclist"}
BAND_SPEED = 1.0
"""m/s: the logged speed at the current step that splits the two speed bands."""
FINE = 4
"""Picture bins per WOSAC bin."""
SCORES = (
    "realism_meta_metric",
    "kinematic_metrics",
    "interactive_metrics",
    "map_based_metrics",
    "linear_speed_likelihood",
    "linear_acceleration_likelihood",
    "angular_speed_likelihood",
    "angular_acceleration_likelihood",
    "simulated_collision_rate",
    "simulated_offroad_rate",
    "min_average_displacement_error",
)


@dataclass(frozen=True)
class Variant:
    """One way of producing a scene's rollouts.

    Attributes:
        name: label of the output file and the tables.
        about: one line for the tables.
        inference: the ``InferenceConfig`` the shipped model runs with; None for log replay.
    """

    name: str
    about: str
    inference: InferenceConfig | None


def _shipped(**changes) -> InferenceConfig:
    return dataclasses.replace(InferenceConfig(), **changes)


VARIANTS: dict[str, Callable[[], Variant]] = {
    "log": lambda: Variant("log", "log replay", None),
    "shipped": lambda: Variant("shipped", "shipped inference", InferenceConfig()),
    "spec": lambda: Variant("spec", "the spec's inference (no rule)", InferenceConfig.spec()),
    "sampled": lambda: Variant(
        "sampled", "actions sampled, head sigma exp(-2)", _shipped(action_sigma=math.exp(-2))
    ),
    "zero_latent": lambda: Variant(
        "zero_latent", "personality z = 0 (prior mean)", _shipped(latent_temperature=0.0)
    ),
    "no_hold_parked": lambda: Variant(
        "no_hold_parked", "parked vehicles driven", _shipped(hold_parked=False)
    ),
    "no_gap_keeping": lambda: Variant(
        "no_gap_keeping", "no gap keeping", _shipped(gap_keeping=None)
    ),
    "curvature_limit": lambda: Variant(
        "curvature_limit", "vehicle curvature <= 0.25 /m", _shipped(vehicle_max_curvature=0.25)
    ),
    "clip_history": lambda: Variant(
        "clip_history", "history motion clipped", _shipped(clip_history_motion=True)
    ),
    "road_keeping": lambda: Variant(
        "road_keeping", "road keeping on", _shipped(road_keeping=RoadKeeping())
    ),
    "collisions_only": lambda: Variant(
        "collisions_only", "selection: collisions only", _shipped(road_edge_weight=0.0)
    ),
    "recorded": lambda: Variant(
        "recorded", "fitted tracker jitter on the kept rollouts", _shipped(recording=RECORDED)
    ),
    "tracker": lambda: Variant(
        "tracker", "tracker jitter (TRACKER) on the kept rollouts", _shipped(recording=TRACKER)
    ),
}


def _value(text: str):
    """A command-line field value: number, bool or None (``recorded``: the fitted jitter)."""
    low = text.lower()
    if low in ("none", "off"):
        return None
    if low in ("true", "false"):
        return low == "true"
    if low == "recorded":
        return RECORDED
    if low == "tracker":
        return TRACKER
    return float(text)


def parse_variant(text: str) -> Variant:
    """A ``VARIANTS`` name or ``LABEL:FIELD=VALUE+...`` over the shipped ``InferenceConfig``."""
    if text in VARIANTS:
        return VARIANTS[text]()
    label, sep, body = text.partition(":")
    if not sep:
        raise ValueError(f"unknown variant {text!r}: one of {sorted(VARIANTS)} or LABEL:F=V+...")
    changes = {}
    for item in body.split("+"):
        name, _, value = item.partition("=")
        changes[name.strip()] = _value(value.strip())
    return Variant(label, body, _shipped(**changes))


def agent_groups(sc: Scenario, f: ScenarioFeatures) -> list[str]:
    """'TYPE <1' or 'TYPE >=1' (logged speed at the current step, m/s) per evaluated agent."""
    rows = f.objects.track_index[: f.objects.num_eval]
    t0 = sc.current_index
    speed = np.hypot(*sc.tracks.velocity[rows, t0, :2].T)
    types = sc.tracks.object_type[rows]
    return [
        f"{TYPES.get(int(t), 'other')} {'<' if v < BAND_SPEED else '>='}{BAND_SPEED:g}"
        for t, v in zip(types, speed, strict=True)
    ]


def fine_edges(spec: HistogramSpec) -> np.ndarray:
    """[FINE * bins + 1] picture bin edges over the feature's WOSAC range."""
    return np.linspace(spec.min_val, spec.max_val, FINE * spec.num_bins + 1)


def _hist(values: torch.Tensor, spec: HistogramSpec) -> list[int]:
    """Picture histogram of finite values clipped to the WOSAC range."""
    v = values[torch.isfinite(values)].double().clamp(spec.min_val, spec.max_val).numpy()
    return np.histogram(v, bins=fine_edges(spec))[0].tolist()


def feature_groups(f: ScenarioFeatures, groups: list[str]) -> dict[str, dict[str, dict]]:
    """Per group and kinematic feature: the log-likelihood sum and count over the scored
    entries, those whose bin no simulated value of the agent reaches (uncovered), and the
    picture histograms of the log and of the simulations at the scored steps."""
    config = get_config(VERSION)
    out: dict[str, dict[str, dict]] = {}
    for name in FEATURES:
        spec = getattr(config.histograms, name)
        log_v, sim_v = getattr(f.log_features, name)[0], getattr(f.sim_features, name)
        ll = histogram_log_likelihood(log_v, sim_v, spec, config.histogram_pseudocount)
        mask = (speed_validity if name in SPEED_MASKED else acceleration_validity)(f.log_valid)
        sim_bins = histogram_bin_index(sim_v, spec)  # [R, E, F]
        counts = torch.nn.functional.one_hot(sim_bins, spec.num_bins).sum((0, 2))  # [E, K]
        uncovered = counts.gather(1, histogram_bin_index(log_v, spec)) == 0  # [E, F]
        for e, g in enumerate(groups):
            m = mask[e]
            if not bool(m.any()):
                continue
            d = out.setdefault(g, {}).setdefault(
                name, {"sum": 0.0, "n": 0, "unc_n": 0, "unc_sum": 0.0, "log": None, "sim": None}
            )
            d["sum"] += float(ll[e][m].sum())
            d["n"] += int(m.sum())
            d["unc_n"] += int((uncovered[e] & m).sum())
            d["unc_sum"] += float(ll[e][uncovered[e] & m].sum())
            hl, hs = _hist(log_v[e][m], spec), _hist(sim_v[:, e][:, m], spec)
            d["log"] = hl if d["log"] is None else [a + b for a, b in zip(d["log"], hl)]
            d["sim"] = hs if d["sim"] is None else [a + b for a, b in zip(d["sim"], hs)]
    return out


def step_motion(x, y, h, valid) -> dict[str, torch.Tensor]:
    """Per-step motion of trajectories [R, E, T] over the future: the yaw rate
    w_t = wrap(h[t+1] - h[t]) / dt and acceleration a_t = (u[t+1] - u[t]) / dt of the step
    speed u_t = |p[t+1] - p[t]| / dt (what an action of one 0.1 s step does), their step-to-step
    changes, with validity masks. Values [R, E, T-1] / [R, E, T-2] / [R, E, T-3]."""
    ok1 = valid[..., 1:] & valid[..., :-1]
    w = wrap_angle(h[..., 1:] - h[..., :-1]) / C.DT
    u = torch.hypot(x[..., 1:] - x[..., :-1], y[..., 1:] - y[..., :-1]) / C.DT
    ok2 = ok1[..., 1:] & ok1[..., :-1]
    a = (u[..., 1:] - u[..., :-1]) / C.DT
    ok3 = ok2[..., 1:] & ok2[..., :-1]
    flip = (w[..., 1:] * w[..., :-1] < 0) & (w[..., 1:].abs() > 0.02) & (w[..., :-1].abs() > 0.02)
    return {
        "|w|": (w.abs(), ok1),
        "|dw|": ((w[..., 1:] - w[..., :-1]).abs(), ok2),
        "w sign flips": (flip.to(w.dtype), ok2),
        "|a|": (a.abs(), ok2),
        "|da|": ((a[..., 1:] - a[..., :-1]).abs(), ok3),
    }


def step_groups(sc: Scenario, f: ScenarioFeatures, groups: list[str]) -> dict[str, dict]:
    """Per group, for the simulations and the log: sums and counts of ``step_motion`` over the
    future steps and of |WOSAC feature| over the scored steps (both from positions)."""
    e, t0 = f.objects.num_eval, sc.current_index
    out: dict[str, dict] = {}
    for who, traj, feats in (("sim", f.sim, f.sim_features), ("log", f.log, f.log_features)):
        cut = slice(t0, None)
        valid = traj.valid[:, :e, cut]
        motion = step_motion(
            traj.x[:, :e, cut], traj.y[:, :e, cut], traj.heading[:, :e, cut], valid
        )
        for name in FEATURES:
            mask = (speed_validity if name in SPEED_MASKED else acceleration_validity)(f.log_valid)
            v = getattr(feats, name)[:, :e]
            motion[f"|{name}|"] = (v.abs().nan_to_num(0.0), mask.expand_as(v) & torch.isfinite(v))
        for k, g in enumerate(groups):
            d = out.setdefault(g, {}).setdefault(who, {})
            for key, (v, m) in motion.items():
                s, n = d.get(key, (0.0, 0))
                d[key] = (s + float(v[:, k][m[:, k]].sum()), n + int(m[:, k].sum()))
    return out


def scene_record(sc: Scenario, rollouts: Rollouts, variant: Variant) -> dict:
    """Everything ``report`` needs of one (variant, scene)."""
    s = score_scenario(sc, rollouts, VERSION)
    f = scenario_features(sc, rollouts)
    groups = agent_groups(sc, f)
    fg = feature_groups(f, groups)
    for name in FEATURES:  # the groups add up to the scene's likelihood
        tot = sum(d[name]["sum"] for d in fg.values() if name in d)
        n = sum(d[name]["n"] for d in fg.values() if name in d)
        if n and not math.isclose(
            math.exp(tot / n), getattr(s, f"{name}_likelihood"), rel_tol=1e-3
        ):
            raise AssertionError(f"{sc.scenario_id} {name}: groups do not add up to the score")
    return {
        "scenario_id": sc.scenario_id,
        "variant": variant.name,
        "about": variant.about,
        "scores": {k: getattr(s, k) for k in SCORES},
        "features": fg,
        "steps": step_groups(sc, f, groups),
    }


def _done(path: Path) -> set[str]:
    if not path.exists():
        return set()
    return {json.loads(line)["scenario_id"] for line in path.read_text().splitlines() if line}


def exact_rollouts(
    model, inference: InferenceConfig, sc: Scenario, seed: int, args: argparse.Namespace
) -> Rollouts:
    """The shipped model's WOSAC rollouts under ``inference`` (no recording), read from
    ``args.cache`` when a run with the same settings stored them there."""
    tag = f"{sc.scenario_id}|{inference!r}|{args.samples}|{args.keep}|{seed}"
    name = hashlib.sha1(tag.encode()).hexdigest() + ".safetensors"
    path = Path(args.cache, name) if args.cache else None
    if path is not None and path.exists():
        return Rollouts(scenario_id=sc.scenario_id, **load_file(path))
    model.inference = inference
    r = trafficbots_rollouts(model, sc, num_rollouts=args.keep, num_samples=args.samples, seed=seed)
    if path is not None:
        path.parent.mkdir(parents=True, exist_ok=True)
        fields = (f.name for f in dataclasses.fields(r) if f.name != "scenario_id")
        save_file({k: getattr(r, k).contiguous() for k in fields}, path)
    return r


def run(args: argparse.Namespace) -> None:
    """Roll out and record every (scene, variant) not recorded yet."""
    torch.set_num_threads(1)
    variants = [parse_variant(v) for v in args.variants.split(",")]
    entries = json.loads(SPLITS.read_text())[args.split]
    start, stop, step = (int(x) if x else None for x in (args.scenes.split(":") + ["", ""])[:3])
    entries = entries[slice(start, stop, step)]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    done = {v.name: _done(out / f"{v.name}.jsonl") for v in variants}
    model = load_default_model()
    for entry in tqdm(entries, desc=f"{args.split} scenes"):
        sc = load_scenarios(Path(args.data) / entry["file"])[0]
        seed = scenario_seed(args.seed, sc.scenario_id)
        exact: dict[InferenceConfig, Rollouts] = {}  # variants that differ in the recording only
        for v in variants:
            if sc.scenario_id in done[v.name]:
                continue
            if v.inference is None:
                r = log_replay_rollouts(sc, args.keep)
            else:
                key = dataclasses.replace(v.inference, recording=None)
                if key not in exact:
                    exact[key] = exact_rollouts(model, key, sc, seed, args)
                r = exact[key]
                if v.inference.recording is not None:
                    r = record_rollouts(wosac_scenario(sc), r, v.inference.recording, seed)
            with open(out / f"{v.name}.jsonl", "a") as fh:
                fh.write(json.dumps(scene_record(sc, r, v)) + "\n")


TRACKER_GROUPS = {
    "vehicle moving >= 3 m/s": (1, 3.0, math.inf),
    "pedestrian walking >= 1 m/s": (2, 1.0, math.inf),
    "pedestrian standing < 0.2 m/s": (2, 0.0, 0.2),
    "vehicle standing < 0.05 m/s": (1, 0.0, 0.05),
}
"""Track groups of the jitter measurement: (``ObjectType``, logged speed range m/s)."""
MIN_TRACK_STEPS = 20


def robust_white_sigma(second_diff: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Per track, the standard deviation of white noise whose second differences are
    ``second_diff`` [A, T]: 1.4826 x median absolute deviation / sqrt(6) over the masked steps
    (NaN for tracks with fewer than ``MIN_TRACK_STEPS``). Returns [A]."""
    x = np.where(mask, second_diff, np.nan)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN rows: tracks left out
        mad = np.nanmedian(np.abs(x - np.nanmedian(x, axis=1, keepdims=True)), axis=1)
    return np.where(mask.sum(1) >= MIN_TRACK_STEPS, 1.4826 * mad / math.sqrt(6.0), np.nan)


def scene_jitter(sc: Scenario) -> dict[str, np.ndarray]:
    """Per group of ``TRACKER_GROUPS``: [K, 3] white jitter of its tracks (vehicles: along and
    across the heading, m; pedestrians: mean of x and y, m; and heading, rad)."""
    tr = sc.tracks
    h = np.unwrap(np.where(tr.valid, tr.heading, 0.0), axis=1)
    speed = np.hypot(tr.velocity[..., 0], tr.velocity[..., 1])[:, 1:-1]
    ok = tr.valid[:, 2:] & tr.valid[:, 1:-1] & tr.valid[:, :-2]
    d2 = lambda v: v[:, 2:] - 2.0 * v[:, 1:-1] + v[:, :-2]  # noqa: E731
    d2x, d2y, d2h = d2(tr.xyz[..., 0]), d2(tr.xyz[..., 1]), d2(h)
    c, s = np.cos(h[:, 1:-1]), np.sin(h[:, 1:-1])
    along, across = c * d2x + s * d2y, -s * d2x + c * d2y
    out = {}
    for name, (kind, lo, hi) in TRACKER_GROUPS.items():
        mask = ok & (tr.object_type == kind)[:, None] & (speed >= lo) & (speed < hi)
        if kind == 1:
            cols = [robust_white_sigma(along, mask), robust_white_sigma(across, mask)]
        else:
            xy = 0.5 * (robust_white_sigma(d2x, mask) + robust_white_sigma(d2y, mask))
            cols = [xy, xy]
        vals = np.stack(cols + [robust_white_sigma(d2h, mask)], axis=1)
        out[name] = vals[np.isfinite(vals).all(1)]
    return out


def tracker(args: argparse.Namespace) -> None:
    """Print the median over tracks of each group's white jitter (``recording.TRACKER``)."""
    entries = json.loads(SPLITS.read_text())[args.split]
    found: dict[str, list[np.ndarray]] = {}
    for entry in tqdm(entries, desc=f"{args.split} scenes"):
        sc = load_scenarios(Path(args.data) / entry["file"])[0]
        for name, vals in scene_jitter(sc).items():
            found.setdefault(name, []).append(vals)
    print("| tracks | count | along or x (m) | across or y (m) | heading (rad) |")
    print("|---|---|---|---|---|")
    for name, parts in found.items():
        vals = np.concatenate(parts)
        med = np.median(vals, axis=0) if len(vals) else np.full(3, np.nan)
        print(f"| {name} | {len(vals)} | {med[0]:.4f} | {med[1]:.4f} | {med[2]:.5f} |")


BOOTSTRAP = 4000


def interval(values: np.ndarray, rng: np.random.Generator) -> tuple[float, float]:
    """90% bootstrap interval of the mean over scenes of ``values`` [S]."""
    means = values[rng.integers(0, len(values), (BOOTSTRAP, len(values)))].mean(1)
    return float(np.percentile(means, 5)), float(np.percentile(means, 95))


def load_runs(folder: Path) -> dict[str, dict[str, dict]]:
    """{variant: {scenario id: record}} of every ``*.jsonl`` in ``folder``, cut to the scenes
    that every variant holds (paired)."""
    runs = {}
    for path in sorted(folder.glob("*.jsonl")):
        recs = [json.loads(line) for line in path.read_text().splitlines() if line]
        runs[path.stem] = {r["scenario_id"]: r for r in recs}
    common = set.intersection(*(set(r) for r in runs.values())) if runs else set()
    return {v: {k: r[k] for k in sorted(common)} for v, r in runs.items()}


def overview(runs: dict[str, dict[str, dict]], baseline: str) -> None:
    """Scores of every variant (means over scenes) and their paired differences from the
    baseline, with 90% intervals."""
    rng = np.random.default_rng(0)
    ids = list(runs[baseline])
    cols = ("realism_meta_metric", "kinematic_metrics") + SCORES[4:8] + SCORES[2:4] + SCORES[8:10]
    short = ("meta", "kinematic", "lin speed", "lin acc", "ang speed", "ang acc", "interactive")
    short += ("map", "collision", "off-road")
    print(f"\n### Scores, {len(ids)} scenes (paired differences: variant - {baseline})\n")
    print("| variant | " + " | ".join(short) + " |")
    print("|---" * (len(short) + 1) + "|")
    base = {k: np.array([runs[baseline][i]["scores"][k] for i in ids]) for k in cols}
    for name, recs in runs.items():
        vals = {k: np.array([recs[i]["scores"][k] for i in ids]) for k in cols}
        cells = [f"{vals[k].mean():.3f}" for k in cols]
        print(f"| {name} ({recs[ids[0]]['about']}) | " + " | ".join(cells) + " |")
        if name == baseline:
            continue
        diffs = []
        for k in cols:
            d = vals[k] - base[k]
            lo, hi = interval(d, rng)
            diffs.append(f"{d.mean():+.3f} [{lo:+.3f}, {hi:+.3f}]")
        print(f"| {name} - {baseline} | " + " | ".join(diffs) + " |")


def group_likelihoods(recs: dict[str, dict], group: str, name: str) -> np.ndarray:
    """Per scene holding the group: exp(mean log-likelihood of its scored entries)."""
    out = [
        math.exp(d["sum"] / d["n"])
        for r in recs.values()
        if (d := r["features"].get(group, {}).get(name)) and d["n"]
    ]
    return np.asarray(out)


def _pooled(recs: dict[str, dict], group: str, name: str, key: str) -> float:
    return sum(r["features"].get(group, {}).get(name, {}).get(key, 0) for r in recs.values())


def by_group(runs: dict[str, dict[str, dict]], baseline: str) -> None:
    """Per agent group and feature: likelihood (mean over the scenes holding the group) of
    every variant; for the baseline also the share of the log's scored entries in bins no
    simulated value reaches and their share of the lost log-likelihood."""
    groups = sorted({g for r in runs[baseline].values() for g in r["features"]})
    names = list(runs)
    print("\n### Likelihood by agent type and logged speed at the current step (m/s)\n")
    head = " | ".join(names)
    print(f"| group | feature | scenes | entries | {head} | uncovered | its share of -ll |")
    print("|---" * (len(names) + 6) + "|")
    for g in groups:
        for name in FEATURES:
            n = _pooled(runs[baseline], g, name, "n")
            if not n:
                continue
            cells = [f"{group_likelihoods(runs[v], g, name).mean():.3f}" for v in names]
            unc = _pooled(runs[baseline], g, name, "unc_n") / n
            lost = _pooled(runs[baseline], g, name, "sum")
            share = _pooled(runs[baseline], g, name, "unc_sum") / lost if lost else 0.0
            k = len(group_likelihoods(runs[baseline], g, name))
            print(f"| {g} | {name} | {k} | {int(n)} | " + " | ".join(cells), end="")
            print(f" | {unc:.3f} | {share:.2f} |")


def steps_table(runs: dict[str, dict[str, dict]], variant: str) -> None:
    """Mean per-step motion (one 0.1 s action) against the WOSAC features, sim and log."""
    recs = runs[variant]
    groups = sorted({g for r in recs.values() for g in r["steps"]})
    keys = list(next(r["steps"][g]["sim"] for r in recs.values() for g in r["steps"]))
    print(f"\n### One 0.1 s step against the WOSAC features ({variant} / log; means)\n")
    print("| group | " + " | ".join(k.replace("|", "\\|") for k in keys) + " |")
    print("|---" * (len(keys) + 1) + "|")
    for g in groups:
        cells = []
        for k in keys:
            pair = []
            for who in ("sim", "log"):
                s = sum(r["steps"].get(g, {}).get(who, {}).get(k, (0, 0))[0] for r in recs.values())
                n = sum(r["steps"].get(g, {}).get(who, {}).get(k, (0, 0))[1] for r in recs.values())
                pair.append(f"{s / n:.3g}" if n else "-")
            cells.append(" / ".join(pair))
        print(f"| {g} | " + " | ".join(cells) + " |")


def picture(runs: dict[str, dict[str, dict]], variants: list[str], path: Path) -> None:
    """Sim-vs-log histograms: one row per feature, one column per agent group; the log filled,
    each variant's simulations as a line; WOSAC bin edges dotted; log-density axis."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    config = get_config(VERSION)
    first = runs[variants[0]]
    groups = sorted({g for r in first.values() for g in r["features"]})
    fig, axes = plt.subplots(len(FEATURES), len(groups), figsize=(3.1 * len(groups), 10))
    axes = np.asarray(axes).reshape(len(FEATURES), len(groups))
    for i, name in enumerate(FEATURES):
        spec = getattr(config.histograms, name)
        edges = fine_edges(spec)
        for j, g in enumerate(groups):
            ax = axes[i, j]
            log = _summed(first, g, name, "log", len(edges) - 1)
            if log.sum() == 0:
                ax.axis("off")
                continue
            ax.stairs(log / log.sum(), edges, fill=True, alpha=0.4, label="log")
            for v in variants:
                sim = _summed(runs[v], g, name, "sim", len(edges) - 1)
                ax.stairs(sim / max(sim.sum(), 1), edges, lw=1.5, label=v)
            for e in spec.edges:
                ax.axvline(e, color="grey", lw=0.5, ls=":")
            ax.set_yscale("log")
            ax.set_ylim(1e-5, 1.0)
            ax.set_title(f"{g} m/s", fontsize=9)
            if j == 0:
                ax.set_ylabel(name.replace("_", " "), fontsize=9)
    axes[0, 0].legend(fontsize=7)
    fig.suptitle(f"Kinematic features, log vs simulation ({len(first)} scenes; share per bin)")
    fig.tight_layout()
    fig.savefig(path, dpi=70)
    plt.close(fig)


def _summed(recs: dict[str, dict], group: str, name: str, who: str, size: int) -> np.ndarray:
    out = np.zeros(size)
    for r in recs.values():
        d = r["features"].get(group, {}).get(name)
        if d and d[who]:
            out += np.asarray(d[who], float)
    return out


def report(args: argparse.Namespace) -> None:
    """Print the tables of the runs in ``args.folder``; draw the picture if asked."""
    runs = load_runs(Path(args.folder))
    if args.baseline not in runs:
        raise SystemExit(f"no {args.baseline}.jsonl in {args.folder}")
    overview(runs, args.baseline)
    by_group(runs, args.baseline)
    steps_table(runs, args.baseline)
    if args.png:
        picture(runs, args.png_variants.split(","), Path(args.png))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="roll out and record the variants")
    r.add_argument("--split", default="validation", choices=("validation", "held_out", "train"))
    r.add_argument("--variants", default="log,shipped", help="comma-separated variants")
    r.add_argument(
        "--scenes", default="::", help="python slice of the split's scenes, START:STOP:STEP"
    )
    r.add_argument("--samples", type=int, default=128, help="rollouts sampled per scene")
    r.add_argument("--keep", type=int, default=32, help="rollouts kept per scene")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--data", default=os.environ.get("TBSIM_WOMD_DIR", "../shared/data/womd"))
    r.add_argument("--out", required=True)
    r.add_argument("--cache", help="folder keeping the exact rollouts for later runs")
    q = sub.add_parser("report", help="tables and histograms of recorded runs")
    q.add_argument("folder")
    q.add_argument("--baseline", default="shipped")
    q.add_argument("--png", help="write the sim-vs-log histograms here")
    q.add_argument("--png-variants", default="shipped", help="simulations drawn in the picture")
    t = sub.add_parser("tracker", help="measure the tracker's white jitter (recording.TRACKER)")
    t.add_argument("--split", default="train", choices=("validation", "held_out", "train"))
    t.add_argument("--data", default=os.environ.get("TBSIM_WOMD_DIR", "../shared/data/womd"))
    sub.add_parser("variants", help="list the named variants")
    args = p.parse_args()
    if args.cmd == "run":
        run(args)
    elif args.cmd == "report":
        report(args)
    elif args.cmd == "tracker":
        tracker(args)
    else:
        for name, make in VARIANTS.items():
            print(f"{name:18s} {make().about}")


if __name__ == "__main__":
    main()
