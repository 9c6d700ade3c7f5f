"""``Rollouts``: R simulated futures of A objects of one scenario, as tensors.

This is the in-memory form of a submission's ``ScenarioRollouts`` (see ``submission.py`` for the
proto converters) and what ``score_scenario`` consumes.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from tbsim_env.core.constants import MAX_ABS_COORDINATE, MAX_ABS_HEADING, NUM_FUTURE
from tbsim_env.core.errors import TbsimError
from tbsim_env.data.scenario import Scenario
from tbsim_env.metrics.wosac.config import NUM_ROLLOUTS


class RolloutsError(TbsimError, ValueError):
    """A ``Rollouts`` container has inconsistent shapes or ids."""


@dataclass(frozen=True)
class Rollouts:
    """Simulated futures of one scenario.

    Attributes:
        scenario_id: the scenario they belong to.
        object_id: [A] int64 track ids (unique).
        x, y, z: [R, A, S] float32 box centre in metres, scenario frame, for the S future steps
            after the current one (S = 80 in WOMD).
        heading: [R, A, S] float32 yaw in radians, CCW from +x.
    """

    scenario_id: str
    object_id: torch.Tensor
    x: torch.Tensor
    y: torch.Tensor
    z: torch.Tensor
    heading: torch.Tensor

    def __post_init__(self) -> None:
        shape = tuple(self.x.shape)
        if len(shape) != 3:
            raise RolloutsError(f"rollouts of {self.scenario_id}: x has shape {shape}, need 3-D")
        for name in ("y", "z", "heading"):
            if tuple(getattr(self, name).shape) != shape:
                raise RolloutsError(
                    f"rollouts of {self.scenario_id}: {name} has shape "
                    f"{tuple(getattr(self, name).shape)}, x has {shape}"
                )
        if tuple(self.object_id.shape) != (shape[1],):
            raise RolloutsError(
                f"rollouts of {self.scenario_id}: object_id has shape "
                f"{tuple(self.object_id.shape)}, expected ({shape[1]},)"
            )
        if torch.unique(self.object_id).numel() != shape[1]:
            raise RolloutsError(f"rollouts of {self.scenario_id}: duplicate object ids")

    @property
    def num_rollouts(self) -> int:
        return int(self.x.shape[0])

    @property
    def num_objects(self) -> int:
        return int(self.x.shape[1])

    @property
    def num_steps(self) -> int:
        return int(self.x.shape[2])

    def select(self, index: torch.Tensor) -> Rollouts:
        """The rollouts at ``index`` ([K] int64), in that order."""
        index = index.to(self.x.device)
        return Rollouts(
            scenario_id=self.scenario_id,
            object_id=self.object_id,
            x=self.x[index],
            y=self.y[index],
            z=self.z[index],
            heading=self.heading[index],
        )

    def mismatch(self, scenario: Scenario, num_steps: int = NUM_FUTURE) -> str | None:
        """Why these rollouts cannot be rollouts of ``scenario``, or None: another scenario
        id, not ``num_steps`` steps, or a sim agent (``Scenario.sim_agent_indices``) missing.
        The one check of the scorer and the viewer (the submission validator checks the proto
        the same way, object by object)."""
        if self.scenario_id != scenario.scenario_id:
            return f"rollouts are for scenario {self.scenario_id!r}, not {scenario.scenario_id!r}"
        where = f"scenario {scenario.scenario_id}"
        if self.num_steps != num_steps:
            return f"{where}: rollouts have {self.num_steps} steps, expected {num_steps}"
        have = set(self.object_id.tolist())
        ids = scenario.tracks.id[scenario.sim_agent_indices()]
        missing = [int(i) for i in ids if int(i) not in have]
        return f"{where}: rollouts miss sim agents {missing}" if missing else None

    def impossible_value(self) -> str | None:
        """The first value no real rollout holds, described (rollout, object, step, field), or
        None: every value must be finite, positions within ``MAX_ABS_COORDINATE`` and
        headings within ``MAX_ABS_HEADING`` (the submission validator's rule)."""
        for name in ("x", "y", "z", "heading"):
            values = getattr(self, name)
            bound = MAX_ABS_HEADING if name == "heading" else MAX_ABS_COORDINATE
            bad = ~(values.abs() <= bound)  # NaN compares False
            if bool(bad.any()):
                r, a, t = (int(i) for i in bad.nonzero()[0])
                return (
                    f"rollout {r}, object {int(self.object_id[a])}, step {t} of the simulated "
                    f"future: {name} is {float(values[r, a, t])!r}; every value must be finite "
                    f"and within {bound:g} {'rad' if name == 'heading' else 'm'}"
                )
        return None

    def to(self, device: torch.device | str) -> Rollouts:
        """The same rollouts on another device."""
        return Rollouts(
            scenario_id=self.scenario_id,
            object_id=self.object_id.to(device),
            x=self.x.to(device),
            y=self.y.to(device),
            z=self.z.to(device),
            heading=self.heading.to(device),
        )


def log_replay_rollouts(
    scenario: Scenario,
    num_rollouts: int = NUM_ROLLOUTS,
    device: torch.device | str = "cpu",
) -> Rollouts:
    """The logged future of every sim agent, repeated ``num_rollouts`` times.

    Invalid future steps keep their stored placeholder values (like the official "logged
    oracle"), so log replay reproduces the logged features exactly.

    Raises:
        MissingFutureError: the log does not hold the 80 steps after the current one (e.g. a
            WOSAC test-split scene, history only).
    """
    idx = scenario.sim_agent_indices()
    start = scenario.current_index + 1
    stop = start + NUM_FUTURE
    scenario.require_log_until(stop - 1, "log replay")
    fut = scenario.tracks.xyz[idx, start:stop].astype(np.float32)
    head = scenario.tracks.stored_heading()[idx, start:stop].astype(np.float32)

    def rep(a: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(a, device=device).unsqueeze(0).repeat(num_rollouts, 1, 1)

    return Rollouts(
        scenario_id=scenario.scenario_id,
        object_id=torch.as_tensor(scenario.tracks.id[idx].astype(np.int64), device=device),
        x=rep(fut[..., 0]),
        y=rep(fut[..., 1]),
        z=rep(fut[..., 2]),
        heading=rep(head),
    )
