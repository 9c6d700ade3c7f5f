"""Bad values inside well-formed inputs, one test per row of issue 28's table (and its extras).

Each input either gives one ``TbsimError`` line naming the file (or scenario), record, object,
step and field, or, where it is legal, finite and correct outputs. The seeded fuzz over all of
them is ``test_fuzz_pipeline.py``.
"""

from __future__ import annotations

import copy
import dataclasses
import gc
import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch

from tbsim_env.cli import main
from tbsim_env.core.constants import MAX_SCENE_EXTENT, MAX_SPEED
from tbsim_env.core.errors import (
    PolicyError,
    ScenarioFormatError,
    TbsimError,
    UnusableScenarioError,
)
from tbsim_env.data import load_scenarios
from tbsim_env.data.scenario import Scenario
from tbsim_env.env import BatchedTrafficEnv, TrafficEnv
from tbsim_env.metrics.protos import sim_agents_submission_pb2 as pb
from tbsim_env.metrics.wosac import score_scenario, score_submission_file
from tbsim_env.metrics.wosac.rollouts import log_replay_rollouts
from tbsim_env.metrics.wosac.scoring import ScoringError
from tbsim_env.metrics.wosac.submission import (
    SubmissionError,
    read_submission,
    write_submission,
)
from tests.pipeline_support import finite, read_proto, run_pipeline, small_proto, write_proto

pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def real_msg(one_scenario_path: Path):
    return read_proto(one_scenario_path)


@pytest.fixture(scope="module")
def small_msg(real_msg):
    return small_proto(real_msg)


def _copy(msg):
    out = type(msg)()
    out.CopyFrom(msg)
    return out


def _refused(path: Path, error: type = ScenarioFormatError, match: str = "") -> TbsimError:
    """The error loading ``path`` raises; it must name the file and be one line."""
    with pytest.raises(error, match=match) as info:
        load_scenarios(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)
    return info.value


def _env_refuses(source, error: type, match: str, name: str | None = None) -> None:
    """Both environments refuse ``source`` with one ``error`` line matching ``match`` and
    naming ``name`` (by default the file ``source``)."""
    name = str(source) if name is None else name
    for make in (
        lambda: TrafficEnv(source, npc_policy="constant_velocity"),
        lambda: BatchedTrafficEnv(source, 2, npc_policy="constant_velocity"),
    ):
        with pytest.raises(error, match=match) as info:
            make()
        assert name in str(info.value) and "\n" not in str(info.value)


# ------------------------------------------------------------ row 1: nothing valid at step 10


def test_no_track_valid_at_the_current_step(tmp_path: Path, small_msg) -> None:
    msg = _copy(small_msg)
    for t in msg.tracks:
        t.states[10].valid = False
    path = write_proto(tmp_path / "none_valid.tfrecord", msg)
    match = r"record 0.*no track is valid at the current step 10 \('current_time_index'\)"
    _refused(path, match=match)
    _env_refuses(path, ScenarioFormatError, match)


def test_no_controllable_agent_names_the_file(tmp_path: Path, small_msg) -> None:
    """The SDC alone is not valid at the start: controlled='sdc' has nobody to control."""
    msg = _copy(small_msg)
    msg.tracks[msg.sdc_track_index].states[10].valid = False
    path = write_proto(tmp_path / "no_sdc.tfrecord", msg)
    (scenario,) = load_scenarios(path)  # a legal scene
    match = "controlled='sdc' selects no agent valid at the start step 10"
    _env_refuses(path, UnusableScenarioError, match, name=f"637f20cafde22ff8 ({path}#record0)")
    with pytest.raises(UnusableScenarioError, match=rf"{path}#record0.*no track with id 99"):
        TrafficEnv(path, controlled=[99], npc_policy="constant_velocity")
    env = TrafficEnv(path, controlled="all", npc_policy="constant_velocity")  # others can drive
    assert len(env.possible_agents) == int(scenario.tracks.valid[:, 10].sum())


# ------------------------------------------------------------ row 2: scenes of 2-11 steps


