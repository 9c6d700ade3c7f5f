"""WOSAC submission I/O: proto round trips, files, and the server's validation rules."""

from __future__ import annotations

import pytest
import torch

from tbsim_env.metrics.protos import sim_agents_submission_pb2 as pb
from tbsim_env.metrics.wosac.rollouts import log_replay_rollouts
from tbsim_env.metrics.wosac.submission import (
    SubmissionError,
    SubmissionMetadata,
    build_submission,
    read_submission,
    rollouts_from_proto,
    rollouts_to_proto,
    validate_scenario_rollouts,
    write_submission,
)
from tbsim_env.metrics.wosac.synthetic import noisy_rollouts, synthetic_scenario

pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def scenario():
    return synthetic_scenario(num_agents=5, seed=2)


@pytest.fixture()
def proto(scenario):
    return rollouts_to_proto(noisy_rollouts(scenario, seed=4))


def test_round_trip_keeps_float32_values(scenario):
    rollouts = noisy_rollouts(scenario, seed=4)
    msg = rollouts_to_proto(rollouts)
    validate_scenario_rollouts(msg, scenario)
    back = rollouts_from_proto(pb.ScenarioRollouts.FromString(msg.SerializeToString()))
    assert back.scenario_id == scenario.scenario_id
    assert torch.equal(back.object_id, rollouts.object_id)
    for name in ("x", "y", "z", "heading"):
        assert torch.equal(getattr(back, name), getattr(rollouts, name))


def test_joint_scenes_in_any_object_order_are_aligned(scenario, proto):
    scene = proto.joint_scenes[5]
    reordered = list(reversed(scene.simulated_trajectories))
    del scene.simulated_trajectories[:]
    scene.simulated_trajectories.extend(reordered)
    validate_scenario_rollouts(proto, scenario)
    back = rollouts_from_proto(proto)
    want = noisy_rollouts(scenario, seed=4)
    assert torch.equal(back.x, want.x)


def test_write_and_read_submission_file(tmp_path, scenario, proto):
    meta = SubmissionMetadata(
        account_name="me@example.com",
        unique_method_name="tbsim-test",
        authors=("A", "B"),
        num_model_parameters="1M",
        acknowledge_complies_with_closed_loop_requirement=True,
    )
    path = tmp_path / "sub.binproto"
    write_submission(path, build_submission([proto], meta))
    sub = read_submission(path)
    assert sub.submission_type == pb.SimAgentsChallengeSubmission.SIM_AGENTS_SUBMISSION
    assert list(sub.authors) == ["A", "B"] and sub.num_model_parameters == "1M"
    assert sub.acknowledge_complies_with_closed_loop_requirement
    validate_scenario_rollouts(sub.scenario_rollouts[0], scenario)


def test_unreadable_file_is_rejected(tmp_path):
    path = tmp_path / "bad.binproto"
    path.write_bytes(b"\x0a\xff\xff\xff")
    with pytest.raises(SubmissionError, match="not a SimAgentsChallengeSubmission"):
        read_submission(path)


def test_31_joint_scenes_rejected(scenario, proto):
    del proto.joint_scenes[-1]
    with pytest.raises(SubmissionError, match="expected 32 joint scenes, got 31"):
        validate_scenario_rollouts(proto, scenario)


def test_missing_agent_rejected(scenario, proto):
    gone = proto.joint_scenes[3].simulated_trajectories[2].object_id
    del proto.joint_scenes[3].simulated_trajectories[2]
    with pytest.raises(SubmissionError, match=f"joint scene 3: object {gone} missing"):
        validate_scenario_rollouts(proto, scenario)


def test_79_steps_rejected(scenario, proto):
    traj = proto.joint_scenes[0].simulated_trajectories[1]
    del traj.center_y[-1]
    with pytest.raises(SubmissionError, match=f"object {traj.object_id}: center_y has 79 steps"):
        validate_scenario_rollouts(proto, scenario)


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        (
            "center_x",
            float("nan"),
            r"center_x is nan; every value must be finite and within 1e\+07 m$",
        ),
        ("center_y", float("inf"), r"center_y is inf"),
        ("center_z", float("-inf"), r"center_z is -inf"),
        (
            "heading",
            float("nan"),
            r"heading is nan; every value must be finite and within 1000 rad$",
        ),
        ("heading", float("inf"), r"heading is inf"),
        ("heading", 1e30, r"heading is 1.0\d*e\+30"),
        ("heading", -1001.0, r"heading is -1001.0"),
        ("center_x", 1e30, r"center_x is 1.0\d*e\+30; every value must be finite and within"),
        ("center_y", -2e7, r"center_y is -20000000.0"),
    ],
)
def test_impossible_values_rejected(scenario, proto, field, value, message):
    """A submission with a non-finite or far-off coordinate is refused, not scored."""
    traj = proto.joint_scenes[4].simulated_trajectories[3]
    getattr(traj, field)[7] = value
    where = f"joint scene 4, object {traj.object_id}: step 7 of the simulated future: "
    with pytest.raises(SubmissionError, match=where + message):
        validate_scenario_rollouts(proto, scenario)


