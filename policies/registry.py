"""The one registry of policy names, read by the environments, the evaluation and the CLI.

A name stands for up to two things:

* ``agents``: a factory of a ``Policy`` that drives agents step by step. The environments
  use it for their NPCs (``npc_policy="name"``), and the WOSAC commands roll it out in closed
  loop (``metrics.wosac.simulate.simulate_rollouts``).
* ``rollouts``: a factory of a WOSAC rollout function ``(scenario, num_rollouts, seed) ->
  Rollouts`` for a policy that samples its rollouts its own way (TrafficBots keeps 32 of 128
  samples; the linear-extrapolation baseline is no step-by-step policy at all).

``register_policy("mine", factory)`` makes ``"mine"`` work in ``TrafficEnv``,
``BatchedTrafficEnv``, ``tbsim evaluate / export-wosac / view --policy`` and ``tbsim demo /
render --npc-policy``. Installed packages can add names without being imported first: an entry
point in the group ``tbsim.policies`` naming a callable that registers them.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from dataclasses import dataclass
from importlib.metadata import entry_points
from typing import Any

from tbsim_env.data.scenario import Scenario
from tbsim_env.metrics.wosac.rollouts import Rollouts
from tbsim_env.metrics.wosac.simulate import simulate_rollouts
from tbsim_env.sim.policy import Policy

RolloutFn = Callable[[Scenario, int, int], Rollouts]
"""``(scenario, num_rollouts, seed) -> Rollouts`` of every sim agent for the 80 WOSAC steps."""

ENTRY_POINT_GROUP = "tbsim.policies"


@dataclass(frozen=True)
class PolicyEntry:
    """What a policy name stands for (see the module docstring).

    Attributes:
        name: the registered name.
        agents: ``factory(**kwargs) -> Policy`` (None: it cannot drive agents step by step).
        rollouts: ``factory(checkpoint=None, device="cpu", **options) -> RolloutFn`` (None:
            closed-loop rollouts of ``agents``).
        summary: one line for ``--help`` and error messages.
    """

    name: str
    agents: Callable[..., Policy] | None
    rollouts: Callable[..., RolloutFn] | None
    summary: str


_REGISTRY: dict[str, PolicyEntry] = {}
_entry_points_loaded = False


def register_policy(
    name: str,
    agents: Callable[..., Policy] | None = None,
    *,
    rollouts: Callable[..., RolloutFn] | None = None,
    summary: str = "",
) -> None:
    """Add a policy name (see the module docstring).

    Raises:
        ValueError: the name is taken, or neither factory is given.
    """
    if name in _REGISTRY:
        raise ValueError(f"policy {name!r} is already registered")
    if agents is None and rollouts is None:
        raise ValueError(f"policy {name!r} needs an agents factory, a rollouts factory or both")
    _REGISTRY[name] = PolicyEntry(name, agents, rollouts, summary)


def _load_entry_points() -> None:
    global _entry_points_loaded
    if _entry_points_loaded:
        return
    _entry_points_loaded = True
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        ep.load()()


def policy_entry(name: str) -> PolicyEntry:
    """The entry of ``name``.

    Raises:
        ValueError: no such name (the message lists the known ones).
    """
    _load_entry_points()
    if name not in _REGISTRY:
        raise ValueError(f"unknown policy {name!r}; known: {', '.join(policy_names())}")
    return _REGISTRY[name]


def policy_names(agents: bool = False) -> tuple[str, ...]:
    """Every registered name, sorted (only those that drive agents with ``agents=True``)."""
    _load_entry_points()
    return tuple(sorted(n for n, e in _REGISTRY.items() if e.agents or not agents))


def make_policy(policy: str | Policy, **kwargs: Any) -> Policy:
    """A policy from its registered name (built with ``kwargs``), or the object itself.

    Raises:
        ValueError: unknown name, or a name that cannot drive agents.
        TypeError: an object that is not a ``Policy``.
    """
    if isinstance(policy, str):
        entry = policy_entry(policy)
        if entry.agents is None:
            drivers = ", ".join(policy_names(agents=True))
            raise ValueError(
                f"policy {policy!r} only makes WOSAC rollouts and cannot drive agents step by "
                f"step; policies that can: {drivers}"
            )
        return entry.agents(**kwargs)
    if not isinstance(policy, Policy):
        raise TypeError(
            f"{policy!r} is not a policy: it needs a 'name', 'initial_state' and 'act' "
            "(see tbsim_env.sim.policy.Policy)"
        )
    return policy


def make_rollout_fn(
    name: str, *, checkpoint: str | None = None, device: str = "cpu", **options: Any
) -> RolloutFn:
    """The WOSAC rollout function of a registered policy.

    Args:
        name: the policy name.
        checkpoint: weights to load (for the policies whose factories take one).
        device: torch device of the rollouts.
        options: further options of the policy's factory (e.g. TrafficBots'
            ``road_edge_weight``).

    Raises:
        ValueError: unknown name, or a checkpoint / option the policy does not take.
    """
    entry = policy_entry(name)
    if entry.rollouts is not None:
        _check_options(entry, entry.rollouts, {"checkpoint": checkpoint, **options})
        return entry.rollouts(checkpoint=checkpoint, device=device, **options)
    kwargs = {"checkpoint": checkpoint} if checkpoint else {}
    _check_options(entry, entry.agents, {**kwargs, **options})
    policy = entry.agents(**kwargs, **options)
    return lambda sc, n, seed: simulate_rollouts(
        sc, policy, num_rollouts=n, seed=seed, device=device
    )


def _check_options(entry: PolicyEntry, factory: Callable, given: dict[str, Any]) -> None:
    """Refuse options (not None) that ``factory`` does not take, naming the policy."""
    params = inspect.signature(factory).parameters
    if any(p.kind is p.VAR_KEYWORD for p in params.values()):
        return
    extra = [k for k, v in given.items() if v is not None and k not in params]
    if extra:
        users = [n for n in policy_names() if _takes(policy_entry(n), extra[0])]
        only = f" ({extra[0]} applies to {' / '.join(users)} only)" if users else ""
        raise ValueError(f"policy {entry.name!r} takes no {', '.join(extra)}{only}")


def _takes(entry: PolicyEntry, option: str) -> bool:
    factory = entry.rollouts or entry.agents
    return option in inspect.signature(factory).parameters


__all__ = [
    "ENTRY_POINT_GROUP",
    "PolicyEntry",
    "RolloutFn",
    "make_policy",
    "make_rollout_fn",
    "policy_entry",
    "policy_names",
    "register_policy",
]
