"""Log replay: agents follow their logged trajectories.

Two ways to replay, both honest about what they are:

* In ``TrafficEnv`` (``npc_policy="log_replay"``) NPCs are simply not controlled: the
  simulator copies the logged state every step, so the replay is exact.
* As a ``Policy`` (for agents that must go through the dynamics, e.g. to compare a learned
  policy with the log under the same integrator), ``LogReplayPolicy.act`` returns the expert
  actions of ``inverse_unicycle`` at the current step; following them reproduces the log
  within centimetres wherever the log is feasible for the unicycle.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import torch

from tbsim_env.data.scenario import Scenario
from tbsim_env.sim.dynamics import inverse_unicycle
from tbsim_env.sim.state import SimState


@dataclass(frozen=True)
class ExpertActions:
    """Expert actions of the whole log.

    Attributes:
        action: [B, N, T-1, 2] (acceleration, yaw rate) from step t to t+1.
        valid: [B, N, T-1] bool.
    """

    action: torch.Tensor
    valid: torch.Tensor


class LogReplayPolicy:
    """Expert (inverse-dynamics) actions that track the log."""

    name = "log_replay"
    exact_replay = True
    """``TrafficEnv`` replays agents of this policy exactly instead of integrating actions."""

    def initial_state(
        self, state: SimState, scenarios: Sequence[Scenario], generator: torch.Generator
    ) -> ExpertActions:
        del scenarios, generator  # Unused.
        log = state.log
        pose, speed, valid = log.take("pose"), log.take("speed"), log.take("valid")
        action, valid = inverse_unicycle(pose, speed, valid, state.agents.object_type)
        return ExpertActions(action=action, valid=valid)

    def act(
        self, state: SimState, policy_state: ExpertActions, generator: torch.Generator
    ) -> tuple[torch.Tensor, ExpertActions]:
        del generator  # Unused.
        t = state.step.clamp(max=policy_state.action.shape[2] - 1)
        idx = t.view(-1, 1, 1, 1).expand(-1, state.num_agents, 1, 2)
        action = policy_state.action.gather(2, idx)[:, :, 0]
        return action, policy_state
