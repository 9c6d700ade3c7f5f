"""Calibrate the generator's behaviour against the kinematics of the real training scenes.

1. Measures the real distributions (``tbsim_env.data.generator.calibration``: linear speed and
   acceleration, angular speed and acceleration per agent type, and the vehicles' headway) on
   the "train" scenes of docs/model_card/real_splits.json, and on the "validation" scenes for
   the report only (nothing is tuned on them).
2. Searches the behaviour parameters (``Behaviour``: factors on the drivers' desired speeds,
   acceleration, braking, headway and standstill gap, the bend acceleration, the cyclists'
   speed and acceleration, the pedestrians' walking speeds, standing share, speed fluctuation
   and sway) by a seeded coordinate search from ``UNCALIBRATED`` that minimises the mean, over
   agent types, of the mean over features of distance / distance before calibration, on
   generated scenes of fixed seeds (``FIT_SEEDS``). Vehicles and cyclists are compared on
   moving tracks (the generator has no parked vehicles, so fitting all tracks would slow its
   drivers down toward the real parked mass), pedestrians on all tracks (the standing share
   is a parameter).
3. Writes the fitted values into tbsim_env/data/generator/behaviour.py (the CALIBRATED block),
   and docs/model_card/generator_calibration.{json,md,png}: the per-type, per-feature
   distances before and after, on train and validation, for all tracks and moving tracks,
   measured on other generated seeds (``REPORT_SEEDS``) than the fit's.

    OMP_NUM_THREADS=1 python scripts/calibrate_generator.py [--max-evals 90]
        [--womd-dir ../shared/data/womd] [--no-write]

Deterministic: same data, same seeds, same result (a few minutes on one core).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from tbsim_env.data.generator import LAYOUTS, generate_scenario
from tbsim_env.data.generator.behaviour import UNCALIBRATED, Behaviour
from tbsim_env.data.generator.calibration import (
    AGENT_TYPES,
    FEATURES,
    Distances,
    Samples,
    distances,
    histogram,
    load_entries,
    pool,
    scene_features,
    split_entries,
)

REPO = Path(__file__).resolve().parents[1]
SPLITS = REPO / "docs" / "model_card" / "real_splits.json"
BEHAVIOUR_PY = REPO / "tbsim_env" / "data" / "generator" / "behaviour.py"
OUT = REPO / "docs" / "model_card" / "generator_calibration"
FIT_SEEDS = tuple(range(1000, 1025))
"""Generated scenes of the fit (``training_mix``: 5 per layout)."""
REPORT_SEEDS = tuple(range(2000, 2060))
"""Generated scenes of the report (12 per layout), none of the fit's."""
OBJECTIVE_SUBSET = {"vehicle": "moving", "pedestrian": "all", "cyclist": "moving"}
"""Tracks each type is fitted on (see the module docstring)."""
SUBSETS = ("all", "moving")


@dataclass(frozen=True)
class Knob:
    """One searched parameter: a value in [lo, hi], set into a Behaviour by ``put``. The bounds
    keep the drivers physically plausible (e.g. time headways of 0.6-3.5 s), so that the fit
    cannot trade realism of behaviour for a closer histogram."""

    name: str
    lo: float
    hi: float
    start: float
    put: Callable[[Behaviour, float], Behaviour]


def _scaled(field: str) -> Callable[[Behaviour, float], Behaviour]:
    """A setter multiplying the UNCALIBRATED range ``field`` by the knob value."""

    def put(b: Behaviour, m: float) -> Behaviour:
        lo, hi = getattr(UNCALIBRATED, field)
        return dataclasses.replace(b, **{field: (round(lo * m, 3), round(hi * m, 3))})

    return put


def _value(field: str) -> Callable[[Behaviour, float], Behaviour]:
    """A setter putting the knob value into scalar ``field``."""
    return lambda b, x: dataclasses.replace(b, **{field: round(float(x), 3)})


def _both(first: str, second: str) -> Callable[[Behaviour, float], Behaviour]:
    """A setter scaling two UNCALIBRATED ranges by the same factor."""
    return lambda b, m: _scaled(second)(_scaled(first)(b, m), m)


