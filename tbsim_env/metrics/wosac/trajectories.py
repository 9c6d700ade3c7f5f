"""Trajectories the WOSAC features are computed on (docs/metrics.md, "Trajectories").

Sim agents are the tracks valid at the current step; evaluated agents are the SDC plus the
tracks to predict (those that are sim agents), sorted by id. The object axis is ordered
evaluated-first (sorted by id), then the other sim agents in track order. Every trajectory
spans the whole scenario (91 steps): logged history, then the logged or simulated future. Box
sizes are the ones logged at the current step, for every step. Everything is float32.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from tbsim_env.data.scenario import Scenario
from tbsim_env.metrics.wosac.rollouts import Rollouts


@dataclass(frozen=True)
class MetricObjects:
    """Which tracks are simulated and evaluated, in metric order.

    Attributes:
        track_index: [N] int64 indices into ``scenario.tracks``, evaluated objects first.
        object_id: [N] int64 track ids in the same order.
        num_eval: E, the first E objects are the evaluated ones (sorted by id).
    """

    track_index: np.ndarray
    object_id: np.ndarray
    num_eval: int

    @property
    def num_objects(self) -> int:
        return int(self.track_index.shape[0])

    @property
    def eval_ids(self) -> np.ndarray:
        return self.object_id[: self.num_eval]


def select_objects(scenario: Scenario) -> MetricObjects:
    """Sim agents (valid at the current step) and evaluated agents (SDC + tracks_to_predict)."""
    tracks = scenario.tracks
    sim = scenario.sim_agent_indices()
    wanted = np.unique(
        np.append(np.asarray(scenario.tracks_to_predict, np.int64), scenario.sdc_index)
    )
    evaluated = np.intersect1d(wanted, sim)
    evaluated = evaluated[np.argsort(tracks.id[evaluated], kind="stable")]
    others = sim[~np.isin(sim, evaluated)]
    order = np.concatenate([evaluated, others]).astype(np.int64)
    return MetricObjects(
        track_index=order, object_id=tracks.id[order].astype(np.int64), num_eval=len(evaluated)
    )


@dataclass(frozen=True)
class ObjectTrajectories:
    """R rollouts of N objects over T steps, float32 on one device.

    Attributes:
        x, y, z: [R, N, T] box centre in metres (scenario frame).
        heading: [R, N, T] yaw in radians, as stored (not re-wrapped).
        valid: [R, N, T] bool.
        length, width, height: [N] box size in metres (logged at the current step).
        object_type: [N] int64 ``ObjectType`` values.
        num_eval: the first E objects are evaluated.
    """

    x: torch.Tensor
    y: torch.Tensor
    z: torch.Tensor
    heading: torch.Tensor
    valid: torch.Tensor
    length: torch.Tensor
    width: torch.Tensor
    height: torch.Tensor
    object_type: torch.Tensor
    num_eval: int

    @property
    def num_rollouts(self) -> int:
        return int(self.x.shape[0])

    def evaluated(self, values: torch.Tensor) -> torch.Tensor:
        """Slice the object axis (dim 1 of [R, N, ...] or dim 0 of [N]) to the evaluated ones."""
        return values[:, : self.num_eval] if values.dim() > 1 else values[: self.num_eval]


def _f32(array: np.ndarray, device: torch.device | str) -> torch.Tensor:
    return torch.as_tensor(np.asarray(array, np.float32), device=device)


def log_trajectories(
    scenario: Scenario, objects: MetricObjects, device: torch.device | str = "cpu"
) -> ObjectTrajectories:
    """The logged trajectories (R = 1), invalid steps keeping their stored placeholder values."""
    tracks = scenario.tracks
    idx = objects.track_index
    xyz = tracks.xyz[idx]
    size = tracks.size[idx, scenario.current_index]
    return ObjectTrajectories(
        x=_f32(xyz[None, :, :, 0], device),
        y=_f32(xyz[None, :, :, 1], device),
        z=_f32(xyz[None, :, :, 2], device),
        heading=_f32(tracks.stored_heading()[None, idx], device),
        valid=torch.as_tensor(tracks.valid[None, idx], device=device),
        length=_f32(size[:, 0], device),
        width=_f32(size[:, 1], device),
        height=_f32(size[:, 2], device),
        object_type=torch.as_tensor(tracks.object_type[idx].astype(np.int64), device=device),
        num_eval=objects.num_eval,
    )


def simulated_trajectories(
    log: ObjectTrajectories, objects: MetricObjects, rollouts: Rollouts, current_index: int
) -> ObjectTrajectories:
    """Logged history (steps 0..current) followed by the simulated future, valid throughout.

    Args:
        log: the logged trajectories of ``objects`` (R = 1).
        objects: metric order of the sim agents.
        rollouts: the simulated futures; must hold every sim agent (any order).
        current_index: last history step.
    """
    pos = {int(i): k for k, i in enumerate(rollouts.object_id.tolist())}
    gather = torch.tensor([pos[int(i)] for i in objects.object_id], device=rollouts.x.device)
    r = rollouts.num_rollouts
    device = log.x.device
    h = current_index + 1

    def join(hist: torch.Tensor, fut: torch.Tensor) -> torch.Tensor:
        fut = fut.index_select(1, gather).to(device=device, dtype=torch.float32)
        return torch.cat([hist[:, :, :h].expand(r, -1, -1), fut], dim=-1)

    valid = torch.cat(
        [
            log.valid[:, :, :h].expand(r, -1, -1),
            torch.ones(r, log.x.shape[1], rollouts.num_steps, dtype=torch.bool, device=device),
        ],
        dim=-1,
    )
    return ObjectTrajectories(
        x=join(log.x, rollouts.x),
        y=join(log.y, rollouts.y),
        z=join(log.z, rollouts.z),
        heading=join(log.heading, rollouts.heading),
        valid=valid,
        length=log.length,
        width=log.width,
        height=log.height,
        object_type=log.object_type,
        num_eval=log.num_eval,
    )


def concat_rollouts(first: ObjectTrajectories, second: ObjectTrajectories) -> ObjectTrajectories:
    """Stack two sets of trajectories of the same objects along the rollout axis.

    Lets the log (R = 1, logged validity) and the simulations go through the feature code in
    one batch; per-rollout validity keeps them independent.
    """
    if first.num_eval != second.num_eval or first.x.shape[1:] != second.x.shape[1:]:
        raise ValueError("concat_rollouts needs trajectories of the same objects and steps")

    def cat(name: str) -> torch.Tensor:
        return torch.cat([getattr(first, name), getattr(second, name)], dim=0)

    return ObjectTrajectories(
        x=cat("x"),
        y=cat("y"),
        z=cat("z"),
        heading=cat("heading"),
        valid=cat("valid"),
        length=first.length,
        width=first.width,
        height=first.height,
        object_type=first.object_type,
        num_eval=first.num_eval,
    )
