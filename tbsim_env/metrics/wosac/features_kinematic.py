"""Kinematic WOSAC features: linear/angular speed and acceleration (docs/metrics.md).

Central differences over the step axis (the last one), NaN-padded at both ends, so that speeds
are NaN at the first and last step and accelerations at the first two and last two steps.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from tbsim_env.core.constants import DT
from tbsim_env.sim.geometry import wrap_angle


def central_diff(values: torch.Tensor) -> torch.Tensor:
    """(v[t+1] - v[t-1]) / 2 along the last axis, NaN at the first and last step.

    Args:
        values: [..., T] float.

    Returns:
        [..., T] float, same dtype.
    """
    pad = torch.full_like(values[..., :1], float("nan"))
    return torch.cat([pad, (values[..., 2:] - values[..., :-2]) / 2.0, pad], dim=-1)


@dataclass(frozen=True)
class KinematicFeatures:
    """Per-step kinematic features, all [..., T] float.

    Attributes:
        linear_speed: m/s, unsigned 3-D speed.
        linear_acceleration: m/s^2, signed change of the speed.
        angular_speed: rad/s.
        angular_acceleration: rad/s^2.
    """

    linear_speed: torch.Tensor
    linear_acceleration: torch.Tensor
    angular_speed: torch.Tensor
    angular_acceleration: torch.Tensor


def linear_speed(x: torch.Tensor, y: torch.Tensor, z: torch.Tensor, dt: float = DT) -> torch.Tensor:
    """Central-difference speed ||p[t+1] - p[t-1]|| / (2 dt), [..., T] m/s (NaN at the ends)."""
    dpos = torch.stack([central_diff(x), central_diff(y), central_diff(z)], dim=-1)
    return torch.linalg.vector_norm(dpos, dim=-1) / dt


def kinematic_features(
    x: torch.Tensor,
    y: torch.Tensor,
    z: torch.Tensor,
    heading: torch.Tensor,
    dt: float = DT,
) -> KinematicFeatures:
    """Linear and angular speed and acceleration from a trajectory.

    The per-step heading change is delta[t] = wrap(h[t+1] - h[t-1]) / 2 (floor-mod wrap), the
    angular speed is delta / dt and the angular acceleration wrap(delta[t+1] - delta[t-1]) / 2
    / dt^2 (computed as wrap(2 * central_diff) / 2, which is the same).

    Args:
        x, y, z: [..., T] box centre in metres.
        heading: [..., T] yaw in radians, wrapped or not.
        dt: step in seconds.
    """
    speed = linear_speed(x, y, z, dt)
    accel = central_diff(speed) / dt
    dh_step = wrap_angle(central_diff(heading) * 2.0) / 2.0
    d2h_step = wrap_angle(central_diff(dh_step) * 2.0) / 2.0
    return KinematicFeatures(
        linear_speed=speed,
        linear_acceleration=accel,
        angular_speed=dh_step / dt,
        angular_acceleration=d2h_step / (dt * dt),
    )


def speed_validity(valid: torch.Tensor) -> torch.Tensor:
    """Scoring mask of speeds: V[k-1] and V[k+1], False at the first and last step.

    Args:
        valid: [..., T] bool logged validity of the scored steps.

    Returns:
        [..., T] bool.
    """
    pad = torch.zeros_like(valid[..., :1])
    return torch.cat([pad, valid[..., :-2] & valid[..., 2:], pad], dim=-1)


def acceleration_validity(valid: torch.Tensor) -> torch.Tensor:
    """Scoring mask of accelerations: speed_valid[k-1] and speed_valid[k+1]."""
    return speed_validity(speed_validity(valid))
