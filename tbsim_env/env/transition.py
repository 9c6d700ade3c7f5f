"""One environment transition, shared by ``TrafficEnv`` and ``BatchedTrafficEnv``.

The order of a step is defined here once: NPC actions, merge with the external actions,
dynamics and log replay (``core.step``), per-agent metrics of the externally controlled agents,
rewards and terminations, then (when the config asks for it) terminated agents leave the
scene. Everything after the NPC actions is ``advance``, pure tensor code that
``torch.compile`` can trace whole (``tbsim_env.env.fused``). The envs add only what their
API needs around it (action parsing, dicts or tensors, episode bookkeeping, observations).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import torch

from policies.base import Policy
from tbsim_env.config import EnvConfig
from tbsim_env.env.agent_metrics import Route, StepMetrics, step_metrics
from tbsim_env.env.rewards import RewardOutcome, reward_and_termination
from tbsim_env.errors import PolicyError
from tbsim_env.sim import core
from tbsim_env.sim.state import SimState
from tbsim_env.torch_utils import cached_arange


@dataclass(frozen=True)
class Controllers:
    """Who drives which agent slot in a batch of scenarios.

    Attributes:
        external: [B, N] bool, slots driven by the caller's actions.
        npc: [B, N] bool, slots driven by ``policy`` (empty when it replays the log exactly).
        policy: the NPC policy.
        has_npc: ``npc`` is not empty (the policy acts every step).
    """

    external: torch.Tensor
    npc: torch.Tensor
    policy: Policy
    has_npc: bool


@dataclass(frozen=True)
class Transition:
    """Result of ``transition``.

    Attributes:
        state: the next state (terminated agents removed when the config says so).
        metrics: ``step_metrics`` of the query agents in the next state (before removal).
        outcome: rewards and terminations of the query agents.
        goal_reached: [B, Q] bool, reached before or at this step.
        policy_state: the NPC policy's state after acting (``policy_state`` without NPCs).
    """

    state: SimState
    metrics: StepMetrics
    outcome: RewardOutcome
    goal_reached: torch.Tensor
    policy_state: Any


def transition(
    state: SimState,
    ext_action: torch.Tensor,
    ctrl: Controllers,
    query: torch.Tensor,
    policy_state: Any,
    generator: torch.Generator,
    route: Route,
    progress: torch.Tensor,
    goal_reached: torch.Tensor,
    has_goal: torch.Tensor,
    config: EnvConfig,
    active: torch.Tensor | None = None,
) -> Transition:
    """Advance a batch of scenarios by one step: the NPCs act, then ``advance``.

    Args:
        state: current state.
        ext_action: [B, N, 2] actions of the external slots (others are not read).
        ctrl: the controller assignment.
        query: [B, Q] int64, slots of the externally controlled agents (metrics, rewards).
        policy_state: the NPC policy's state (not read without NPCs).
        generator: random stream of stochastic policies.
        route, progress, goal_reached, has_goal, config, active: as ``advance``.
    """
    action, policy_state = npc_actions(state, ext_action, ctrl, policy_state, generator)
    out = advance(state, action, query, route, progress, goal_reached, has_goal, config, active)
    return dataclasses.replace(out, policy_state=policy_state)


def npc_actions(
    state: SimState,
    ext_action: torch.Tensor,
    ctrl: Controllers,
    policy_state: Any,
    generator: torch.Generator,
) -> tuple[torch.Tensor, Any]:
    """(The actions of every slot [B, N, 2]: the NPC policy's merged with ``ext_action``, the
    policy's next state); ``ext_action`` and ``policy_state`` unchanged without NPCs.

    Raises:
        PolicyError: the policy gave a NaN or infinite action to an NPC it drives (naming the
            policy, and the batch rows and track ids of those NPCs); the dynamics never see it.
    """
    if not ctrl.has_npc:
        return ext_action, policy_state
    npc_action, policy_state = ctrl.policy.act(state, policy_state, generator)
    bad = ctrl.npc & state.valid & ~torch.isfinite(npc_action).all(-1)
    if bool(bad.any()):
        rows, slots = bad.nonzero(as_tuple=True)
        ids = state.agents.track_id[rows, slots].tolist()
        agents = [f"row {r} track {t}" for r, t in zip(rows.tolist(), ids)]
        more = f" and {len(agents) - 5} more" if len(agents) > 5 else ""
        name = getattr(ctrl.policy, "name", type(ctrl.policy).__name__)
        raise PolicyError(
            f"NPC policy {name!r} returned a non-finite action at step "
            f"{int(state.step.max())} for {len(agents)} agent(s): {', '.join(agents[:5])}{more}"
        )
    action = core.merge_actions((ctrl.npc, npc_action), (ctrl.external, ext_action))
    return action, policy_state


def advance(
    state: SimState,
    action: torch.Tensor,
    query: torch.Tensor,
    route: Route,
    progress: torch.Tensor,
    goal_reached: torch.Tensor,
    has_goal: torch.Tensor,
    config: EnvConfig,
    active: torch.Tensor | None = None,
) -> Transition:
    """The step after the actions are known: dynamics and log replay, metrics, rewards,
    terminations and removals. Pure tensor code (``torch.compile`` traces it in one graph).

    Args:
        state: current state.
        action: [B, N, 2] actions of every slot (only controlled slots are read).
        query: [B, Q] int64, slots of the externally controlled agents (metrics, rewards).
        route: logged routes of the query agents.
        progress: [B, Q] m, best progress along the route so far.
        goal_reached: [B, Q] bool, the goal was reached before this step.
        has_goal: [B, Q] bool, the route is longer than the goal radius.
        config: rewards, terminations and whether terminated agents leave.
        active: optional [B, Q] bool, the query agents whose termination removes them (e.g.
            not the padding of a batch); all by default.

    Returns:
        The transition, with ``policy_state`` None.
    """
    state = core.step(state, action)
    metrics = step_metrics(state, query, route)
    outcome = reward_and_termination(
        metrics, progress, goal_reached, has_goal, config.reward, config.termination
    )
    leaving = outcome.terminated if active is None else outcome.terminated & active
    # Eagerly, skip the removal when nobody leaves; a compiled graph cannot branch on data.
    if config.remove_terminated and (torch.compiler.is_compiling() or bool(leaving.any())):
        state = remove_agents(state, query, leaving)
    return Transition(
        state=state,
        metrics=metrics,
        outcome=outcome,
        goal_reached=goal_reached | outcome.goal_now,
        policy_state=None,
    )


def remove_agents(state: SimState, query: torch.Tensor, remove: torch.Tensor) -> SimState:
    """``state`` without the query agents flagged in ``remove`` [B, Q] (they leave for good)."""
    slots = cached_arange(state.num_agents, state.device)
    gone = ((query.unsqueeze(-1) == slots) & remove.unsqueeze(-1)).any(1)  # [B, N]
    return state.replace(valid=state.valid & ~gone)
