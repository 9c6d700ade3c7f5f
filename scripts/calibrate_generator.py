"""Calibrate the generator's behaviour against the kinematics of the real training scenes.

1. Measures the real distributions (``tbsim_env.metrics.calibration``: linear speed and
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
from typing import Any

import numpy as np
from tqdm import tqdm

from tbsim_env.data.generator import LAYOUTS, generate_scenario
from tbsim_env.data.generator.behaviour import UNCALIBRATED, Behaviour
from tbsim_env.data.generator.recording import Recording
from tbsim_env.metrics.calibration import (
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
RECORDING_PY = REPO / "tbsim_env" / "data" / "generator" / "recording.py"
OUT = REPO / "docs" / "model_card" / "generator_calibration"
FIT_SEEDS = tuple(range(1000, 1025))
"""Generated scenes of the fit (``training_mix``: 5 per layout)."""
REPORT_SEEDS = tuple(range(2000, 2060))
"""Generated scenes of the report (12 per layout), none of the fit's."""
OBJECTIVE_SUBSET = {"vehicle": "moving", "pedestrian": "all", "cyclist": "moving"}
"""Tracks each type's behaviour is fitted on (see the module docstring)."""
SUBSETS = ("all", "moving")
VARIANTS = ("before", "after", "recorded")
"""Generated sides of the report: uncalibrated, calibrated behaviour, calibrated behaviour with
the fitted recording."""


@dataclass(frozen=True)
class Knob:
    """One searched parameter: a value in [lo, hi], set into a Behaviour by ``put``. The bounds
    keep the drivers physically plausible (e.g. time headways of 0.6-3.5 s), so that the fit
    cannot trade realism of behaviour for a closer histogram."""

    name: str
    lo: float
    hi: float
    start: float
    put: Callable[[Any, float], Any]


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


def _fine(field: str) -> Callable[[Recording, float], Recording]:
    """A setter putting the knob value into ``field`` of a Recording (five decimals: the jitter
    is a few millimetres or milliradians)."""
    return lambda r, x: dataclasses.replace(r, **{field: round(float(x), 5)})


REC_BASE = Recording(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.19, 0.125)
"""The search's starting point without jitter or parked vehicles. The velocity jitter is not
searched (the WOSAC features come from positions): it is the median scatter of the real train
tracks' logged speed around a 1 s quadratic fit (vehicles 0.16 m/s, pedestrians 0.11), divided
by 0.85 (the share of white noise such a fit leaves)."""
REC_KNOBS = (
    Knob("parked_occupancy", 0.0, 1.0, 0.5, _fine("parked_occupancy")),
    Knob("jitter_along", 0.0, 0.03, 0.012, _fine("jitter_along")),
    Knob("jitter_lateral", 0.0, 0.01, 0.004, _fine("jitter_lateral")),
    Knob("jitter_heading", 0.0, 0.003, 0.0014, _fine("jitter_heading")),
    Knob("ped_jitter", 0.0, 0.015, 0.007, _fine("ped_jitter")),
    Knob("ped_jitter_heading", 0.0, 0.55, 0.27, _fine("ped_jitter_heading")),
    Knob("ped_walking_jitter_heading", 0.0, 0.02, 0.008, _fine("ped_walking_jitter_heading")),
)
"""The recording's knobs. Start values: the jitter measured on the real train tracks (median
residual of a 1 s quadratic fit of moving vehicles' and pedestrians' poses; the median heading
scatter of standing pedestrians), half the lot slots taken. The jitter stays within twice the
measured values, so that it cannot stand in for driving the generator does not reproduce (the
histogram distance alone would take more heading jitter for the turns of real vehicles)."""


def recording_of(x: np.ndarray) -> Recording:
    """The Recording of knob values x [len(REC_KNOBS)]."""
    r = REC_BASE
    for knob, value in zip(REC_KNOBS, x):
        r = knob.put(r, float(value))
    return r