@pytest.mark.parametrize("steps", [2, 5, 10, 11])
def test_short_scenes(tmp_path: Path, small_msg, steps: int) -> None:
    msg = _copy(small_msg)
    del msg.timestamps_seconds[steps:]
    del msg.dynamic_map_states[steps:]
    for t in msg.tracks:
        del t.states[steps:]
    path = write_proto(tmp_path / f"short{steps}.tfrecord", msg)
    if steps <= 10:
        match = rf"'current_time_index' 10 is not among the {steps} steps"
        _refused(path, match=match)
        _env_refuses(path, ScenarioFormatError, match)
        return
    # 11 steps: a history-only scene (the WOSAC test split) runs whole episodes.
    assert run_pipeline(path) == "ok"
    env = TrafficEnv(path, npc_policy="constant_velocity")
    env.reset(seed=0)
    steps_run = 0
    while env.agents:
        _, rewards, *_ = env.step({a: np.zeros(2, np.float32) for a in env.agents})
        assert finite(rewards)
        steps_run += 1
    assert steps_run == 80


# ------------------------------------------------------------ row 3: JSON integers out of range


def _json_doc(womd_dir: Path) -> dict:
    return json.loads((womd_dir / "gpudrive" / "tfrecord-00000-of-01000_222.json").read_text())


def _set(*path_value):
    *path, value = path_value

    def mutate(doc: dict) -> None:
        for key in path[:-1]:
            doc = doc[key]
        doc[path[-1]] = value

    return mutate


TTP = ("metadata", "tracks_to_predict", 0)


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (_set(*TTP, "difficulty", 300), r"\[0\]\.difficulty: 300 outside \[0, 2\]"),
        (_set(*TTP, "track_index", 1e20), r"\[0\]\.track_index: expected an integer, got 1e\+20"),
        (_set(*TTP, "track_index", 10**20), r"\[0\]\.track_index: 100000000000000000000 outside"),
        (_set(*TTP, "track_index", 2.7), r"\[0\]\.track_index: expected an integer, got 2\.7"),
        (_set(*TTP, "track_index", 30), r"entry 0: track_index 30 outside the track list"),
        (_set("objects", 3, "id", 10**20), r"objects\[3\]\.id: 100000000000000000000 outside"),
        (_set("objects", 3, "id", -4), r"objects\[3\]\.id: -4 outside \[0, 2147483647\]"),
        (_set("roads", 5, "id", 10**400), r"roads\[5\]\.id: an integer of 1329 bits outside"),
        (_set("metadata", "objects_of_interest", [10**30]), r"interest\[0\]: .* outside"),
        (_set("metadata", "sdc_track_index", True), r"sdc_track_index: expected an integer"),
        (
            _set("objects", 2, "position", 4, "y", True),
            r"\[2\]\.position: expected numbers, got True",
        ),
        (_set("objects", 2, "heading", 4, "0.5"), r"\[2\]\.heading: expected numbers, got '0\.5'"),
        (
            _set("objects", 2, "velocity", 4, "x", None),
            r"\[2\]\.velocity: expected numbers, got None",
        ),
        (_set("objects", 2, "length", 10**400), r"\[2\]\.length: values are not numbers of this"),
        (_set("objects", 2, "valid", 4, 7), r"objects\[2\]\.valid: expected a list of booleans"),
    ],
)
def test_gpudrive_json_integers_and_types(tmp_path: Path, womd_dir: Path, mutate, message) -> None:
    doc = _json_doc(womd_dir)
    mutate(doc)
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(doc))
    _refused(path, match=message)


