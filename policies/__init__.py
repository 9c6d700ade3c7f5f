"""Policies that drive agents: log replay, constant velocity and TrafficBots V1.5."""

from __future__ import annotations

from collections.abc import Callable

from policies.base import Policy, PolicyState
from policies.constant_velocity import ConstantVelocityPolicy
from policies.log_replay import LogReplayPolicy

_REGISTRY: dict[str, Callable[..., Policy]] = {
    "log_replay": LogReplayPolicy,
    "constant_velocity": ConstantVelocityPolicy,
}


def register_policy(name: str, factory: Callable[..., Policy]) -> None:
    """Add a policy factory under ``name`` (raises if the name is taken)."""
    if name in _REGISTRY:
        raise ValueError(f"policy {name!r} is already registered")
    _REGISTRY[name] = factory


def policy_names() -> tuple[str, ...]:
    return tuple(sorted(_REGISTRY))


def make_policy(policy: str | Policy, **kwargs) -> Policy:
    """A policy from its registered name, or the object itself if it already is one."""
    if isinstance(policy, str):
        if policy not in _REGISTRY:
            raise ValueError(f"unknown policy {policy!r}; known: {', '.join(policy_names())}")
        return _REGISTRY[policy](**kwargs)
    if not isinstance(policy, Policy):
        raise TypeError(
            f"{policy!r} is not a policy: it needs a 'name', 'initial_state' and 'act' "
            "(see policies.base.Policy)"
        )
    return policy


__all__ = [
    "ConstantVelocityPolicy",
    "LogReplayPolicy",
    "Policy",
    "PolicyState",
    "make_policy",
    "policy_names",
    "register_policy",
]
