"""The policy interface: any controller of agents in the batched simulator.

The simulation layer defines it and the policies (``policies/``) implement it, so that the
closed-loop rollouts (``metrics.wosac.simulate``) drive any policy without depending on one.

A policy keeps no hidden per-rollout attributes: whatever it remembers (history windows, latent
samples, destinations) lives in an explicit ``PolicyState`` that ``act`` returns and the caller
passes back. One policy object can therefore drive many rollouts at once.

Optional: ``for_scenarios(scenarios) -> Policy``. A caller that will only start rollouts from a
known set of scenarios and restarts batch rows one at a time (``BatchedTrafficEnv``) calls it
once and uses the returned policy, whose state shapes must then be the same for any batch drawn
from the set (``TrafficBotsPolicy`` trims its token rows to those the set uses).

Optional: ``owns_state = True``. Every tensor of the policy's states is the state's alone (no
cache, constant or other state refers to it, none is a view of another), so a caller that
alone holds a state (``BatchedTrafficEnv``) may write restarted rows into it in place instead
of copying the batch's tables (``IDMPolicy``: its routes are megabytes per batch).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

import torch

from tbsim_env.data.scenario import Scenario
from tbsim_env.sim.state import SimState

PolicyState = Any
"""Opaque per-rollout state of a policy (a frozen dataclass of tensors, or None)."""


@runtime_checkable
class Policy(Protocol):
    """Produces actions for every agent slot of a batched ``SimState``."""

    name: str

    def initial_state(
        self, state: SimState, scenarios: Sequence[Scenario], generator: torch.Generator
    ) -> PolicyState:
        """State at the start of a rollout (called once after reset).

        Args:
            state: the simulator state at the first simulated step.
            scenarios: the B scenarios of the batch (for map or metadata needs).
            generator: the rollout's random generator (seeded by the caller).
        """
        ...

    def act(
        self, state: SimState, policy_state: PolicyState, generator: torch.Generator
    ) -> tuple[torch.Tensor, PolicyState]:
        """Actions for all agents.

        Args:
            state: current simulator state.
            policy_state: what ``initial_state`` or the previous ``act`` returned.
            generator: the rollout's random generator.

        Returns:
            (action [B, N, 2] float32 (acceleration m/s^2, yaw rate rad/s) for every agent slot;
            the caller uses it only where this policy controls the agent, and clips it to the
            type limits; next policy state).
        """
        ...
