"""The step of ``TrafficEnv`` after the NPC actions, as one pure function, optionally compiled.

``advance_and_observe`` runs ``transition.advance`` (dynamics and log replay, metrics, rewards,
terminations, removals), appends the new state to the history and observes it.
``StepFunction`` calls it eagerly or through ``torch.compile``. A batch-of-one step is a few
hundred tiny tensor operations, so most of its time is per-operation overhead (Python, the
dispatcher, allocation). One compiled graph of fused C++ kernels removes most of it: about
twice the env steps/s on one CPU thread (``bench/env_step.py`` prints both).

A compiled graph cannot branch on data, so three eager shortcuts are not taken inside it (each
checks ``torch.compiler.is_compiling()``): the batch-of-one paths that read the step as a
Python number index instead, the collision test does not stop early when nobody is near, and
the box corners the road-edge grid cannot vouch for are not recomputed over every segment.
The step reports them in ``StepMetrics.offroad_stale`` instead, and ``StepFunction`` redoes
such a step eagerly (rare: a corner far from the map, or in a cell crowded with edges).

Compiled results equal the eager ones up to float rounding (inductor fuses and reorders
arithmetic: observations differ by ~1e-7), so ``compile=True`` gives up ``TrafficEnv``'s
bit-for-bit equality with ``BatchedTrafficEnv`` for speed. Compiling takes ~15 s on the
first step (and again, once, when a scenario of another shape arrives: the second graph has
dynamic shapes) and needs a C++ compiler, as ``torch.compile`` on the CPU does.
"""

from __future__ import annotations

from typing import NamedTuple

import torch

from tbsim_env.config import EnvConfig
from tbsim_env.env.agent_metrics import Route
from tbsim_env.env.transition import Transition, advance
from tbsim_env.observation import (
    History,
    IndexedObservation,
    MapContext,
    ObsConfig,
    observe,
    observe_indexed,
    push_history,
)
from tbsim_env.sim.state import SimState


class FusedStep(NamedTuple):
    """Result of ``advance_and_observe``.

    Attributes:
        transition: ``advance``'s result (``policy_state`` None).
        history: the history with the new state appended.
        obs: ``observe`` of the query agents in the new state, [B, Q, ...] per key.
    """

    transition: Transition
    history: History
    obs: dict[str, torch.Tensor]


def advance_and_observe(
    state: SimState,
    action: torch.Tensor,
    query: torch.Tensor,
    route: Route,
    progress: torch.Tensor,
    goal_reached: torch.Tensor,
    has_goal: torch.Tensor,
    config: EnvConfig,
    history: History,
    ctx: MapContext,
    obs_config: ObsConfig,
    agent_static: torch.Tensor,
) -> FusedStep:
    """``advance``, then the history and the observations of the query agents.

    Args:
        state .. config: as ``transition.advance`` (``action`` [B, N, 2] of every slot, NPC
            actions merged in).
        history: the history ending at ``state``'s step.
        ctx: the batch's static map context.
        obs_config: observation sizes.
        agent_static: ``agent_static_features`` of the batch.
    """
    tr = advance(state, action, query, route, progress, goal_reached, has_goal, config)
    # Removing terminated agents leaves every pose as step_metrics saw it, so the agent
    # distances of the metrics serve the observations.
    history = push_history(history, tr.state)
    obs = observe(
        tr.state,
        history,
        ctx,
        query,
        obs_config,
        agent_static=agent_static,
        agent_distance=tr.metrics.agent_distance,
    )
    return FusedStep(tr, history, obs)


class IndexedStep(NamedTuple):
    """Result of ``advance_and_observe_indexed``: the transition, the history with the new
    state appended, and the indexed observation of the query agents."""

    transition: Transition
    history: History
    obs: IndexedObservation


def advance_and_observe_indexed(
    state: SimState,
    action: torch.Tensor,
    query: torch.Tensor,
    route: Route,
    progress: torch.Tensor,
    goal_reached: torch.Tensor,
    has_goal: torch.Tensor,
    config: EnvConfig,
    history: History,
    ctx: MapContext,
    obs_config: ObsConfig,
    agent_static: torch.Tensor,
    active: torch.Tensor,
) -> IndexedStep:
    """``BatchedTrafficEnv``'s step after the NPC actions: ``advance`` (only ``active`` query
    agents may leave), the history, and ``observe_indexed`` of the query agents (arguments as
    ``advance_and_observe``)."""
    tr = advance(state, action, query, route, progress, goal_reached, has_goal, config, active)
    history = push_history(history, tr.state)
    obs = observe_indexed(tr.state, history, ctx, query, obs_config, agent_static)
    return IndexedStep(tr, history, obs)


class StepFunction:
    """A fused step function (``advance_and_observe`` by default), eager or compiled with
    ``torch.compile``.

    Attributes:
        eager_redos: compiled steps redone eagerly because the road-edge grid could not
            vouch for more box corners than the graph recomputes (see the module docstring).
    """

    def __init__(self, compile: bool = False, fn=advance_and_observe) -> None:
        self.eager_redos = 0
        self._eager = fn
        self._fn = torch.compile(fn, fullgraph=True) if compile else None

    def __call__(self, *args):
        """``fn(*args)``, through the compiled graph when there is one."""
        if self._fn is None:
            return self._eager(*args)
        out = self._fn(*args)
        if bool(out.transition.metrics.offroad_stale.any()):
            self.eager_redos += 1
            out = self._eager(*args)
        return out


__all__ = [
    "FusedStep",
    "IndexedStep",
    "StepFunction",
    "advance_and_observe",
    "advance_and_observe_indexed",
]