KNOBS = (
    Knob("speed_scale", 0.7, 1.4, 1.0, _value("speed_scale")),
    Knob("max_accel x", 0.6, 1.8, 1.0, _scaled("max_accel")),
    Knob("comfort_decel x", 0.6, 1.8, 1.0, _scaled("comfort_decel")),
    Knob("time_headway x", 0.7, 1.6, 1.0, _scaled("time_headway")),
    Knob("min_gap x", 0.6, 1.6, 1.0, _scaled("min_gap")),
    Knob("lateral_accel", 1.5, 3.5, 2.0, _value("lateral_accel")),
    Knob("ped_standing_share", 0.0, 0.8, 0.0, _value("ped_standing_share")),
    Knob("walking speeds x", 0.6, 1.4, 1.0, _both("ped_speed", "crossing_speed")),
    Knob("ped_speed_sigma", 0.0, 0.8, 0.0, _value("ped_speed_sigma")),
    Knob("ped_sway_sigma", 0.0, 0.3, 0.0, _value("ped_sway_sigma")),
    Knob("ped_wander_tau", 0.2, 3.0, 1.0, _value("ped_wander_tau")),
    Knob("cyclist_speed x", 0.6, 1.5, 1.0, _scaled("cyclist_speed")),
    Knob("cyclist accel/decel x", 0.5, 2.5, 1.0, _both("cyclist_accel", "cyclist_decel")),
)


def behaviour_of(x: np.ndarray) -> Behaviour:
    """The Behaviour of knob values x [K] (UNCALIBRATED for the knobs' start values)."""
    b = UNCALIBRATED
    for knob, value in zip(KNOBS, x):
        b = knob.put(b, float(value))
    return b


def generated_samples(
    b: Behaviour, seeds: tuple[int, ...], progress: bool = False
) -> dict[str, Samples]:
    """Pooled samples of the generated scenes of ``seeds`` (the ``training_mix`` layout of
    each seed) under ``b``, per subset."""
    it = tqdm(seeds, desc="generate", leave=False) if progress else seeds
    scenes = [generate_scenario(LAYOUTS[s % len(LAYOUTS)], s, behaviour=b) for s in it]
    return {sub: pool(scene_features(sc, sub == "moving") for sc in scenes) for sub in SUBSETS}


def real_samples(womd_dir: Path, split: str) -> dict[str, Samples]:
    """Pooled samples of the real scenes of ``split``, per subset."""
    scenes = load_entries(split_entries(SPLITS, split), womd_dir)
    return {sub: pool(scene_features(sc, sub == "moving") for sc in scenes) for sub in SUBSETS}


def objective_distances(gen: dict[str, Samples], real: dict[str, Samples]) -> Distances:
    """Per type, the distances on the type's fitted subset (``OBJECTIVE_SUBSET``)."""
    by_sub = {sub: distances(gen[sub], real[sub]) for sub in SUBSETS}
    return {name: by_sub[OBJECTIVE_SUBSET[name]][name] for name in AGENT_TYPES}


def objective(d: Distances, d0: Distances) -> float:
    """Mean over agent types of the mean over features of d / d0 (1 before calibration)."""
    per_type = [np.mean([d[n][f] / d0[n][f] for f in d[n]]) for n in AGENT_TYPES]
    return float(np.mean(per_type))


def coordinate_search(
    cost: Callable[[np.ndarray], float], max_evals: int
) -> tuple[np.ndarray, float, int]:
    """Deterministic coordinate search over ``KNOBS`` within their bounds.

    Each knob in turn tries a step up and a step down (a quarter of its range at first) and
    keeps a better value; after a pass without improvement the steps halve. Stops after
    ``max_evals`` evaluations or when the steps fall below 1/64 of the ranges.

    Returns:
        (best knob values [K], best cost, evaluations used).
    """
    lo = np.array([k.lo for k in KNOBS])
    hi = np.array([k.hi for k in KNOBS])
    x = np.array([k.start for k in KNOBS])
    best = cost(x)
    step = 0.25 * (hi - lo)
    evals = 1
    bar = tqdm(total=max_evals, desc="search", initial=1)
    while evals < max_evals and (step > (hi - lo) / 64).any():
        improved = False
        for k in range(len(KNOBS)):
            for sign in (1.0, -1.0):
                y = x.copy()
                y[k] = np.clip(x[k] + sign * step[k], lo[k], hi[k])
                if y[k] == x[k] or evals >= max_evals:
                    continue
                c = cost(y)
                evals += 1
                bar.update(1)
                bar.set_postfix(cost=f"{min(best, c):.3f}")
                if c < best:
                    x, best, improved = y, c, True
                    break
        if not improved:
            step = step / 2.0
    bar.close()
    return x, best, evals


