"""Constant velocity: zero acceleration and zero yaw rate (keep speed and heading)."""

from __future__ import annotations

from collections.abc import Sequence

import torch

from tbsim_env.data.scenario import Scenario
from tbsim_env.sim.state import SimState


class ConstantVelocityPolicy:
    """Every agent keeps its current speed and heading."""

    name = "constant_velocity"
    exact_replay = False

    def initial_state(
        self, state: SimState, scenarios: Sequence[Scenario], generator: torch.Generator
    ) -> None:
        del state, scenarios, generator  # Unused.
        return None

    def act(
        self, state: SimState, policy_state: None, generator: torch.Generator
    ) -> tuple[torch.Tensor, None]:
        del generator  # Unused.
        return torch.zeros(*state.pose.shape[:2], 2, device=state.device), policy_state
