"""WOSAC parity with Waymo's own code, field by field and feature by feature.

The oracle is ``wosac_reference/`` in the shared data (its README): the official 2024 (1.6.4) and
2025 (1.6.7) outputs for two submissions (the logged future, and constant velocity) on the two
real Scenario protos and on a third, converted scene. Every per-scenario field must equal the
official JSON, and every per-object, per-step feature the official arrays where they are valid.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from tbsim_env.data.womd import read_scenarios
from tbsim_env.metrics.wosac.evaluate import score_submission_file
from tbsim_env.metrics.wosac.scoring import scenario_features
from tbsim_env.metrics.wosac.submission import read_submission, rollouts_from_proto

pytestmark = [pytest.mark.usefixtures("torch_one_thread"), pytest.mark.float_sensitive]

THIRD = "tfrecord-00082-of-01000_465"
# (rollouts file, official JSON, version); the JSON lists every scenario the file holds.
CASES = [
    ("rollouts_log.binproto", "official_log_2024.json", "wosac2024"),
    ("rollouts_log.binproto", "official_log_2025.json", "wosac2025"),
    ("rollouts_const_vel.binproto", "official_const_vel_2025.json", "wosac2025"),
    (f"{THIRD}.rollouts_log.binproto", f"official_{THIRD}_log_2025.json", "wosac2025"),
    (f"{THIRD}.rollouts_const_vel.binproto", f"official_{THIRD}_const_vel_2025.json", "wosac2025"),
]
# (scenario, rollouts name in the file names, version) of every official feature file.
FEATURE_CASES = [
    ("637f20cafde22ff8", "log", "2024"),
    ("637f20cafde22ff8", "log", "2025"),
    ("ee519cf571686d19", "log", "2024"),
    ("ee519cf571686d19", "log", "2025"),
    ("ee519cf571686d19", "const_vel", "2025"),
    (THIRD, "log", "2025"),
    (THIRD, "const_vel", "2025"),
]
# Official JSON names that differ from ``ScenarioScores``'.
ALIASES = {"metametric": "realism_meta_metric", "min_ade": "min_average_displacement_error"}


@pytest.fixture(scope="module")
def reference(womd_dir):
    return womd_dir / "wosac_reference"


@pytest.fixture(scope="module")
def scenarios(womd_dir, reference):
    files = [
        womd_dir / "waymo-open-dataset" / "motion_data_one_scenario.tfrecord",
        womd_dir / "waymo-open-dataset" / "womd_scenario_input.tfrecord",
        reference / f"{THIRD}.tfrecord",
    ]
    return {s.scenario_id: s for f in files for s in read_scenarios(f)}


@pytest.mark.parametrize("rollouts_file, official_file, version", CASES)
def test_every_scenario_field_equals_the_official_code(
    scenarios, reference, rollouts_file, official_file, version
):
    official = json.loads((reference / official_file).read_text())
    scores = score_submission_file(scenarios.values(), reference / rollouts_file, version)
    mine = {s.scenario_id: s for s in scores}
    assert sorted(mine) == sorted(sc["scenario_id"] for sc in official["scenarios"])
    for sc in official["scenarios"]:
        got = mine[sc["scenario_id"]]
        assert got.num_sim_agents == sc["n_sim_objects"]
        assert got.num_evaluated == len(sc["evaluated_object_ids"])
        fields = {**sc["metrics"], **sc["buckets"]}
        fields.pop("scenario_id")
        for name, want in fields.items():
            value = getattr(got, ALIASES.get(name, name))
            assert value == pytest.approx(want, abs=1e-4), (sc["scenario_id"], name)


def _check_feature(name: str, mine: np.ndarray, ref: np.ndarray, valid: np.ndarray) -> None:
    """Equal where valid: booleans exactly, time to collision to 1e-4 s, the rest to float32
    rounding of the official code (coordinates of order 1e3 m; placeholder speeds of 1e4 m/s)."""
    assert mine.shape == ref.shape, name
    if mine.dtype == bool:
        bad = (mine != ref) & valid
    else:
        atol = 1e-4 if name.endswith("time_to_collision") else 2e-3
        close = np.isclose(mine, ref, rtol=1e-5, atol=atol, equal_nan=True)
        bad = ~close & valid
    where = [tuple(int(i) for i in ix) for ix in np.argwhere(bad)[:5]]
    assert not bad.any(), f"{name}: {int(bad.sum())} valid entries differ, e.g. at {where}"


@pytest.mark.parametrize("scenario_id, rollouts, version", FEATURE_CASES)
def test_every_feature_equals_the_official_code_per_object_and_step(
    scenarios, reference, scenario_id, rollouts, version
):
    official = np.load(reference / f"{scenario_id}.{rollouts}.{version}.features.npz")
    prefix = f"{THIRD}." if scenario_id == THIRD else ""
    submission = read_submission(reference / f"{prefix}rollouts_{rollouts}.binproto")
    proto = next(r for r in submission.scenario_rollouts if r.scenario_id == scenario_id)
    features = scenario_features(scenarios[scenario_id], rollouts_from_proto(proto))
    np.testing.assert_array_equal(features.objects.eval_ids, official["log_object_id"])
    np.testing.assert_array_equal(features.log_valid.numpy(), official["log_valid"][0])
    for field in dataclasses.fields(features.log_features):
        for which, values in (("log", features.log_features), ("sim", features.sim_features)):
            key = f"{which}_{field.name}"
            if key not in official:  # 1.6.4 (2024) has no traffic-light feature
                assert version == "2024" and "traffic_light" in key
                continue
            mine = getattr(values, field.name).numpy()
            _check_feature(key, mine, official[key], _scored(official, which, field.name))


def _scored(official, which: str, name: str) -> np.ndarray:
    """Where a feature is compared: valid steps, and for speeds and accelerations the steps the
    official code scores (``mask_speed``/``mask_accel``). The readers zero the placeholder
    states of invalid steps, where the protos keep a stray centre_z, so 3-D speeds next to
    invalid steps differ from the official ones there; those are never scored."""
    valid = official[f"{which}_valid"]
    if "speed" in name:
        return valid & official["mask_speed"][None]
    if "acceleration" in name:
        return valid & official["mask_accel"][None]
    return valid


def test_metrics_read_headings_as_stored(scenarios):
    """ee519cf571686d19 stores headings off by whole turns (e.g. track 631); the official TTC
    compares them unwrapped, so the metrics must see them as stored, the simulation wrapped."""
    tracks = scenarios["ee519cf571686d19"].tracks
    raw, wrapped = tracks.stored_heading(), tracks.heading
    turns = np.round((raw - wrapped) / (2 * np.pi))
    assert (turns[tracks.valid] != 0).sum() > 100
    np.testing.assert_allclose(raw - wrapped, turns * 2 * np.pi, atol=1e-5)
    assert (np.abs(wrapped[tracks.valid]) <= np.pi).all()
    moved = scenarios["ee519cf571686d19"].transformed(yaw=1.1, shift=(3000.0, -1500.0))
    ok = tracks.valid
    np.testing.assert_allclose(
        moved.tracks.stored_heading()[ok], raw[ok].astype(np.float64) + 1.1, atol=1e-5
    )