def _format_behaviour(b: Behaviour) -> str:
    """Python source of ``CALIBRATED = Behaviour(...)``."""
    lines = ["CALIBRATED = Behaviour("]
    for f in dataclasses.fields(b):
        v = getattr(b, f.name)
        text = f"({v[0]!r}, {v[1]!r})" if isinstance(v, tuple) else repr(v)
        lines.append(f"    {f.name}={text},")
    return "\n".join(lines + [")"])


def write_behaviour(b: Behaviour, path: Path = BEHAVIOUR_PY) -> None:
    """Replace the CALIBRATED block of behaviour.py with ``b``."""
    src = path.read_text()
    block = f"# BEGIN CALIBRATED\n{_format_behaviour(b)}\n# END CALIBRATED"
    new, n = re.subn(r"# BEGIN CALIBRATED\n.*?# END CALIBRATED", block, src, flags=re.S)
    if n != 1:
        raise RuntimeError(f"{path}: no single CALIBRATED block")
    path.write_text(new)


def report(
    real: dict[str, dict[str, Samples]], before: dict[str, Samples], after: dict[str, Samples]
) -> dict:
    """distances[split][subset][type][feature] = {"before", "after", "ratio"}."""
    out: dict = {}
    for split, r in real.items():
        out[split] = {}
        for sub in SUBSETS:
            d0, d1 = distances(before[sub], r[sub]), distances(after[sub], r[sub])
            out[split][sub] = {
                n: {
                    f: {"before": d0[n][f], "after": d1[n][f], "ratio": d1[n][f] / d0[n][f]}
                    for f in d0[n]
                }
                for n in AGENT_TYPES
            }
    return out


def type_ratios(dist: dict) -> dict:
    """Per split, subset and type, the mean over features of after / before."""
    return {
        split: {
            sub: {n: float(np.mean([v["ratio"] for v in d[n].values()])) for n in d}
            for sub, d in subs.items()
        }
        for split, subs in dist.items()
    }


def type_normalised(dist: dict) -> dict:
    """Per split, subset and type, the mean over features of distance / histogram range,
    before and after (one number per type; the issue's "distance per type")."""
    out: dict = {}
    for split, subs in dist.items():
        out[split] = {}
        for sub, d in subs.items():
            out[split][sub] = {}
            for n in AGENT_TYPES:
                width = {f.name: f.hi - f.lo for f in FEATURES[n]}
                out[split][sub][n] = {
                    k: float(np.mean([v[k] / width[f] for f, v in d[n].items()]))
                    for k in ("before", "after")
                }
    return out


