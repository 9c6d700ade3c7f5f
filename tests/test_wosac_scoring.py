"""WOSAC scoring: the real submission against the official reference values, log replay,
aggregation, reports, and the synthetic case (runs without data)."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from tbsim_env.metrics.wosac.evaluate import score_submission_file
from tbsim_env.metrics.wosac.report import scores_table, scores_to_json
from tbsim_env.metrics.wosac.rollouts import Rollouts, log_replay_rollouts
from tbsim_env.metrics.wosac.scoring import (
    LIKELIHOOD_NAMES,
    ScenarioScores,
    ScoringError,
    aggregate,
    score_scenario,
)
from tbsim_env.metrics.wosac.submission import SubmissionError
from tbsim_env.metrics.wosac.synthetic import noisy_rollouts, synthetic_scenario

# Official per-scenario values for test_submission.binproto on 637f20cafde22ff8
# (docs/metrics.md, "Parity with Waymo's official code").
REFERENCE = {
    "wosac2024": {
        "realism_meta_metric": 0.2313,
        "kinematic_metrics": 0.2868,
        "interactive_metrics": 0.2562,
        "map_based_metrics": 0.1674,
        "min_average_displacement_error": 2.0847,
        "average_displacement_error": 2.5053,
        "simulated_collision_rate": 0.6875,
        "simulated_offroad_rate": 0.2656,
        "time_to_collision_likelihood": 0.7837,
    },
    "wosac2025": {
        "realism_meta_metric": 0.2582,
        "kinematic_metrics": 0.2868,
        "interactive_metrics": 0.2497,
        "map_based_metrics": 0.2529,
        "min_average_displacement_error": 2.0847,
        "average_displacement_error": 2.5053,
        "simulated_collision_rate": 0.6875,
        "simulated_offroad_rate": 0.2656,
        "time_to_collision_likelihood": 0.7543,
        "traffic_light_violation_likelihood": 1.0,
    },
}
SHARED_LIKELIHOODS = {
    "linear_speed": 0.6471,
    "linear_acceleration": 0.1293,
    "angular_speed": 0.0616,
    "angular_acceleration": 0.3093,
    "distance_to_nearest_object": 0.2372,
    "collision_indication": 0.0529,
    "distance_to_road_edge": 0.4022,
    "offroad_indication": 0.0736,
}
LOG_REPLAY_META = {"wosac2024": 0.8070, "wosac2025": 0.8266}


pytestmark = [pytest.mark.usefixtures("torch_one_thread"), pytest.mark.float_sensitive]


@pytest.fixture(scope="module")
def real_pair(womd_dir, one_scenario_path):
    from tbsim_env.data.womd import read_scenarios

    scenario = next(iter(read_scenarios(one_scenario_path)))
    path = womd_dir / "waymo-open-dataset/sim_agents/test_submission.binproto"
    return scenario, path


@pytest.fixture(scope="module")
def real_scores(real_pair):
    scenario, path = real_pair
    return {v: score_submission_file([scenario], path, v)[0] for v in REFERENCE}


@pytest.fixture(scope="module")
def log_scores(real_pair):
    scenario, _ = real_pair
    replay = log_replay_rollouts(scenario)
    return {v: score_scenario(scenario, replay, v) for v in REFERENCE}


def _check_ranges(s: ScenarioScores) -> None:
    for name, value in s.likelihoods().items():
        assert 0.0 <= value <= 1.0, name
    for name in ("realism_meta_metric", "kinematic_metrics", "interactive_metrics"):
        assert 0.0 <= getattr(s, name) <= 1.0
    assert 0.0 <= s.map_based_metrics <= 1.0


@pytest.mark.parametrize("version", sorted(REFERENCE))
def test_real_submission_matches_official_scores(real_scores, version):
    s = real_scores[version]
    assert s.scenario_id == "637f20cafde22ff8" and s.version == version
    assert (s.num_sim_agents, s.num_evaluated) == (50, 4)
    _check_ranges(s)
    for name, want in REFERENCE[version].items():
        assert getattr(s, name) == pytest.approx(want, abs=1e-3), name
    for name, want in SHARED_LIKELIHOODS.items():
        assert getattr(s, f"{name}_likelihood") == pytest.approx(want, abs=1e-3), name


@pytest.mark.parametrize("version", sorted(REFERENCE))
def test_log_replay_beats_submission(real_scores, log_scores, version):
    log = log_scores[version]
    _check_ranges(log)
    assert log.realism_meta_metric == pytest.approx(LOG_REPLAY_META[version], abs=1e-3)
    assert log.realism_meta_metric > real_scores[version].realism_meta_metric
    assert log.average_displacement_error == 0.0
    assert log.min_average_displacement_error == 0.0
    # Every rollout repeats the log, so each agent's indications agree with the log 32 times.
    assert log.collision_indication_likelihood == pytest.approx(1.0, abs=1e-4)
    assert log.offroad_indication_likelihood == pytest.approx(1.0, abs=1e-4)


def test_official_ttc_difference_between_versions(log_scores):
    # docs/metrics.md, "Parity with Waymo's official code": 0.8607 (all evaluated) vs 0.8362
    # (vehicles only).
    assert log_scores["wosac2024"].time_to_collision_likelihood == pytest.approx(0.8607, abs=1e-3)
    assert log_scores["wosac2025"].time_to_collision_likelihood == pytest.approx(0.8362, abs=1e-3)


def test_unknown_scenario_in_submission_rejected(real_pair):
    _, path = real_pair
    with pytest.raises(SubmissionError, match="'637f20cafde22ff8' of the submission is not"):
        score_submission_file([synthetic_scenario(num_agents=3)], path)


def test_aggregate_and_reports(real_scores, log_scores):
    scores = [real_scores["wosac2025"], log_scores["wosac2025"]]
    mean = aggregate(scores)
    assert mean.num_scenarios == 2
    for name in LIKELIHOOD_NAMES:
        field = f"{name}_likelihood"
        assert getattr(mean, field) == pytest.approx(sum(getattr(s, field) for s in scores) / 2)
    assert mean.realism_meta_metric == pytest.approx(
        sum(s.realism_meta_metric for s in scores) / 2, abs=1e-12
    )
    table = scores_table(scores)
    assert "637f20cafde22ff8" in table and "MEAN" in table and "0.2582" in table
    data = json.loads(json.dumps(scores_to_json(scores)))
    assert data["version"] == "wosac2025" and len(data["scenarios"]) == 2
    assert set(data["scenarios"][0]) == {f.name for f in dataclasses.fields(ScenarioScores)}
    with pytest.raises(ScoringError, match="different metric versions"):
        aggregate([real_scores["wosac2024"], log_scores["wosac2025"]])
    with pytest.raises(ScoringError, match="empty"):
        aggregate([])


# --------------------------------------------------------------------------- no data needed


@pytest.fixture(scope="module")
def synthetic():
    return synthetic_scenario(num_agents=12, seed=5, stop_x=60.0)


def test_synthetic_log_replay_beats_noise(synthetic):
    noisy = score_scenario(synthetic, noisy_rollouts(synthetic, noise_std=0.3, seed=1))
    log = score_scenario(synthetic, log_replay_rollouts(synthetic))
    _check_ranges(noisy)
    _check_ranges(log)
    assert log.realism_meta_metric > noisy.realism_meta_metric
    assert log.average_displacement_error == 0.0 < noisy.min_average_displacement_error
    assert noisy.min_average_displacement_error <= noisy.average_displacement_error
    assert math.isclose(
        log.realism_meta_metric,
        sum(w * log.likelihoods()[n] for n, w in _weights("wosac2025").items()),
        rel_tol=1e-9,
    )


def _weights(version):
    from tbsim_env.metrics.wosac.config import get_config

    return get_config(version).weights.as_dict()


def test_red_light_runner_scores_a_violation_rate(synthetic):
    # Agent 0 drives on the signalled lane through the red stop line at x = 60 m in the log.
    log = score_scenario(synthetic, log_replay_rollouts(synthetic))
    assert log.simulated_traffic_light_violation_rate > 0.0
    assert log.traffic_light_violation_likelihood == pytest.approx(1.0, abs=1e-4)
    # Stopping every agent at its current position: no violation any more, lower likelihood.
    replay = log_replay_rollouts(synthetic)
    still = Rollouts(
        scenario_id=replay.scenario_id,
        object_id=replay.object_id,
        x=replay.x[..., :1].expand_as(replay.x).clone(),
        y=replay.y,
        z=replay.z,
        heading=replay.heading,
    )
    stopped = score_scenario(synthetic, still)
    assert stopped.simulated_traffic_light_violation_rate == 0.0
    assert stopped.traffic_light_violation_likelihood < 0.9


def test_score_scenario_input_errors(synthetic):
    replay = log_replay_rollouts(synthetic)
    with pytest.raises(ScoringError, match="not 'other'"):
        score_scenario(synthetic.replace(scenario_id="other"), replay)
    partial = Rollouts(
        scenario_id=replay.scenario_id,
        object_id=replay.object_id[1:],
        x=replay.x[:, 1:],
        y=replay.y[:, 1:],
        z=replay.z[:, 1:],
        heading=replay.heading[:, 1:],
    )
    with pytest.raises(ScoringError, match=r"miss sim agents \[1000\]"):
        score_scenario(synthetic, partial)
    short = Rollouts(
        scenario_id=replay.scenario_id,
        object_id=replay.object_id,
        x=replay.x[..., :79],
        y=replay.y[..., :79],
        z=replay.z[..., :79],
        heading=replay.heading[..., :79],
    )
    with pytest.raises(ScoringError, match="79 steps, expected 80"):
        score_scenario(synthetic, short)
    with pytest.raises(ValueError, match="unknown WOSAC metric version"):
        score_scenario(synthetic, replay, version="wosac2023")


def test_evaluated_objects_are_sdc_and_valid_tracks_to_predict_sorted_by_id(synthetic):
    from tbsim_env.metrics.wosac.trajectories import select_objects

    objects = select_objects(synthetic)
    assert objects.eval_ids.tolist() == [1000, 1001, 1002, 1011]  # tracks to predict + SDC
    assert objects.num_objects == 12
    valid = synthetic.tracks.valid.copy()
    valid[1, synthetic.current_index] = False  # not a sim agent any more: not evaluated
    tracks = type(synthetic.tracks)(**{**synthetic.tracks.__dict__, "valid": valid})
    changed = synthetic.replace(tracks=tracks, tracks_to_predict=np.array([2, 1, 0]))
    objects = select_objects(changed)
    assert objects.eval_ids.tolist() == [1000, 1002, 1011]
    assert 1001 not in objects.object_id.tolist()
    scores = score_scenario(changed, log_replay_rollouts(changed))
    assert (scores.num_sim_agents, scores.num_evaluated) == (11, 3)


def test_float64_rollouts_and_explicit_device(synthetic):
    replay = log_replay_rollouts(synthetic)
    as64 = Rollouts(
        scenario_id=replay.scenario_id,
        object_id=replay.object_id,
        x=replay.x.double(),
        y=replay.y.double(),
        z=replay.z.double(),
        heading=replay.heading.double(),
    )
    a = score_scenario(synthetic, replay, "wosac2024")
    b = score_scenario(synthetic, as64, "wosac2024", device="cpu")
    assert dataclasses.asdict(a) == dataclasses.asdict(b)


def test_a_scene_logged_beyond_the_rollouts_is_scored_on_their_steps(womd_dir):
    """WOMD's 20 s scenes (ScenarioNet pickles of ~199 steps): WOSAC rollouts cover the 80
    steps after the current one, and the scene is scored on its first 91, as the 9 s ones."""
    from tbsim_env.data import load_scenarios
    from tbsim_env.evaluation import evaluate_policy

    path = womd_dir / "scenarionet_more" / "scenestreamer" / "sd_waymo_v1.2_a2e36ea909d28a37.pkl"
    long_scene = load_scenarios(path)[0]
    assert long_scene.num_steps > 150
    scores, kept = evaluate_policy(
        [long_scene], "constant_velocity", num_rollouts=4, keep_rollouts=True
    )
    s = scores[0]
    assert kept[0].num_steps == 80
    assert 0.0 < s.realism_meta_metric < 1.0 and math.isfinite(s.min_average_displacement_error)
    cut = long_scene.on_time_grid(long_scene.current_index + 81)
    assert dataclasses.asdict(s) == dataclasses.asdict(score_scenario(cut, kept[0]))
