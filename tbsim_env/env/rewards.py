"""Reward and termination of externally controlled agents: one definition for every env."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from tbsim_env.config import RewardConfig, TerminationConfig
from tbsim_env.env.agent_metrics import StepMetrics
from tbsim_env.torch_utils import const


@dataclass(frozen=True)
class RewardOutcome:
    """Result of ``reward_and_termination``.

    Attributes:
        reward: [B, Q] float32 reward of this step.
        terminated: [B, Q] bool, the agent's episode ends by an event this step.
        goal_now: [B, Q] bool, the agent reached its goal this step (first time).
        progress_best: [B, Q] m, best progress so far (the new baseline).
    """

    reward: torch.Tensor
    terminated: torch.Tensor
    goal_now: torch.Tensor
    progress_best: torch.Tensor


def reward_and_termination(
    metrics: StepMetrics,
    progress_best: torch.Tensor,
    goal_reached: torch.Tensor,
    has_goal: torch.Tensor,
    reward_config: RewardConfig,
    termination_config: TerminationConfig,
) -> RewardOutcome:
    """Per-agent reward and termination of one step (the definition of ``TrafficEnv``).

    reward = collision * [collided] + offroad * [off road] + progress * (metres of new
    progress beyond the best so far) + goal * [goal reached now] + log_divergence * gap + alive.

    Args:
        metrics: ``step_metrics`` of the new state, fields [B, Q].
        progress_best: [B, Q] m, best progress along the logged route before this step.
        goal_reached: [B, Q] bool, the goal was reached before this step.
        has_goal: [B, Q] bool, the logged route is longer than the goal radius.
        reward_config: reward weights.
        termination_config: termination events.
    """
    rc, tc = reward_config, termination_config
    # Weights as cached float32 constants: the same bits as Python floats (which become
    # float32 scalars here), without wrapping a new tensor per operation. Zeros stay Python
    # floats (the constant cache does not tell 0.0 from -0.0).
    w = lambda value: value if value == 0 else const(float(value), progress_best)  # noqa: E731
    gained = (metrics.progress - progress_best).clamp_min(0.0)
    goal_now = (metrics.goal_distance <= w(rc.goal_radius)) & has_goal & ~goal_reached
    coll, off = metrics.collision, metrics.offroad
    # Terms with weight 0 are skipped: they add (+/-) 0 (the metrics are finite), and the
    # final ``+ rc.alive`` turns a -0 sum into +0 exactly as the full sum would.
    terms = (
        (rc.collision, coll),
        (rc.offroad, off),
        (rc.progress, gained),
        (rc.goal, goal_now),
        (rc.log_divergence, metrics.log_divergence),
    )
    reward = None
    for weight, value in terms:
        if weight != 0.0:
            reward = w(weight) * value if reward is None else reward + w(weight) * value
    reward = (torch.zeros_like(gained) if reward is None else reward) + w(rc.alive)
    events = [x for on, x in ((tc.collision, coll), (tc.offroad, off), (tc.goal, goal_now)) if on]
    term = torch.zeros_like(coll) if not events else events[0]
    for x in events[1:]:
        term = term | x
    return RewardOutcome(
        reward=reward.float(),
        terminated=term,
        goal_now=goal_now,
        progress_best=torch.maximum(progress_best, metrics.progress),
    )
