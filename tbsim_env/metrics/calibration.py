"""Kinematic distributions of scenes per agent type, and a distance between them.

Used to calibrate the generator against real WOMD scenes (``scripts/calibrate_generator.py``)
and by the tests that keep it calibrated. Real and generated scenes go through the same code:

* per track and step, from the logged box centre and heading on the 0.1 s grid, the WOSAC
  kinematic features (``metrics.wosac.features_kinematic``: central differences): linear speed
  (m/s), linear acceleration (m/s^2), angular speed (rad/s) and angular acceleration (rad/s^2),
  kept where WOSAC scores them (the neighbouring steps are valid);
* for vehicles, the headway: the bumper-to-bumper gap (m) to the object followed in front, by
  the WOSAC time-to-collision rule (ahead, heading within 75 degrees, laterally overlapping),
  kept while the vehicle moves faster than ``HEADWAY_MIN_SPEED`` and the gap is below
  ``HEADWAY_MAX_GAP``.

With ``moving_only``, tracks that never leave a ``STATIC_MAX_DISPLACEMENT`` circle around their
first valid position (parked vehicles, standing pedestrians) are left out, on both sides.

Every valid step of every track of a type is one sample (steps pooled over scenes). A feature's
distribution is a histogram over fixed bins (``FEATURES``; values outside are counted in the end
bins) and the distance between two histograms is the 1-D Wasserstein-1 distance (earth mover's
distance) between them, in the feature's unit: the integral of |CDF_a - CDF_b| over the range.
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from tbsim_env.core.constants import ObjectType
from tbsim_env.data.loader import load_scenarios
from tbsim_env.data.scenario import Scenario
from tbsim_env.metrics.wosac.config import (
    TTC_MAX_HEADING_DIFF,
    TTC_MIN_LATERAL_OVERLAP,
    TTC_SMALL_HEADING_DIFF,
)
from tbsim_env.metrics.wosac.features_kinematic import (
    acceleration_validity,
    kinematic_features,
    speed_validity,
)

HEADWAY_MIN_SPEED = 1.0
"""Headway samples are taken while the vehicle moves faster than this, m/s (car following,
not parking or queueing)."""

HEADWAY_MAX_GAP = 50.0
"""Headway samples are taken when the followed object is nearer than this, m."""


STATIC_MAX_DISPLACEMENT = 2.0
"""A track is static when its logged box centre never gets farther than this from its first
valid position, m."""


@dataclass(frozen=True)
class FeatureSpec:
    """Fixed histogram of one feature.

    Attributes:
        name: feature name (a key of ``scene_features``' per-type dicts).
        lo, hi: histogram range in the feature's unit; values outside go to the end bins.
        bins: number of equal bins.
        unit: unit of the feature and of its Wasserstein distance.
    """

    name: str
    lo: float
    hi: float
    bins: int
    unit: str

    @property
    def edges(self) -> np.ndarray:
        """[bins + 1] bin edges."""
        return np.linspace(self.lo, self.hi, self.bins + 1)


def _kin(speed: float, accel: float, yaw: float, yaw_acc: float) -> tuple[FeatureSpec, ...]:
    return (
        FeatureSpec("linear_speed", 0.0, speed, 60, "m/s"),
        FeatureSpec("linear_acceleration", -accel, accel, 60, "m/s^2"),
        FeatureSpec("angular_speed", -yaw, yaw, 60, "rad/s"),
        FeatureSpec("angular_acceleration", -yaw_acc, yaw_acc, 60, "rad/s^2"),
    )


AGENT_TYPES: tuple[str, ...] = ("vehicle", "pedestrian", "cyclist")
"""Agent types compared, names as in ``ObjectType`` (lower case)."""

FEATURES: dict[str, tuple[FeatureSpec, ...]] = {
    "vehicle": (*_kin(30.0, 6.0, 1.0, 4.0), FeatureSpec("headway", 0.0, HEADWAY_MAX_GAP, 50, "m")),
    "pedestrian": _kin(4.0, 3.0, 3.0, 20.0),
    "cyclist": _kin(12.0, 4.0, 1.5, 6.0),
}
"""Histogram of every feature compared, per agent type."""

_TYPE_CODE = {
    "vehicle": int(ObjectType.VEHICLE),
    "pedestrian": int(ObjectType.PEDESTRIAN),
    "cyclist": int(ObjectType.CYCLIST),
}

Samples = dict[str, dict[str, np.ndarray]]
"""agent type -> feature name -> [n] float64 samples."""


def _headway(
    xy: torch.Tensor,
    heading: torch.Tensor,
    size: torch.Tensor,
    valid: torch.Tensor,
    ego: np.ndarray,
) -> torch.Tensor:
    """Gap to the followed object of each ego track, [E, T] m (inf where none is followed).

    Args:
        xy: [A, T, 2] box centres, m.
        heading: [A, T] yaw, rad.
        size: [A, 2] (length, width) at the track's first valid step, m.
        valid: [A, T] bool.
        ego: [E] indices of the ego tracks.
    """
    out = torch.full((len(ego), xy.shape[1]), float("inf"), dtype=xy.dtype)
    half_l, half_w = size[:, 0, None] / 2.0, size[:, 1, None] / 2.0  # [A, 1]
    for k, e in enumerate(ego):
        yaw_diff = torch.remainder(heading - heading[e] + torch.pi, 2 * torch.pi) - torch.pi
        yaw_diff = yaw_diff.abs()  # [A, T]
        c, s = yaw_diff.cos().abs(), yaw_diff.sin().abs()
        d = xy - xy[e]
        ce, se = heading[e].cos(), heading[e].sin()
        rx = d[..., 0] * ce + d[..., 1] * se
        ry = -d[..., 0] * se + d[..., 1] * ce
        long = rx - half_l[e] - (half_l * c + half_w * s)
        lat = ry.abs() - half_w[e] - (half_l * s + half_w * c)
        followed = (
            (long > 0.0)
            & (yaw_diff <= TTC_MAX_HEADING_DIFF)
            & (lat < 0.0)
            & ((lat < -TTC_MIN_LATERAL_OVERLAP) | (yaw_diff <= TTC_SMALL_HEADING_DIFF))
            & valid
            & valid[e]
        )
        followed[e] = False
        out[k] = torch.where(followed, long, float("inf")).amin(dim=0)
    return out


def _first_valid_size(scenario: Scenario) -> np.ndarray:
    """[A, 2] (length, width) of each track at its first valid step, m."""
    t = scenario.tracks
    first = np.argmax(t.valid, axis=1)
    return t.size[np.arange(t.num_tracks), first, :2].astype(np.float64)


def moving_tracks(scenario: Scenario) -> np.ndarray:
    """[A] bool, tracks whose box centre gets farther than ``STATIC_MAX_DISPLACEMENT`` from
    its first valid position."""
    t = scenario.tracks
    first = np.argmax(t.valid, axis=1)
    start = t.xyz[np.arange(t.num_tracks), first, :2]
    d = np.linalg.norm(t.xyz[..., :2] - start[:, None], axis=-1)
    return (np.where(t.valid, d, 0.0) > STATIC_MAX_DISPLACEMENT).any(axis=1)


def scene_features(scenario: Scenario, moving_only: bool = False) -> Samples:
    """Samples of every feature of ``FEATURES`` in one scene, per agent type.

    Args:
        scenario: a scene (real or generated) on the 0.1 s grid; all its logged steps count.
        moving_only: leave out static tracks (``moving_tracks``); the headway's followed
            objects are all tracks either way.

    Returns:
        agent type -> feature name -> [n] float64 samples (n may be 0).
    """
    t = scenario.tracks
    xyz = torch.as_tensor(t.xyz, dtype=torch.float64)
    heading = torch.as_tensor(t.heading, dtype=torch.float64)
    valid = torch.as_tensor(t.valid)
    kin = kinematic_features(xyz[..., 0], xyz[..., 1], xyz[..., 2], heading)
    v_ok, a_ok = speed_validity(valid), acceleration_validity(valid)
    keep_track = moving_tracks(scenario) if moving_only else np.ones(t.num_tracks, bool)
    out: Samples = {}
    for name in AGENT_TYPES:
        rows = torch.as_tensor((t.object_type == _TYPE_CODE[name]) & keep_track)
        feats = {
            "linear_speed": kin.linear_speed[rows][v_ok[rows]],
            "linear_acceleration": kin.linear_acceleration[rows][a_ok[rows]],
            "angular_speed": kin.angular_speed[rows][v_ok[rows]],
            "angular_acceleration": kin.angular_acceleration[rows][a_ok[rows]],
        }
        out[name] = {k: v.numpy().astype(np.float64) for k, v in feats.items()}
    ego = np.flatnonzero((t.object_type == _TYPE_CODE["vehicle"]) & keep_track)
    size = torch.as_tensor(_first_valid_size(scenario))
    gap = _headway(xyz[..., :2], heading, size, valid, ego)
    moving = kin.linear_speed[ego] > HEADWAY_MIN_SPEED  # NaN (ends) compares False
    keep = v_ok[ego] & moving & (gap < HEADWAY_MAX_GAP)
    out["vehicle"]["headway"] = gap[keep].numpy().astype(np.float64)
    return out


def pool(samples: Iterable[Samples]) -> Samples:
    """Concatenate the samples of several scenes, per type and feature."""
    parts = list(samples)
    return {
        name: {
            f.name: np.concatenate([p[name][f.name] for p in parts] + [np.zeros(0)])
            for f in FEATURES[name]
        }
        for name in AGENT_TYPES
    }


def histogram(values: np.ndarray, spec: FeatureSpec) -> np.ndarray:
    """[bins] probabilities of ``values`` (clipped into the range), all 0 when empty."""
    clipped = np.clip(values, spec.lo, spec.hi)
    counts, _ = np.histogram(clipped, bins=spec.edges)
    total = counts.sum()
    return counts / total if total else counts.astype(np.float64)


def wasserstein(p: np.ndarray, q: np.ndarray, spec: FeatureSpec) -> float:
    """Wasserstein-1 distance between two histograms of ``spec`` (each summing to 1), in the
    feature's unit: sum over bins of |CDF_p - CDF_q| times the bin width. NaN if either is
    empty."""
    if p.sum() == 0.0 or q.sum() == 0.0:
        return float("nan")
    width = (spec.hi - spec.lo) / spec.bins
    return float(np.abs(np.cumsum(p) - np.cumsum(q)).sum() * width)


Distances = dict[str, dict[str, float]]
"""agent type -> feature name -> Wasserstein-1 distance in the feature's unit."""


def distances(a: Samples, b: Samples) -> Distances:
    """Per type and feature, the distance between the histograms of two pooled samples."""
    return {
        name: {
            f.name: wasserstein(histogram(a[name][f.name], f), histogram(b[name][f.name], f), f)
            for f in FEATURES[name]
        }
        for name in AGENT_TYPES
    }


def split_entries(splits_path: Path, split: str) -> list[dict]:
    """Entries (``file``, ``scenario_id``, ...) of one split of a real_splits.json file
    (``scripts/make_real_splits.py``), in file order."""
    return list(json.loads(splits_path.read_text())[split])


def load_entries(entries: Iterable[dict], womd_dir: Path) -> list[Scenario]:
    """The real scenes of split entries, read from ``womd_dir`` (files relative to it)."""
    out = []
    cache: dict[str, list[Scenario]] = {}
    for e in entries:
        if e["file"] not in cache:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                cache[e["file"]] = load_scenarios(womd_dir / e["file"])
        found = [s for s in cache[e["file"]] if s.scenario_id == e["scenario_id"]]
        if not found:
            raise ValueError(f"{e['file']}: no scenario {e['scenario_id']}")
        out.append(found[0])
    return out
