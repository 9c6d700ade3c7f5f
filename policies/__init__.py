"""Policies that drive agents: log replay, constant velocity and TrafficBots V1.5."""

from __future__ import annotations

from collections.abc import Callable

from policies.base import Policy, PolicyState
from policies.constant_velocity import ConstantVelocityPolicy
from policies.log_replay import LogReplayPolicy


def _trafficbots(checkpoint: str | None = None, device: str = "cpu", **kwargs) -> Policy:
    """TrafficBots V1.5 from a checkpoint, or the shipped weights when none is given."""
    from policies.trafficbots.checkpoint import load_checkpoint
    from policies.trafficbots.policy import TrafficBotsPolicy
    from policies.trafficbots.wosac import load_default_model

    model = (
        load_checkpoint(checkpoint, map_location=device)
        if checkpoint
        else load_default_model(device)
    )
    return TrafficBotsPolicy(model, **kwargs)


_REGISTRY: dict[str, Callable[..., Policy]] = {
    "log_replay": LogReplayPolicy,
    "constant_velocity": ConstantVelocityPolicy,
    "trafficbots": _trafficbots,
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
