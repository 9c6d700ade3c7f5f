"""Planar geometry helpers, batched and pure: angle wrapping and frame changes."""

from __future__ import annotations

import math

import torch


def cos_sin(angle: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(cos, sin) of ``angle``.

    The input is made contiguous first: on CPU with several threads, torch's cos/sin of a
    strided view (e.g. ``pose[..., 2]``) can be ~1000x slower than of a contiguous tensor.
    """
    a = angle.contiguous()
    return torch.cos(a), torch.sin(a)


def wrap_angle(angle: torch.Tensor) -> torch.Tensor:
    """Wrap radians to [-pi, pi)."""
    return torch.remainder(angle + math.pi, 2.0 * math.pi) - math.pi


def rotate(xy: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    """Rotate vectors by ``yaw`` (counter-clockwise).

    Args:
        xy: [..., 2].
        yaw: [...] radians, broadcastable to ``xy[..., 0]``.

    Returns:
        [..., 2].
    """
    c, s = cos_sin(yaw)
    x, y = xy[..., 0], xy[..., 1]
    return torch.stack([c * x - s * y, s * x + c * y], dim=-1)


def to_local(xy: torch.Tensor, origin: torch.Tensor) -> torch.Tensor:
    """Express points in the frame of ``origin`` poses.

    Args:
        xy: [..., 2] points in the world frame.
        origin: [..., 3] (x, y, yaw) broadcastable to ``xy``.

    Returns:
        [..., 2] ``R(yaw)^T (xy - origin_xy)``.
    """
    return rotate(xy - origin[..., :2], -origin[..., 2])


def relative_pose(query: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Pose of ``target`` in the frame of ``query`` (dx, dy, dyaw), dyaw wrapped.

    Args:
        query: [..., 3] (x, y, yaw).
        target: [..., 3] (x, y, yaw), broadcastable against ``query``.

    Returns:
        [..., 3].
    """
    dxy = to_local(target[..., :2], query)
    dyaw = wrap_angle(target[..., 2] - query[..., 2])
    return torch.cat([dxy, dyaw[..., None]], dim=-1)