def behaviour_of(x: np.ndarray) -> Behaviour:
    """The Behaviour of knob values x [K] (UNCALIBRATED for the knobs' start values)."""
    b = UNCALIBRATED
    for knob, value in zip(KNOBS, x):
        b = knob.put(b, float(value))
    return b


def generated_samples(
    b: Behaviour,
    seeds: tuple[int, ...],
    progress: bool = False,
    recording: Recording | None = None,
) -> dict[str, Samples]:
    """Pooled samples of the generated scenes of ``seeds`` (the ``training_mix`` layout of
    each seed) under ``b`` and ``recording``, per subset."""
    it = tqdm(seeds, desc="generate", leave=False) if progress else seeds
    scenes = [
        generate_scenario(LAYOUTS[s % len(LAYOUTS)], s, behaviour=b, recording=recording)
        for s in it
    ]
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
    cost: Callable[[np.ndarray], float], max_evals: int, knobs: tuple[Knob, ...] = KNOBS
) -> tuple[np.ndarray, float, int]:
    """Deterministic coordinate search over ``knobs`` within their bounds.

    Each knob in turn tries a step up and a step down (a quarter of its range at first) and
    keeps a better value; after a pass without improvement the steps halve. Stops after
    ``max_evals`` evaluations or when the steps fall below 1/64 of the ranges.

    Returns:
        (best knob values [K], best cost, evaluations used).
    """
    lo = np.array([k.lo for k in knobs])
    hi = np.array([k.hi for k in knobs])
    x = np.array([k.start for k in knobs])
    best = cost(x)
    step = 0.25 * (hi - lo)
    evals = 1
    bar = tqdm(total=max_evals, desc="search", initial=1)
    while evals < max_evals and (step > (hi - lo) / 64).any():
        improved = False
        for k in range(len(knobs)):
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


def _format(name: str, value: Any) -> str:
    """Python source of ``NAME = Cls(...)`` for a dataclass value."""
    lines = [f"{name} = {type(value).__name__}("]
    for f in dataclasses.fields(value):
        v = getattr(value, f.name)
        text = f"({v[0]!r}, {v[1]!r})" if isinstance(v, tuple) else repr(v)
        lines.append(f"    {f.name}={text},")
    return "\n".join(lines + [")"])


def write_block(name: str, value: Any, path: Path) -> None:
    """Replace the ``# BEGIN NAME`` ... ``# END NAME`` block of ``path`` with ``value``."""
    src = path.read_text()
    block = f"# BEGIN {name}\n{_format(name, value)}\n# END {name}"
    new, n = re.subn(rf"# BEGIN {name}\n.*?# END {name}", block, src, flags=re.S)
    if n != 1:
        raise RuntimeError(f"{path}: no single {name} block")
    path.write_text(new)


def report(real: dict[str, dict[str, Samples]], generated: dict[str, dict[str, Samples]]) -> dict:
    """distances[split][subset][type][feature] = {variant: distance, "ratio": after / before,
    "ratio_recorded": recorded / before} for the ``VARIANTS`` of ``generated``."""
    out: dict = {}
    for split, r in real.items():
        out[split] = {}
        for sub in SUBSETS:
            d = {v: distances(generated[v][sub], r[sub]) for v in VARIANTS}
            out[split][sub] = {
                n: {
                    f: {
                        **{v: d[v][n][f] for v in VARIANTS},
                        "ratio": d["after"][n][f] / d["before"][n][f],
                        "ratio_recorded": d["recorded"][n][f] / d["before"][n][f],
                    }
                    for f in d["before"][n]
                }
                for n in AGENT_TYPES
            }
    return out


def type_ratios(dist: dict) -> dict:
    """Per split, subset and type, the mean over features of after / before and of recorded /
    before."""
    return {
        split: {
            sub: {n: {k: float(np.mean([v[k] for v in d[n].values()])) for k in RATIOS} for n in d}
            for sub, d in subs.items()
        }
        for split, subs in dist.items()
    }