def test_exported_rollout_count_is_checked(scenario):
    proto = rollouts_to_proto(noisy_rollouts(scenario, seed=4, num_rollouts=2))
    validate_scenario_rollouts(proto, scenario, num_rollouts=2)
    with pytest.raises(SubmissionError, match="expected 32 joint scenes, got 2"):
        validate_scenario_rollouts(proto, scenario)


def test_duplicate_extra_and_unnamed_agents_rejected(scenario, proto):
    dup = pb.ScenarioRollouts()
    dup.CopyFrom(proto)
    dup.joint_scenes[1].simulated_trajectories.add().CopyFrom(
        dup.joint_scenes[1].simulated_trajectories[0]
    )
    with pytest.raises(SubmissionError, match="joint scene 1: object 1000 appears twice"):
        validate_scenario_rollouts(dup, scenario)
    proto.joint_scenes[2].simulated_trajectories[0].object_id = 77
    with pytest.raises(SubmissionError, match="object 77 is not a sim agent"):
        validate_scenario_rollouts(proto, scenario)
    proto.joint_scenes[2].simulated_trajectories[0].ClearField("object_id")
    with pytest.raises(SubmissionError, match="has no object_id"):
        validate_scenario_rollouts(proto, scenario)


def test_scenario_id_checked(scenario, proto):
    proto.scenario_id = "another"
    with pytest.raises(SubmissionError, match="rollouts are for scenario 'another'"):
        validate_scenario_rollouts(proto, scenario)
    proto.ClearField("scenario_id")
    with pytest.raises(SubmissionError, match="no scenario_id"):
        validate_scenario_rollouts(proto, scenario)


def test_agents_invalid_at_current_step_are_not_sim_agents(scenario):
    valid = scenario.tracks.valid.copy()
    valid[1, scenario.current_index] = False
    tracks = type(scenario.tracks)(**{**scenario.tracks.__dict__, "valid": valid})
    changed = scenario.replace(tracks=tracks)
    msg = rollouts_to_proto(log_replay_rollouts(scenario))
    with pytest.raises(SubmissionError, match="object 1001 is not a sim agent"):
        validate_scenario_rollouts(msg, changed)
    validate_scenario_rollouts(rollouts_to_proto(log_replay_rollouts(changed)), changed)


def test_real_submission_validates(womd_dir, one_scenario_path):
    from tbsim_env.data.womd import read_scenarios

    scenario = next(iter(read_scenarios(one_scenario_path)))
    sub = read_submission(womd_dir / "waymo-open-dataset/sim_agents/test_submission.binproto")
    assert len(sub.scenario_rollouts) == 1
    validate_scenario_rollouts(sub.scenario_rollouts[0], scenario)
    rollouts = rollouts_from_proto(sub.scenario_rollouts[0])
    assert tuple(rollouts.x.shape) == (32, 50, 80)


def test_submission_proto_coexists_with_the_scenario_proto():
    # Both declare package waymo.open_dataset in the default descriptor pool: no name clash.
    from tbsim_env.data.protos import scenario_pb2

    assert pb.SimulatedTrajectory.DESCRIPTOR.full_name == "waymo.open_dataset.SimulatedTrajectory"
    assert scenario_pb2.Scenario.DESCRIPTOR.full_name == "waymo.open_dataset.Scenario"
    fields = {f.name: f.number for f in pb.SimulatedTrajectory.DESCRIPTOR.fields}
    assert fields == {
        "center_x": 2,
        "center_y": 3,
        "center_z": 4,
        "heading": 5,
        "object_id": 6,
        "width": 7,
        "length": 8,
        "height": 9,
        "object_type": 10,
        "valid": 11,
    }
    sub_fields = {f.name: f.number for f in pb.SimAgentsChallengeSubmission.DESCRIPTOR.fields}
    assert sub_fields["acknowledge_complies_with_closed_loop_requirement"] == 14
    assert sub_fields["public_model_names"] == 13 and sub_fields["num_model_parameters"] == 12


def test_package_exports():
    import tbsim_env.metrics.wosac as wosac

    for name in wosac.__all__:
        assert hasattr(wosac, name), name
