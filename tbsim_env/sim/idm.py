"""The Intelligent Driver Model (Treiber, Hennecke & Helbing 2000), batched and pure.

The one implementation of the IDM acceleration in the simulation and policies: the ``idm``
NPC policy (``policies.idm``) and TrafficBots' gap-keeping rule
(``policies.trafficbots.rules.gap_keeping_cap``) both call it. With v the speed, v0 the desired
speed, s the bumper gap to the leader and dv = v - v_lead::

    a_idm = a (1 - (v / v0)^delta - (s* / s)^2),  s* = s0 + max(0, v T + v dv / (2 sqrt(a b)))

a: maximum acceleration, b: comfortable deceleration, T: time headway, s0: standstill gap.
A gap of +inf is free road (no interaction term). Every argument broadcasts (tensors of any
shape, or floats).
"""

from __future__ import annotations

from dataclasses import dataclass, fields

import torch

MIN_DESIRED_SPEED = 0.01
"""m/s; smaller desired speeds count as this one (the free-road term divides by it)."""


@dataclass(frozen=True)
class IDMTerms:
    """IDM parameters of a set of agents: tensors broadcastable to the agents' shape [...], or
    floats.

    Attributes:
        max_accel: a, m/s^2 (> 0).
        comfort_decel: b, m/s^2 (> 0).
        time_headway: T, s (>= 0).
        standstill_gap: s0, m (>= 0).
        exponent: delta of the free-road term (dimensionless, > 0).
    """

    max_accel: torch.Tensor | float
    comfort_decel: torch.Tensor | float
    time_headway: torch.Tensor | float
    standstill_gap: torch.Tensor | float
    exponent: torch.Tensor | float = 4.0


def terms_at(terms: IDMTerms, index: torch.Tensor) -> IDMTerms:
    """The terms of the agents ``index`` [K] int64: rows of its [L] tensors (floats as they
    are)."""
    values = (getattr(terms, f.name) for f in fields(IDMTerms))
    return IDMTerms(*(v.index_select(0, index) if torch.is_tensor(v) else v for v in values))


def desired_gap(speed: torch.Tensor, lead_speed: torch.Tensor, p: IDMTerms) -> torch.Tensor:
    """s* = s0 + max(0, v T + v (v - v_lead) / (2 sqrt(a b))), metres.

    Args:
        speed: [...] v, m/s (negative speeds count as 0).
        lead_speed: [...] the leader's speed along the follower's path, m/s.
        p: the follower's parameters.
    """
    v = speed.clamp_min(0.0)
    return p.standstill_gap + (v * p.time_headway + approach_gap(v, lead_speed, p)).clamp_min(0.0)


def approach_gap(speed: torch.Tensor, lead_speed: torch.Tensor, p: IDMTerms) -> torch.Tensor:
    """The dynamic part of the desired gap, v (v - v_lead) / (2 sqrt(a b)), metres (negative
    when the leader is faster).

    Args:
        speed: [...] v, m/s (>= 0).
        lead_speed: [...] the leader's speed along the follower's path, m/s.
        p: the follower's parameters.
    """
    return speed * (speed - lead_speed) / (2.0 * (p.max_accel * p.comfort_decel) ** 0.5)


def crowding(
    speed: torch.Tensor, gap: torch.Tensor, lead_speed: torch.Tensor, p: IDMTerms, min_gap: float
) -> torch.Tensor:
    """(s* / s)^2, the share of the maximum acceleration a leader takes away; 0 where the gap
    is +inf (nothing ahead). With several leaders the largest counts.

    Args:
        speed: [...] v, m/s.
        gap: [...] bumper gap s, m; smaller gaps (overlaps included) count as ``min_gap``.
        lead_speed: [...] the leader's speed along the follower's path, m/s.
        p: the follower's parameters.
        min_gap: m (> 0).
    """
    s = gap.clamp_min(min_gap)
    ratio = (desired_gap(speed, lead_speed, p) / s) ** 2
    return torch.where(torch.isfinite(gap), ratio, torch.zeros_like(ratio))


def interaction(
    speed: torch.Tensor, gap: torch.Tensor, lead_speed: torch.Tensor, p: IDMTerms, min_gap: float
) -> torch.Tensor:
    """The interaction term a (1 - (s* / s)^2) alone (the acceleration cap a leader imposes),
    m/s^2; +inf where the gap is +inf (nothing ahead). Arguments as ``crowding``."""
    cap = p.max_accel * (1.0 - crowding(speed, gap, lead_speed, p, min_gap))
    return torch.where(torch.isfinite(gap), cap, float("inf"))


def acceleration(
    speed: torch.Tensor, desired_speed: torch.Tensor, crowded: torch.Tensor, p: IDMTerms
) -> torch.Tensor:
    """The full IDM acceleration a (1 - (v / v0)^delta - (s* / s)^2), m/s^2.

    Args:
        speed: [...] v, m/s.
        desired_speed: [...] v0, m/s (at least ``MIN_DESIRED_SPEED``).
        crowded: [...] ``crowding`` of the most constraining leader (0: free road).
        p: parameters.
    """
    v0 = desired_speed.clamp_min(MIN_DESIRED_SPEED)
    free = 1.0 - (speed.clamp_min(0.0) / v0) ** p.exponent
    return p.max_accel * (free - crowded)


__all__ = [
    "MIN_DESIRED_SPEED",
    "IDMTerms",
    "acceleration",
    "approach_gap",
    "crowding",
    "desired_gap",
    "interaction",
]
