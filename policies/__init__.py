"""Policies that drive agents: log replay, constant velocity, rule-based IDM traffic and
TrafficBots V1.5, and the one registry of policy names (``policies.registry``) that every part
of tbsim reads."""

from __future__ import annotations

from policies.constant_velocity import ConstantVelocityPolicy
from policies.idm import IDMPolicy
from policies.log_replay import LogReplayPolicy
from policies.registry import (
    PolicyEntry,
    make_policy,
    make_rollout_fn,
    policy_entry,
    policy_names,
    register_policy,
)
from tbsim_env.metrics.wosac.simulate import linear_extrapolation_rollouts
from tbsim_env.sim.policy import Policy, PolicyState


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


def _trafficbots_rollouts(
    checkpoint: str | None = None,
    device: str = "cpu",
    num_samples: int = 128,
    road_edge_weight: float | None = None,
):
    """TrafficBots' WOSAC sampling: ``num_samples`` rollouts, the 32 least colliding kept."""
    from policies.trafficbots.wosac import trafficbots_rollout_fn

    return trafficbots_rollout_fn(
        checkpoint=checkpoint,
        device=device,
        num_samples=num_samples,
        road_edge_weight=road_edge_weight,
    )


def _idm(route: str = "log", **settings) -> Policy:
    """Rule-based IDM traffic (``policies.idm``); ``settings`` are ``IDMConfig`` fields."""
    return IDMPolicy(route=route, **settings)


def _idm_lanes(**settings) -> Policy:
    """``idm`` with ``route="lanes"``."""
    return IDMPolicy(route="lanes", **settings)


def _linear_extrapolation_rollouts(checkpoint: None = None, device: str = "cpu"):
    """The official WOSAC tutorial baseline (no step-by-step policy)."""
    del checkpoint, device  # nothing to load, numpy on the CPU
    return lambda sc, n, seed: linear_extrapolation_rollouts(sc, num_rollouts=n, seed=seed)


register_policy("log_replay", LogReplayPolicy, summary="the logged trajectories, exactly")
register_policy(
    "constant_velocity", ConstantVelocityPolicy, summary="keep speed and heading (baseline)"
)
register_policy(
    "idm",
    _idm,
    summary="rule-based reactive traffic: IDM along the logged path, signals, stop signs",
)
register_policy(
    "idm_lanes",
    _idm_lanes,
    summary="idm on lane-graph routes (forks follow the logged future where there is one)",
)
register_policy(
    "linear_extrapolation",
    rollouts=_linear_extrapolation_rollouts,
    summary="WOSAC tutorial baseline: last displacement plus noise (WOSAC rollouts only)",
)
register_policy(
    "trafficbots",
    _trafficbots,
    rollouts=_trafficbots_rollouts,
    summary="the shipped TrafficBots V1.5 (docs/MODEL_CARD.md)",
)

__all__ = [
    "ConstantVelocityPolicy",
    "IDMPolicy",
    "LogReplayPolicy",
    "Policy",
    "PolicyEntry",
    "PolicyState",
    "make_policy",
    "make_rollout_fn",
    "policy_entry",
    "policy_names",
    "register_policy",
]