def write_markdown(doc: dict, path: Path) -> None:
    """The short table of docs/model_card/generator_calibration.md."""
    d, ratios = doc["distances"], doc["type_ratio"]
    rows = [
        "# Generator calibration against real kinematics",
        "",
        f"`scripts/calibrate_generator.py` fits the generator's behaviour parameters "
        f"(`tbsim_env/data/generator/behaviour.py`, `CALIBRATED`) to the real **train** scenes "
        f"of `real_splits.json` ({doc['real_scenes']['train']} scenes); the "
        f"{doc['real_scenes']['validation']} **validation** scenes are only measured. "
        f"Distance: {doc['metric']}. Generated side: {len(REPORT_SEEDS)} scenes "
        f"(`training_mix` seeds {REPORT_SEEDS[0]}-{REPORT_SEEDS[-1]}; the fit used seeds "
        f"{FIT_SEEDS[0]}-{FIT_SEEDS[-1]}). Fitted on moving tracks for vehicles and cyclists, "
        "all tracks for pedestrians (marked *).",
        "",
        "| type | feature (unit) | tracks | train before | train after | val before | val after |",
        "|---|---|---|---|---|---|---|",
    ]
    for n in AGENT_TYPES:
        for spec in FEATURES[n]:
            for sub in SUBSETS:
                star = "*" if OBJECTIVE_SUBSET[n] == sub else ""
                tr, va = d["train"][sub][n][spec.name], d["validation"][sub][n][spec.name]
                rows.append(
                    f"| {n} | {spec.name} ({spec.unit}) | {sub}{star} | {tr['before']:.3f} | "
                    f"{tr['after']:.3f} | {va['before']:.3f} | {va['after']:.3f} |"
                )
    norm = doc["type_normalised"]
    rows += ["", "Per type: mean over features of distance / histogram range (before -> after),"]
    rows += ["and mean over features of after / before:", ""]
    rows += ["| type | tracks | train | validation | train after/before | val after/before |"]
    rows += ["|---|---|---|---|---|---|"]
    for n in AGENT_TYPES:
        for sub in SUBSETS:
            tr, va = norm["train"][sub][n], norm["validation"][sub][n]
            rows.append(
                f"| {n} | {sub} | {tr['before']:.4f} -> {tr['after']:.4f} | "
                f"{va['before']:.4f} -> {va['after']:.4f} | {ratios['train'][sub][n]:.2f} | "
                f"{ratios['validation'][sub][n]:.2f} |"
            )
    rows += ["", "Parameters (before -> after):", "", "| parameter | before | after |"]
    rows += ["|---|---|---|"]
    for k, v0 in doc["parameters"]["before"].items():
        rows.append(f"| {k} | {v0} | {doc['parameters']['after'][k]} |")
    rows += ["", *doc["notes"], ""]
    path.write_text("\n".join(rows))


