"""What both environments do once at construction: device, scenarios, controlled agents, NPC
policy.

One definition each of: the device (``resolve_device``), where scenarios come from
(``resolve_scenarios``), which agents a ``controlled`` spec selects (``controlled_indices``),
the agents' PettingZoo names (``agent_name``), how the NPC policy is made
(``make_npc_policy``), and which scenarios an env can run (``select_scenarios``: the episode's
time grid, the log-length check of log replay, scenes where nothing is controllable)."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from policies import make_policy
from policies.base import Policy
from tbsim_env.core.config import EnvConfig
from tbsim_env.core.errors import UnusableScenarioError
from tbsim_env.core.malloc import keep_freed_memory
from tbsim_env.data.scenario import Scenario
from tbsim_env.sim.horizon import episode_scenario

ControlledSpec = str | Sequence[int]


def agent_name(track_id: int) -> str:
    """PettingZoo name of the agent with WOMD track id ``track_id``."""
    return f"track_{int(track_id)}"


def resolve_device(device: str | torch.device) -> torch.device:
    """``torch.device(device)``; on the CPU, ``malloc.keep_freed_memory()`` too (once per
    process: a step's freed temporaries stay with the process instead of page-faulting back)."""
    out = torch.device(device)
    if out.type == "cpu":
        keep_freed_memory()
    return out


def resolve_scenarios(scenarios: Any) -> list[Scenario]:
    """Scenarios from None (embedded default), a path / glob / folder, or a list of either.

    ``Scenario`` objects given directly are validated like the ones a reader returns
    (``Scenario.validate``: shapes, references, plausibility bounds).

    Raises:
        ScenarioFormatError: a file or a given ``Scenario`` is malformed or implausible.
    """
    if scenarios is None:
        from tbsim_env.data.generator import default_scenarios

        return list(default_scenarios())
    if isinstance(scenarios, Scenario):
        return [scenarios.validate()]
    from tbsim_env.data import load_scenarios

    if isinstance(scenarios, (str, os.PathLike)):
        out = load_scenarios(scenarios)
    else:
        items = list(scenarios)
        if all(isinstance(s, Scenario) for s in items):
            out = [s.validate() for s in items]
        else:
            out = load_scenarios(items)
    if not out:
        raise ValueError(f"no scenarios found in {scenarios!r}")
    return out


def controlled_indices(scenario: Scenario, controlled: ControlledSpec, start: int) -> list[int]:
    """Track indices of the externally controlled agents (all must be valid at ``start``).

    Args:
        scenario: the scenario.
        controlled: ``"sdc"``, ``"tracks_to_predict"``, ``"all"``, or track ids.
        start: the first simulated step.
    """
    valid = scenario.tracks.valid[:, start]
    if isinstance(controlled, str):
        if controlled == "sdc":
            idx = [scenario.sdc_index]
        elif controlled == "tracks_to_predict":
            idx = sorted(set(int(i) for i in scenario.tracks_to_predict) | {scenario.sdc_index})
        elif controlled == "all":
            idx = [int(i) for i in np.flatnonzero(valid)]
        else:
            raise ValueError(
                f"controlled={controlled!r}; use 'sdc', 'tracks_to_predict', 'all' or a list "
                "of track ids"
            )
        return [i for i in idx if valid[i]]
    ids = {int(t): k for k, t in enumerate(scenario.tracks.id)}
    out = []
    for tid in controlled:
        if int(tid) not in ids:
            raise UnusableScenarioError(
                f"no track with id {tid} (controlled={list(controlled)!r})",
                scenario.scenario_id,
                scenario.source,
            )
        if not valid[ids[int(tid)]]:
            raise UnusableScenarioError(
                f"track {tid} is not valid at step {start}, so it cannot be controlled from "
                "the start",
                scenario.scenario_id,
                scenario.source,
            )
        out.append(ids[int(tid)])
    return out


def make_npc_policy(
    npc_policy: str | Policy, kwargs: dict[str, Any] | None, device: torch.device
) -> Policy:
    """The NPC policy of an env: a ``Policy`` as given, or a registered name built with
    ``kwargs`` (``"trafficbots"`` on the env's device, trimmed to the token rows the
    scenarios use and keeping each scene's tokens and encoding for its next episodes, unless
    ``kwargs`` say otherwise)."""
    kwargs = dict(kwargs or {})
    if npc_policy == "trafficbots":
        kwargs.setdefault("device", str(device))
        kwargs.setdefault("trim", True)
        kwargs.setdefault("cache_scenes", True)
    return make_policy(npc_policy, **kwargs)


@dataclass(frozen=True)
class Selection:
    """The scenarios an env runs and the agents it hands to the caller.

    Attributes:
        scenarios: on the episode's time grid (``Scenario.on_time_grid``).
        queries: per scenario, the track indices of its externally controlled agents.
    """

    scenarios: list[Scenario]
    queries: list[list[int]]


def select_scenarios(
    scenarios: Any,
    controlled: ControlledSpec,
    config: EnvConfig,
    policy: Policy,
    drop_unusable: bool,
) -> Selection:
    """The scenarios of ``scenarios`` an env with these settings can run.

    Args:
        scenarios: as ``resolve_scenarios``.
        controlled: which agents the caller controls.
        config: the episode settings (time grid, start step).
        policy: the NPC policy (log replay needs the log up to the last step).
        drop_unusable: leave out scenarios where ``controlled`` selects no agent valid at
            the start (an error only when none is left); otherwise each is an error.

    Raises:
        UnusableScenarioError: a scenario (or every one, with ``drop_unusable``) has no
            controllable agent; ``MissingFutureError`` for log replay of a short log.
    """
    replays = bool(getattr(policy, "exact_replay", False))
    every = [
        episode_scenario(sc, config, replays_log=replays) for sc in resolve_scenarios(scenarios)
    ]
    start = config.start_step
    kept, queries = [], []
    for sc in every:
        idx = controlled_indices(sc, controlled, start)
        if not idx and not drop_unusable:
            raise UnusableScenarioError(
                f"controlled={controlled!r} selects no agent valid at the start step {start}",
                sc.scenario_id,
                sc.source,
            )
        if idx:
            kept.append(sc)
            queries.append(idx)
    if not kept:
        names = ", ".join(f"{sc.scenario_id} ({sc.source})" for sc in every[:3])
        more = f" and {len(every) - 3} more" if len(every) > 3 else ""
        raise UnusableScenarioError(
            f"controlled={controlled!r} selects no agent valid at the start step {start} "
            f"in any of the scenarios: {names}{more}"
        )
    return Selection(scenarios=kept, queries=queries)


__all__ = [
    "ControlledSpec",
    "Selection",
    "agent_name",
    "controlled_indices",
    "make_npc_policy",
    "resolve_device",
    "resolve_scenarios",
    "select_scenarios",
]
