"""Rewards and terminations of externally controlled agents: one definition for every env.

The reward of a step is a weighted sum of *named terms*:

    reward = sum over terms of weight(term) * term(inputs)

Each term is a pure function of ``RewardInputs`` (the step's metrics, the progress gained and
whether the goal was reached this step) returning [B, Q]. The built-in terms are
``REWARD_TERM_NAMES``; ``register_reward_term`` adds one, and ``RewardConfig(terms=...)`` gives
it a weight::

    register_reward_term("speeding", lambda x: (x.speed - 15.0).clamp_min(0.0))
    config = EnvConfig(reward=RewardConfig(terms=(("speeding", -0.1),)))

Terms with weight 0 are not computed. ``RewardOutcome.terms`` holds every computed term, so
``reward == sum(weight * term)`` can be checked (and logged) per term.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from tbsim_env.core.config import RewardConfig, TerminationConfig
from tbsim_env.core.torch_utils import cast, const
from tbsim_env.env.agent_metrics import StepMetrics


@dataclass(frozen=True)
class RewardInputs:
    """What a reward term may read, each [B, Q] over the query agents.

    Attributes:
        metrics: ``step_metrics`` of the new state.
        gained: m of progress along the logged route beyond the best so far (>= 0).
        goal_now: bool, the agent reached its goal this step (first time).
        speed: m/s, the agent's speed in the new state.
    """

    metrics: StepMetrics
    gained: torch.Tensor
    goal_now: torch.Tensor
    speed: torch.Tensor


RewardTerm = Callable[[RewardInputs], torch.Tensor]
"""A reward term: ``RewardInputs`` -> [B, Q] values (bool or float)."""

_TERMS: dict[str, RewardTerm] = {
    "collision": lambda x: x.metrics.collision,
    "offroad": lambda x: x.metrics.offroad,
    "progress": lambda x: x.gained,
    "goal": lambda x: x.goal_now,
    "log_divergence": lambda x: x.metrics.log_divergence,
    "alive": lambda x: torch.ones_like(x.gained),
}

REWARD_TERM_NAMES = tuple(_TERMS)
"""The built-in terms, weighted by the ``RewardConfig`` fields of the same names."""


def register_reward_term(name: str, term: RewardTerm) -> None:
    """Add a reward term that ``RewardConfig(terms=((name, weight), ...))`` can weight.

    Args:
        name: the term's name (not a built-in one; re-registering a user term replaces it).
        term: pure function ``RewardInputs -> [B, Q]`` tensor; it runs inside the compiled
            step when the env compiles, so it must be tensor code without data-dependent
            Python branches.
    """
    if name in REWARD_TERM_NAMES:
        raise ValueError(f"{name!r} is a built-in reward term; weight it with RewardConfig")
    if not callable(term):
        raise TypeError(f"reward term {name!r} must be callable, got {type(term).__name__}")
    _TERMS[name] = term


def reward_weights(config: RewardConfig) -> dict[str, float]:
    """{term name: weight} of every non-zero term of ``config``, built-ins first.

    Raises:
        ValueError: ``config.terms`` names a term nobody registered, or twice.
    """
    weights = {name: float(getattr(config, name)) for name in REWARD_TERM_NAMES}
    for name, weight in config.terms:
        if name not in _TERMS or name in REWARD_TERM_NAMES:
            known = sorted(set(_TERMS) - set(REWARD_TERM_NAMES))
            raise ValueError(
                f"RewardConfig.terms names {name!r}, which is not a registered reward term "
                f"(registered: {known}; built-ins are RewardConfig fields)"
            )
        if name in weights:
            raise ValueError(f"RewardConfig.terms weights {name!r} twice")
        weights[name] = float(weight)
    return {k: w for k, w in weights.items() if w != 0.0}


@dataclass(frozen=True)
class RewardOutcome:
    """Result of ``reward_and_termination``.

    Attributes:
        reward: [B, Q] float32 reward of this step: the weighted sum of ``terms``.
        terms: {name: [B, Q]} the unweighted value (bool or float) of every term with a
            non-zero weight.
        terminated: [B, Q] bool, the agent's episode ends by an event this step.
        goal_now: [B, Q] bool, the agent reached its goal this step (first time).
        progress_best: [B, Q] m, best progress so far (the new baseline).
    """

    reward: torch.Tensor
    terms: dict[str, torch.Tensor]
    terminated: torch.Tensor
    goal_now: torch.Tensor
    progress_best: torch.Tensor


@dataclass(frozen=True)
class Baseline:
    """Per-agent reward state before the step, each [B, Q].

    Attributes:
        progress_best: m, best progress along the logged route so far.
        goal_reached: bool, the goal was reached before this step.
        has_goal: bool, the logged route is longer than the goal radius.
    """

    progress_best: torch.Tensor
    goal_reached: torch.Tensor
    has_goal: torch.Tensor


def reward_and_termination(
    metrics: StepMetrics,
    speed: torch.Tensor,
    baseline: Baseline,
    reward_config: RewardConfig,
    termination_config: TerminationConfig,
) -> RewardOutcome:
    """Per-agent reward and termination of one step (the definition of both envs).

    Args:
        metrics: ``step_metrics`` of the new state, fields [B, Q].
        speed: [B, Q] m/s of the query agents in the new state.
        baseline: progress, goal and has-goal state before this step.
        reward_config: term weights and the goal radius.
        termination_config: termination events.
    """
    best = baseline.progress_best
    gained = (metrics.progress - best).clamp_min_(const(0.0, best))
    radius = const(float(reward_config.goal_radius), best)
    goal_now = torch.bitwise_and(
        torch.bitwise_and(metrics.goal_distance <= radius, baseline.has_goal),
        ~baseline.goal_reached,
    )
    inputs = RewardInputs(metrics=metrics, gained=gained, goal_now=goal_now, speed=speed)
    terms: dict[str, torch.Tensor] = {}
    reward = None
    for name, weight in reward_weights(reward_config).items():
        value = _TERMS[name](inputs)
        terms[name] = value
        # A cached float32 constant: the bits of the Python float, without a new tensor; a
        # flag as float 0 / 1 first (two operations where the product's promotion records five).
        if value.dtype == torch.bool and best.dtype == torch.float32:
            value = cast(value, best.dtype)
        weighted = const(weight, best) * value
        reward = weighted if reward is None else reward + weighted
    # "+ 0.0" makes an all -0 sum +0, as a sum over the zero-weight terms would.
    reward = torch.zeros_like(gained) if reward is None else reward + const(0.0, reward)
    tc = termination_config
    events = [x for on, x in ((tc.collision, metrics.collision), (tc.offroad, metrics.offroad),
                              (tc.goal, goal_now)) if on]  # fmt: skip
    terminated = torch.zeros_like(metrics.collision) if not events else events[0]
    for x in events[1:]:
        terminated = torch.bitwise_or(terminated, x)
    return RewardOutcome(
        reward=reward if reward.dtype == torch.float32 else reward.float(),
        terms=terms,
        terminated=terminated,
        goal_now=goal_now,
        progress_best=torch.maximum(best, metrics.progress),
    )


__all__ = [
    "REWARD_TERM_NAMES",
    "Baseline",
    "RewardInputs",
    "RewardOutcome",
    "RewardTerm",
    "register_reward_term",
    "reward_and_termination",
    "reward_weights",
]