def plot(real: Samples, before: Samples, after: Samples, path: Path, title: str) -> None:
    """Histograms per type (rows) and feature (columns): real train, before, after."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ncol = max(len(v) for v in FEATURES.values())
    fig, axes = plt.subplots(len(AGENT_TYPES), ncol, figsize=(4 * ncol, 3 * len(AGENT_TYPES)))
    for i, n in enumerate(AGENT_TYPES):
        for j in range(ncol):
            ax = axes[i, j]
            if j >= len(FEATURES[n]):
                ax.axis("off")
                continue
            spec = FEATURES[n][j]
            mid = 0.5 * (spec.edges[1:] + spec.edges[:-1])
            for s, label, style in ((real, "real train", "k-"), (before, "before", "C3--")):
                ax.plot(mid, histogram(s[n][spec.name], spec), style, label=label, lw=1.2)
            ax.plot(mid, histogram(after[n][spec.name], spec), "C0-", label="after", lw=1.2)
            ax.set_yscale("log")
            ax.set_title(f"{n}: {spec.name}", fontsize=9)
            ax.set_xlabel(spec.unit, fontsize=8)
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


NOTES = [
    "What the generator does not reproduce:",
    "",
    "* Parked vehicles: it has none. On the real train scenes about 60% of the vehicle steps "
    "belong to tracks that never move 2 m (about 20% in generated scenes: vehicles waiting at "
    "lights), so the all-tracks vehicle speed distance stays large; that is why vehicles are "
    "fitted on moving tracks.",
    "* Tracking noise: generated tracks are exact, while the real logs jitter. The long tails "
    "of the real angular speed and acceleration (all types) and much of the real acceleration "
    "spread come from it; no behaviour parameter moves those distances. For the same reason "
    "the fit keeps no standing sidewalk pedestrians (a noise-free standing pedestrian adds an "
    "exact-zero acceleration spike that costs more than its zero speeds gain) and no sideways "
    "sway (any sway large enough to matter makes the yaw rate far noisier than the logs).",
    "* Crossing pedestrians turn at the corners of their paths in one step (the isolated "
    "spikes at the ends of the pedestrian angular histograms).",
    "* Cyclists: 23 real train tracks; no change of their parameters improved the fit, so they "
    "keep the hand-set values.",
    "* Headway: the gap to the followed vehicle moves little either way (table); the fitted "
    "headway and gap parameters mostly trade it against speed and acceleration.",
]


def fit(real_train: dict[str, Samples], max_evals: int) -> tuple[Behaviour, dict]:
    """Search the knobs on ``FIT_SEEDS``: (fitted behaviour, fit summary)."""
    d0 = objective_distances(generated_samples(UNCALIBRATED, FIT_SEEDS), real_train)

    def cost(x: np.ndarray) -> float:
        gen = generated_samples(behaviour_of(x), FIT_SEEDS)
        return objective(objective_distances(gen, real_train), d0)

    x, best, evals = coordinate_search(cost, max_evals)
    summary = {
        "objective_subset": OBJECTIVE_SUBSET,
        "objective": "mean over types of the mean over features of distance / distance "
        "before calibration, on the fit seeds and the real train scenes",
        "evaluations": evals,
        "objective_before": 1.0,
        "objective_after": best,
    }
    return behaviour_of(x), summary


def write_report(real: dict[str, dict[str, Samples]], fitted: Behaviour, summary: dict) -> None:
    """docs/model_card/generator_calibration.{json,md,png} for ``fitted`` on REPORT_SEEDS."""
    before = generated_samples(UNCALIBRATED, REPORT_SEEDS, progress=True)
    after = generated_samples(fitted, REPORT_SEEDS, progress=True)
    dist = report(real, before, after)
    doc = {
        "metric": "Wasserstein-1 distance between fixed-bin histograms (values clipped into "
        "the range), in the feature's unit",
        "features": {n: [dataclasses.asdict(f) for f in FEATURES[n]] for n in AGENT_TYPES},
        "real_scenes": {s: len(split_entries(SPLITS, s)) for s in ("train", "validation")},
        "generated_seeds": {
            "fit": [FIT_SEEDS[0], FIT_SEEDS[-1]],
            "report": [REPORT_SEEDS[0], REPORT_SEEDS[-1]],
        },
        "fit": summary,
        "parameters": {
            "before": dataclasses.asdict(UNCALIBRATED),
            "after": dataclasses.asdict(fitted),
        },
        "distances": dist,
        "type_ratio": type_ratios(dist),
        "type_normalised": type_normalised(dist),
        "notes": NOTES,
    }
    OUT.with_suffix(".json").write_text(json.dumps(doc, indent=1) + "\n")
    write_markdown(doc, OUT.with_suffix(".md"))
    title = (
        "Kinematic histograms, all tracks: real train (black), generator before (red) and "
        "after (blue) calibration"
    )
    plot(real["train"]["all"], before["all"], after["all"], OUT.with_suffix(".png"), title)


def main() -> None:
    default_dir = os.environ.get("TBSIM_WOMD_DIR", str(REPO.parent / "shared" / "data" / "womd"))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--womd-dir", type=Path, default=Path(default_dir))
    ap.add_argument("--max-evals", type=int, default=90)
    ap.add_argument("--no-write", action="store_true", help="search and print only")
    ap.add_argument(
        "--report-only",
        action="store_true",
        help="no search: rewrite the report for the CALIBRATED behaviour now in behaviour.py",
    )
    args = ap.parse_args()
    real = {s: real_samples(args.womd_dir, s) for s in ("train", "validation")}
    if args.report_only:
        from tbsim_env.data.generator.behaviour import CALIBRATED

        old = (
            json.loads(OUT.with_suffix(".json").read_text())
            if OUT.with_suffix(".json").exists()
            else {}
        )
        write_report(real, CALIBRATED, old.get("fit", {}))
        print(f"wrote {OUT.name}.json/.md/.png")
        return
    fitted, summary = fit(real["train"], args.max_evals)
    print(f"objective {summary['objective_after']:.3f} after {summary['evaluations']} evaluations")
    print(_format_behaviour(fitted))
    if args.no_write:
        return
    write_behaviour(fitted)
    write_report(real, fitted, summary)
    print(f"wrote {BEHAVIOUR_PY.name} and {OUT.name}.json/.md/.png")


if __name__ == "__main__":
    main()