RATIOS = ("ratio", "ratio_recorded")


def normalised(d: Distances, name: str) -> float:
    """Range-normalised distance of one type: mean over its features of distance / range."""
    return float(np.mean([d[name][f.name] / (f.hi - f.lo) for f in FEATURES[name]]))


def type_normalised(dist: dict) -> dict:
    """Per split, subset and type, the mean over features of distance / histogram range, per
    variant (one number per type; the issue's "distance per type")."""
    out: dict = {}
    for split, subs in dist.items():
        out[split] = {}
        for sub, d in subs.items():
            out[split][sub] = {}
            for n in AGENT_TYPES:
                width = {f.name: f.hi - f.lo for f in FEATURES[n]}
                out[split][sub][n] = {
                    k: float(np.mean([v[k] / width[f] for f, v in d[n].items()])) for k in VARIANTS
                }
    return out


def write_markdown(doc: dict, path: Path) -> None:
    """The short tables of docs/model_card/generator_calibration.md."""
    d, ratios = doc["distances"], doc["type_ratio"]
    rows = [
        "# Generator calibration against real kinematics",
        "",
        "`scripts/calibrate_generator.py` fits the generator to the real **train** scenes of "
        f"`real_splits.json` ({doc['real_scenes']['train']} scenes); the "
        f"{doc['real_scenes']['validation']} **validation** scenes are only measured. Two "
        "stages: the agents' behaviour (`tbsim_env/data/generator/behaviour.py`, `CALIBRATED`, "
        "the default of `generate_scenario`), fitted on moving tracks for vehicles and cyclists "
        "and all tracks for pedestrians (marked *); then, with that behaviour, the recording "
        "(`tbsim_env/data/generator/recording.py`, `RECORDED`: parked vehicles in lot rows "
        "behind the sidewalks and the tracker's jitter, `generate_scenario(..., "
        "recording=RECORDED)`), fitted on all tracks of every type. "
        f"Distance: {doc['metric']}. Generated side: {len(REPORT_SEEDS)} scenes "
        f"(`training_mix` seeds {REPORT_SEEDS[0]}-{REPORT_SEEDS[-1]}; the fits used seeds "
        f"{FIT_SEEDS[0]}-{FIT_SEEDS[-1]}). Columns: before calibration, calibrated behaviour, "
        "calibrated behaviour + recording.",
        "",
        "| type | feature (unit) | tracks | train before | after | + recording | "
        "val before | after | + recording |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for n in AGENT_TYPES:
        for spec in FEATURES[n]:
            for sub in SUBSETS:
                star = "*" if OBJECTIVE_SUBSET[n] == sub else ""
                cells = [
                    f"{d[split][sub][n][spec.name][v]:.3f}"
                    for split in ("train", "validation")
                    for v in VARIANTS
                ]
                rows.append(
                    f"| {n} | {spec.name} ({spec.unit}) | {sub}{star} | " + " | ".join(cells) + " |"
                )
    norm = doc["type_normalised"]
    rows += ["", "Per type: mean over features of distance / histogram range (before -> after ->"]
    rows += ["+ recording), and mean over features of distance / distance before:", ""]
    rows += [
        "| type | tracks | train | validation | train: after, + recording "
        "| val: after, + recording |"
    ]
    rows += ["|---|---|---|---|---|---|"]
    for n in AGENT_TYPES:
        for sub in SUBSETS:
            cells = [
                " -> ".join(f"{norm[sp][sub][n][v]:.4f}" for v in VARIANTS)
                for sp in ("train", "validation")
            ]
            cells += [
                f"{ratios[sp][sub][n]['ratio']:.2f}, {ratios[sp][sub][n]['ratio_recorded']:.2f}"
                for sp in ("train", "validation")
            ]
            rows.append(f"| {n} | {sub} | " + " | ".join(cells) + " |")
    rows += ["", "Behaviour parameters (before -> after):", "", "| parameter | before | after |"]
    rows += ["|---|---|---|"]
    for k, v0 in doc["parameters"]["before"].items():
        rows.append(f"| {k} | {v0} | {doc['parameters']['after'][k]} |")
    rows += ["", "Recording (fitted; the search started from the values measured on the real "]
    rows += [
        "train tracks, the first column):",
        "",
        "| parameter | start | fitted |",
        "|---|---|---|",
    ]
    for knob in REC_KNOBS:
        rows.append(f"| {knob.name} | {knob.start} | {doc['parameters']['recording'][knob.name]} |")
    for name in ("speed_jitter", "ped_speed_jitter"):
        value = doc["parameters"]["recording"][name]
        rows.append(f"| {name} | {value} (measured) | not fitted |")
    rows += ["", *doc["notes"], ""]
    path.write_text("\n".join(rows))


def plot(real: Samples, generated: dict[str, Samples], path: Path, title: str) -> None:
    """Histograms per type (rows) and feature (columns): real train and the ``VARIANTS``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ncol = max(len(v) for v in FEATURES.values())
    fig, axes = plt.subplots(len(AGENT_TYPES), ncol, figsize=(4 * ncol, 3 * len(AGENT_TYPES)))
    styles = {"before": "C3--", "after": "C0-", "recorded": "C2-"}
    for i, n in enumerate(AGENT_TYPES):
        for j in range(ncol):
            ax = axes[i, j]
            if j >= len(FEATURES[n]):
                ax.axis("off")
                continue
            spec = FEATURES[n][j]
            mid = 0.5 * (spec.edges[1:] + spec.edges[:-1])
            ax.plot(mid, histogram(real[n][spec.name], spec), "k-", label="real train", lw=1.2)
            for v in VARIANTS:
                label = "+ recording" if v == "recorded" else v
                ax.plot(
                    mid, histogram(generated[v][n][spec.name], spec), styles[v], label=label, lw=1.2
                )
            ax.set_yscale("log")
            ax.set_title(f"{n}: {spec.name}", fontsize=9)
            ax.set_xlabel(spec.unit, fontsize=8)
    axes[0, 0].legend(fontsize=8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


NOTES = [
    "What the calibrated generator still does not reproduce:",
    "",
    "* Parked vehicles stand in lot rows behind the sidewalks only: real scenes also park them "
    "along the kerb inside the road edges, which the layouts have no room for.",
    "* The jitter is white and the same for every track of a type up to its log-normal factor; "
    "real tracking noise grows with the range to the SDC and with occlusion.",
    "* Crossing pedestrians turn at the corners of their paths in one step (the isolated "
    "spikes at the ends of the pedestrian angular histograms).",
    "* Cyclists: 23 real train tracks; no change of their behaviour parameters improved the "
    "fit, so they keep the hand-set values.",
    "* Headway: the gap to the followed vehicle moves little either way (table); the fitted "
    "headway and gap parameters mostly trade it against speed and acceleration.",
]


def fit(real_train: dict[str, Samples], max_evals: int) -> tuple[Behaviour, dict]:
    """Search the behaviour knobs on ``FIT_SEEDS``: (fitted behaviour, fit summary)."""
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


def fit_recording(
    real_train: dict[str, Samples], behaviour: Behaviour, max_evals: int
) -> tuple[Recording, dict]:
    """Search the recording knobs on ``FIT_SEEDS`` with ``behaviour``, on all tracks of every
    type, against the uncalibrated generator: (fitted recording, fit summary)."""
    d0 = distances(generated_samples(UNCALIBRATED, FIT_SEEDS)["all"], real_train["all"])

    def cost(x: np.ndarray) -> float:
        gen = generated_samples(behaviour, FIT_SEEDS, recording=recording_of(x))
        d = distances(gen["all"], real_train["all"])
        return float(np.mean([normalised(d, n) / normalised(d0, n) for n in AGENT_TYPES]))

    x, best, evals = coordinate_search(cost, max_evals, REC_KNOBS)
    summary = {
        "objective": "mean over types of the range-normalised distance (mean over features of "
        "distance / histogram range) over the same before calibration, all tracks, on the fit "
        "seeds and the real train scenes",
        "evaluations": evals,
        "objective_after": best,
    }
    return recording_of(x), summary


def write_report(
    real: dict[str, dict[str, Samples]], fitted: Behaviour, recording: Recording, summary: dict
) -> None:
    """docs/model_card/generator_calibration.{json,md,png} for ``fitted`` and ``recording`` on
    REPORT_SEEDS."""
    generated = {
        "before": generated_samples(UNCALIBRATED, REPORT_SEEDS, progress=True),
        "after": generated_samples(fitted, REPORT_SEEDS, progress=True),
        "recorded": generated_samples(fitted, REPORT_SEEDS, True, recording),
    }
    dist = report(real, generated)
    rec = dataclasses.asdict(recording)
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
            "recording": rec,
        },
        "distances": dist,
        "type_ratio": type_ratios(dist),
        "type_normalised": type_normalised(dist),
        "notes": NOTES,
    }
    OUT.with_suffix(".json").write_text(json.dumps(doc, indent=1) + "\n")
    write_markdown(doc, OUT.with_suffix(".md"))
    title = (
        "Kinematic histograms, all tracks: real train (black), generator before (red), "
        "calibrated (blue), calibrated + recording (green)"
    )
    plot(
        real["train"]["all"],
        {v: g["all"] for v, g in generated.items()},
        OUT.with_suffix(".png"),
        title,
    )


def main() -> None:
    default_dir = os.environ.get("TBSIM_WOMD_DIR", str(REPO.parent / "shared" / "data" / "womd"))
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--womd-dir", type=Path, default=Path(default_dir))
    ap.add_argument("--max-evals", type=int, default=90, help="per stage")
    ap.add_argument(
        "--stages",
        default="behaviour,recording",
        help="stages to fit, comma separated (the others keep the values in the code)",
    )
    ap.add_argument("--no-write", action="store_true", help="search and print only")
    ap.add_argument(
        "--report-only",
        action="store_true",
        help="no search: rewrite the report for CALIBRATED and RECORDED as they are in the code",
    )
    args = ap.parse_args()
    from tbsim_env.data.generator.behaviour import CALIBRATED
    from tbsim_env.data.generator.recording import RECORDED

    real = {s: real_samples(args.womd_dir, s) for s in ("train", "validation")}
    old = (
        json.loads(OUT.with_suffix(".json").read_text())
        if OUT.with_suffix(".json").exists()
        else {}
    )
    summary = old.get("fit", {})
    fitted, recording = CALIBRATED, RECORDED
    stages = set() if args.report_only else set(args.stages.split(","))
    if "behaviour" in stages:
        fitted, summary = fit(real["train"], args.max_evals)
        print(
            f"behaviour objective {summary['objective_after']:.3f} "
            f"after {summary['evaluations']} evaluations"
        )
        print(_format("CALIBRATED", fitted))
    if "recording" in stages:
        recording, rec_summary = fit_recording(real["train"], fitted, args.max_evals)
        summary = {**summary, "recording": rec_summary}
        print(
            f"recording objective {rec_summary['objective_after']:.3f} "
            f"after {rec_summary['evaluations']} evaluations"
        )
        print(_format("RECORDED", recording))
    if args.no_write:
        return
    if "behaviour" in stages:
        write_block("CALIBRATED", fitted, BEHAVIOUR_PY)
    if "recording" in stages:
        write_block("RECORDED", recording, RECORDING_PY)
    write_report(real, fitted, recording, summary)
    print(f"wrote {OUT.name}.json/.md/.png")


if __name__ == "__main__":
    main()