def test_cli_prints_one_line_and_exits_2(tmp_path: Path, womd_dir: Path, capsys) -> None:
    doc = _json_doc(womd_dir)
    doc["roads"][5]["id"] = 10**400
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(doc))
    assert main(["info", str(path)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(path) in err and r"roads[5].id" in err


# ------------------------------------------------------------ row 4: huge velocities


@pytest.mark.parametrize("speed", [1e20, 3e38, MAX_SPEED + 1.0])
def test_huge_velocity_refused(tmp_path: Path, small_msg, speed: float) -> None:
    msg = _copy(small_msg)
    msg.tracks[2].states[30].velocity_y = speed
    path = write_proto(tmp_path / "fast.tfrecord", msg)
    track = msg.tracks[2].id
    _refused(path, match=rf"track {track} \(index 2\) at step 30: the speed .* beyond 500 m/s")


def test_speed_at_the_bound_gives_finite_outputs(tmp_path: Path, small_msg) -> None:
    msg = _copy(small_msg)
    for t in msg.tracks:  # every agent at nearly the bound, along and across its heading
        for s in t.states:
            if s.valid:
                s.velocity_x, s.velocity_y = 0.7 * MAX_SPEED, -0.7 * MAX_SPEED
    path = write_proto(tmp_path / "fast.tfrecord", msg)
    assert run_pipeline(path) == "ok"


# ------------------------------------------------------------ row 5: far positions


def test_far_position_refused_also_in_memory(tmp_path: Path, small_msg) -> None:
    msg = _copy(small_msg)
    msg.tracks[1].states[40].center_x = 1e30
    path = write_proto(tmp_path / "far.tfrecord", msg)
    _refused(path, match=r"at step 40: field 'center_x' of a valid state lies beyond 1e\+07 m")
    # The same value in a Scenario given to the environments as an object.
    (scenario,) = load_scenarios(write_proto(tmp_path / "ok.tfrecord", small_msg))
    xyz = scenario.tracks.xyz.copy()
    xyz[1, 40, 0] = 1e30
    bad = scenario.replace(tracks=dataclasses.replace(scenario.tracks, xyz=xyz))
    _env_refuses([bad], ScenarioFormatError, "lies beyond 1e\\+07 m", name=str(scenario.source))


def test_scene_wider_than_the_extent_refused(tmp_path: Path, small_msg) -> None:
    msg = _copy(small_msg)
    feature = next(f for f in msg.map_features if f.WhichOneof("feature_data") == "road_edge")
    feature.road_edge.polyline[0].x += MAX_SCENE_EXTENT + 10.0
    path = write_proto(tmp_path / "wide.tfrecord", msg)
    _refused(path, match=rf"the scene spans .* m along x \(.*map feature {feature.id} at x = ")


def test_scene_moved_by_ten_thousand_km_keeps_its_outputs(tmp_path: Path, small_msg) -> None:
    """Route arc lengths, progress, goal and log distances of a scene 9,900 km from the origin
    equal those at the origin (float32 after recentering; was inf with a 1e30 m position)."""
    (scenario,) = load_scenarios(write_proto(tmp_path / "ok.tfrecord", small_msg))
    moved = scenario.transformed(shift=(9.9e6, -9.9e6))
    runs = []
    for sc in (scenario, moved):
        env = TrafficEnv([sc], controlled="all", npc_policy="constant_velocity")
        env.reset(seed=0)
        rows = []
        for _ in range(5):
            _, rewards, _, _, infos = env.step(env.expert_actions())
            rows.append([[rewards[a], *(infos[a][k] for k in KEYS)] for a in sorted(rewards)])
        runs.append(np.array(rows))
    assert np.isfinite(runs[1]).all()
    np.testing.assert_allclose(runs[1], runs[0], atol=2e-3)


KEYS = ("progress", "goal_distance", "log_divergence", "offroad_distance", "speed")


# ------------------------------------------------------------ row 6: box sizes, NPC actions


@pytest.mark.parametrize(
    ("size", "message"),
    [(-1e30, "is not positive"), (0.0, "is not positive"), (-1.0, "is not positive"),
     (-5.0, "is not positive"), (150.0, "is larger than 100 m"), (float("nan"), "non-finite")],
)  # fmt: skip
def test_box_sizes_refused(tmp_path: Path, small_msg, size: float, message: str) -> None:
    msg = _copy(small_msg)
    for s in msg.tracks[3].states:
        s.width = size
    path = write_proto(tmp_path / "size.tfrecord", msg)
    _refused(
        path, match=rf"track {msg.tracks[3].id} \(index 3\) at step \d+: field 'width'.*{message}"
    )


def test_tiny_box_with_trafficbots_npcs_is_finite(tmp_path: Path, small_msg) -> None:
    """A positive size, however small, is legal: TrafficBots NPCs still act finitely."""
    msg = _copy(small_msg)
    for s in msg.tracks[3].states:
        s.length = s.width = 1e-30
    path = write_proto(tmp_path / "tiny.tfrecord", msg)
    env = TrafficEnv(path, controlled="sdc", npc_policy="trafficbots")
    obs, _ = env.reset(seed=0)
    for _ in range(3):
        out = env.step({a: np.zeros(2, np.float32) for a in env.agents})
        assert finite(out)


class _NanPolicy:
    """Constant velocity, except a NaN action for the agent in slot 1 of every row."""

    name = "nan_at_slot_1"
    exact_replay = False

    def initial_state(self, state, scenarios, generator):
        return None

    def act(self, state, policy_state, generator):
        action = torch.zeros(*state.pose.shape[:2], 2)
        action[:, 1, 0] = float("nan")
        return action, policy_state


def test_non_finite_npc_action_is_refused(tmp_path: Path, small_msg) -> None:
    path = write_proto(tmp_path / "ok.tfrecord", small_msg)
    track = small_msg.tracks[1].id
    match = (
        "NPC policy 'nan_at_slot_1' returned a non-finite action at step 10 for 1 "
        rf"agent\(s\): row 0 track {track}$"
    )
    env = TrafficEnv(path, npc_policy=_NanPolicy())
    env.reset(seed=0)
    with pytest.raises(PolicyError, match=match):
        env.step({a: np.zeros(2, np.float32) for a in env.agents})
    benv = BatchedTrafficEnv(path, 1, npc_policy=_NanPolicy(), seed=0)
    benv.reset()
    with pytest.raises(PolicyError, match=match):
        benv.step(torch.zeros(1, benv.num_agents, 2))


# ------------------------------------------------------------ rows 7 and 8: submissions


@pytest.fixture(scope="module")
def submission(womd_dir: Path) -> pb.SimAgentsChallengeSubmission:
    return read_submission(
        womd_dir / "waymo-open-dataset" / "sim_agents" / "test_submission.binproto"
    )


@pytest.fixture(scope="module")
def logged(one_scenario_path: Path) -> list[Scenario]:
    return load_scenarios(one_scenario_path)


@pytest.mark.parametrize(
    ("field", "value"),
    [("center_x", float("nan")), ("center_y", float("inf")), ("center_z", 1e30),
     ("heading", float("nan")), ("heading", float("-inf")), ("heading", 1e30)],
)  # fmt: skip
def test_submission_impossible_value(tmp_path: Path, submission, logged, field, value) -> None:
    sub = copy.deepcopy(submission)
    traj = sub.scenario_rollouts[0].joint_scenes[17].simulated_trajectories[4]
    getattr(traj, field)[33] = value
    path = tmp_path / "bad.binproto"
    write_submission(path, sub)
    where = (
        f"{path}: scenario 637f20cafde22ff8, joint scene 17, object {traj.object_id}: "
        f"step 33 of the simulated future: {field} is "
    )
    with pytest.raises(SubmissionError, match=f"^{where}"):
        score_submission_file(logged, path)
    assert (
        main(["wosac-score", "--data", logged[0].source.split("#")[0], "--submission", str(path)])
        == 2
    )


def test_scoring_refuses_non_finite_rollouts(logged) -> None:
    rollouts = log_replay_rollouts(logged[0], num_rollouts=2)
    rollouts.heading[1, 3, 7] = float("nan")
    oid = int(rollouts.object_id[3])
    with pytest.raises(ScoringError, match=f"rollout 1, object {oid}, step 7 .*heading is nan"):
        score_scenario(logged[0], rollouts)


def test_submission_listing_a_scenario_twice(tmp_path: Path, submission, logged) -> None:
    sub = copy.deepcopy(submission)
    sub.scenario_rollouts.add().CopyFrom(sub.scenario_rollouts[0])
    path = tmp_path / "twice.binproto"
    write_submission(path, sub)
    with pytest.raises(
        SubmissionError, match=f"{path}: scenario '637f20cafde22ff8' is listed twice"
    ):
        score_submission_file(logged, path)


def test_read_submission_closes_its_file(womd_dir: Path) -> None:
    path = womd_dir / "waymo-open-dataset" / "sim_agents" / "test_submission.binproto"
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read_submission(path)
        gc.collect()
    assert not [w for w in caught if issubclass(w.category, ResourceWarning)]


# ------------------------------------------------------------ extras of the issue


@pytest.mark.parametrize("value", [float("nan"), float("inf"), 1e30])
def test_signal_stop_point_refused(tmp_path: Path, small_msg, value: float) -> None:
    msg = _copy(small_msg)
    state = msg.dynamic_map_states[0].lane_states[0]
    state.stop_point.y = value
    path = write_proto(tmp_path / "stop.tfrecord", msg)
    _refused(path, match=rf"traffic signal of lane {state.lane}: 'stop_point' y is")


def test_duplicate_map_feature_ids_refused(tmp_path: Path, small_msg) -> None:
    msg = _copy(small_msg)
    msg.map_features[4].id = msg.map_features[1].id
    path = write_proto(tmp_path / "dup.tfrecord", msg)
    _refused(path, match=rf"map feature id {msg.map_features[1].id} is used by 2 features")


def test_current_time_index_is_honoured_or_refused(tmp_path: Path, small_msg) -> None:
    msg = _copy(small_msg)
    msg.current_time_index = 20
    path = write_proto(tmp_path / "late.tfrecord", msg)
    (scenario,) = load_scenarios(path)
    assert scenario.current_index == 20  # WOSAC rollouts start there
    _env_refuses(
        path,
        UnusableScenarioError,
        r"current step \('current_time_index'\) is 20, but the episode starts at step 10",
    )
