"""WOSAC submission I/O: read, write, validate, and convert to and from ``Rollouts``.

Files are raw serialized ``SimAgentsChallengeSubmission`` protos (no TFRecord framing), as the
challenge server expects. ``validate_scenario_rollouts`` does the server's checks
(docs/metrics.md): scenario id present, 32 joint scenes, 80 steps in each of x, y, z and
heading, and exactly the sim agents (tracks valid at the current step) in every joint scene;
and it refuses what no real rollout holds: a non-finite coordinate or heading, a coordinate
beyond ``MAX_ABS_COORDINATE``, a heading beyond ``MAX_ABS_HEADING`` (constants.py), naming the
scenario, joint scene, object, step and field.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from google.protobuf.message import DecodeError

from tbsim_env.core.constants import MAX_ABS_COORDINATE, MAX_ABS_HEADING, NUM_FUTURE
from tbsim_env.core.errors import TbsimError
from tbsim_env.data.scenario import Scenario
from tbsim_env.metrics.protos import sim_agents_submission_pb2 as pb
from tbsim_env.metrics.wosac.config import NUM_ROLLOUTS
from tbsim_env.metrics.wosac.rollouts import Rollouts

_COORDS = ("center_x", "center_y", "center_z", "heading")


class SubmissionError(TbsimError, ValueError):
    """A submission (file or scenario rollouts) breaks the challenge format."""


def read_submission(path: str | os.PathLike[str]) -> pb.SimAgentsChallengeSubmission:
    """Parse a raw serialized ``SimAgentsChallengeSubmission`` file.

    Raises:
        SubmissionError: if the file is not a valid submission proto.
        FileNotFoundError: no such file.
    """
    with open(path, "rb") as fh:
        data = fh.read()
    sub = pb.SimAgentsChallengeSubmission()
    try:
        sub.ParseFromString(data)
    except Exception as err:  # the upb runtime raises DecodeError and others (e.g. MemoryError)
        kind = "" if isinstance(err, DecodeError) else f"{type(err).__name__}: "
        raise SubmissionError(
            f"{os.fspath(path)}: not a SimAgentsChallengeSubmission ({kind}{err})"
        ) from err
    return sub


def write_submission(
    path: str | os.PathLike[str], submission: pb.SimAgentsChallengeSubmission
) -> None:
    """Write a submission as raw serialized bytes (parent folders must exist)."""
    with open(path, "wb") as f:
        f.write(submission.SerializeToString(deterministic=True))


@dataclass(frozen=True)
class SubmissionMetadata:
    """The method description of a submission (fields 3-14 of the proto).

    ``uses_lidar_data``, ``uses_camera_data``, ``uses_public_model_pretraining`` and
    ``num_model_parameters`` are required by the challenge for a valid entry.
    """

    account_name: str
    unique_method_name: str
    authors: tuple[str, ...] = ()
    affiliation: str = ""
    description: str = ""
    method_link: str = ""
    uses_lidar_data: bool = False
    uses_camera_data: bool = False
    uses_public_model_pretraining: bool = False
    num_model_parameters: str = ""
    public_model_names: tuple[str, ...] = ()
    acknowledge_complies_with_closed_loop_requirement: bool = False


def build_submission(
    scenario_rollouts: Sequence[pb.ScenarioRollouts], metadata: SubmissionMetadata
) -> pb.SimAgentsChallengeSubmission:
    """Assemble a sim-agents submission from per-scenario rollouts and the method description."""
    sub = pb.SimAgentsChallengeSubmission(
        submission_type=pb.SimAgentsChallengeSubmission.SIM_AGENTS_SUBMISSION,
        account_name=metadata.account_name,
        unique_method_name=metadata.unique_method_name,
        authors=list(metadata.authors),
        affiliation=metadata.affiliation,
        description=metadata.description,
        method_link=metadata.method_link,
        uses_lidar_data=metadata.uses_lidar_data,
        uses_camera_data=metadata.uses_camera_data,
        uses_public_model_pretraining=metadata.uses_public_model_pretraining,
        num_model_parameters=metadata.num_model_parameters,
        public_model_names=list(metadata.public_model_names),
        acknowledge_complies_with_closed_loop_requirement=(
            metadata.acknowledge_complies_with_closed_loop_requirement
        ),
    )
    sub.scenario_rollouts.extend(scenario_rollouts)
    return sub


def validate_scenario_rollouts(
    rollouts: pb.ScenarioRollouts, scenario: Scenario, *, num_rollouts: int = NUM_ROLLOUTS
) -> None:
    """Check one scenario's rollouts the way the challenge server does, and their values.

    Args:
        rollouts: one scenario's rollouts.
        scenario: the scenario (its log up to the current step; no future needed).
        num_rollouts: joint scenes expected (the challenge's 32 unless a caller exports fewer).

    Raises:
        SubmissionError: naming the first problem, e.g. "expected 32 joint scenes, got 31",
            "joint scene 3: object 1234 missing" or "center_x has a non-finite value".
    """
    where = f"scenario {scenario.scenario_id}"
    if not rollouts.HasField("scenario_id") or not rollouts.scenario_id:
        raise SubmissionError(f"{where}: rollouts have no scenario_id")
    if rollouts.scenario_id != scenario.scenario_id:
        raise SubmissionError(f"{where}: rollouts are for scenario {rollouts.scenario_id!r}")
    n = len(rollouts.joint_scenes)
    if n != num_rollouts:
        raise SubmissionError(f"{where}: expected {num_rollouts} joint scenes, got {n}")
    expected = {int(i) for i in scenario.tracks.id[scenario.sim_agent_indices()]}
    for j, scene in enumerate(rollouts.joint_scenes):
        seen: set[int] = set()
        for traj in scene.simulated_trajectories:
            if not traj.HasField("object_id"):
                raise SubmissionError(f"{where}, joint scene {j}: a trajectory has no object_id")
            oid = int(traj.object_id)
            if oid in seen:
                raise SubmissionError(f"{where}, joint scene {j}: object {oid} appears twice")
            if oid not in expected:
                raise SubmissionError(
                    f"{where}, joint scene {j}: object {oid} is not a sim agent "
                    "(not a track valid at the current step)"
                )
            seen.add(oid)
            for name in _COORDS:
                values = getattr(traj, name)
                if len(values) != NUM_FUTURE:
                    raise SubmissionError(
                        f"{where}, joint scene {j}, object {oid}: {name} has {len(values)} "
                        f"steps, expected {NUM_FUTURE}"
                    )
                problem = _impossible_value(name, np.asarray(values, np.float64))
                if problem:
                    raise SubmissionError(f"{where}, joint scene {j}, object {oid}: {problem}")
        missing = sorted(expected - seen)
        if missing:
            more = f" (and {len(missing) - 1} more)" if len(missing) > 1 else ""
            raise SubmissionError(f"{where}, joint scene {j}: object {missing[0]} missing{more}")


def _impossible_value(name: str, values: np.ndarray) -> str | None:
    """What is wrong with a trajectory's ``values`` [S] of coordinate ``name``, or None.

    Every value must be finite; positions within ``MAX_ABS_COORDINATE``, headings within
    ``MAX_ABS_HEADING``.
    """
    bound, unit = (MAX_ABS_HEADING, "rad") if name == "heading" else (MAX_ABS_COORDINATE, "m")
    ok = np.isfinite(values)
    ok &= np.abs(np.where(ok, values, 0.0)) <= bound
    if ok.all():
        return None
    k = int(np.argmin(ok))
    return (
        f"step {k} of the simulated future: {name} is {float(values[k])!r}; every value must "
        f"be finite and within {bound:g} {unit}"
    )


def rollouts_from_proto(
    rollouts: pb.ScenarioRollouts, device: torch.device | str = "cpu"
) -> Rollouts:
    """Convert ``ScenarioRollouts`` to tensors (objects in the first joint scene's order).

    Raises:
        SubmissionError: if the joint scenes hold different object sets or ragged arrays
            (run ``validate_scenario_rollouts`` first for the full checks).
    """
    scenes = rollouts.joint_scenes
    if not scenes or not scenes[0].simulated_trajectories:
        raise SubmissionError(f"scenario {rollouts.scenario_id}: rollouts are empty")
    ids = [int(t.object_id) for t in scenes[0].simulated_trajectories]
    pos = {oid: k for k, oid in enumerate(ids)}
    steps = len(scenes[0].simulated_trajectories[0].center_x)
    arr = np.zeros((4, len(scenes), len(ids), steps), np.float32)
    for j, scene in enumerate(scenes):
        if len(scene.simulated_trajectories) != len(ids):
            raise SubmissionError(
                f"scenario {rollouts.scenario_id}, joint scene {j}: "
                f"{len(scene.simulated_trajectories)} objects, joint scene 0 has {len(ids)}"
            )
        for traj in scene.simulated_trajectories:
            k = pos.get(int(traj.object_id))
            if k is None:
                raise SubmissionError(
                    f"scenario {rollouts.scenario_id}, joint scene {j}: object "
                    f"{traj.object_id} is not in joint scene 0"
                )
            for c, name in enumerate(_COORDS):
                values = getattr(traj, name)
                if len(values) != steps:
                    raise SubmissionError(
                        f"scenario {rollouts.scenario_id}, joint scene {j}, object "
                        f"{traj.object_id}: {name} has {len(values)} steps, expected {steps}"
                    )
                arr[c, j, k] = values
    t = torch.as_tensor(arr, device=device)
    return Rollouts(
        scenario_id=rollouts.scenario_id,
        object_id=torch.tensor(ids, dtype=torch.int64, device=device),
        x=t[0],
        y=t[1],
        z=t[2],
        heading=t[3],
    )


def rollouts_to_proto(rollouts: Rollouts) -> pb.ScenarioRollouts:
    """Convert tensors to ``ScenarioRollouts`` (float32 values, one joint scene per rollout)."""
    stacked = torch.stack([rollouts.x, rollouts.y, rollouts.z, rollouts.heading]).float()
    arr = stacked.cpu().numpy()  # [4, R, A, S]
    ids = rollouts.object_id.cpu().tolist()
    out = pb.ScenarioRollouts(scenario_id=rollouts.scenario_id)
    for j in range(rollouts.num_rollouts):
        scene = out.joint_scenes.add()
        for k, oid in enumerate(ids):
            scene.simulated_trajectories.add(
                object_id=int(oid),
                center_x=arr[0, j, k].tolist(),
                center_y=arr[1, j, k].tolist(),
                center_z=arr[2, j, k].tolist(),
                heading=arr[3, j, k].tolist(),
            )
    return out
