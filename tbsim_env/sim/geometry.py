"""Planar geometry helpers, batched and pure: angle wrapping, frame changes, point-segment
projection (the simulator's off-road test, the road-edge grid and TrafficBots' collision check
share it)."""

from __future__ import annotations

import math

import torch

from tbsim_env.core import constants as C
from tbsim_env.core.boxes import cos_sin  # noqa: F401  (re-exported)
from tbsim_env.core.torch_utils import const


def wrap_angle(angle: torch.Tensor) -> torch.Tensor:
    """Wrap radians to [-pi, pi)."""
    pi = const(math.pi, angle)
    return torch.remainder(angle + pi, const(2.0 * math.pi, angle)) - pi


def rotate(xy: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    """Rotate vectors by ``yaw`` (counter-clockwise).

    Args:
        xy: [..., 2].
        yaw: [...] radians, broadcastable to ``xy[..., 0]``.

    Returns:
        [..., 2].
    """
    c, s = cos_sin(yaw)
    x, y = xy.unbind(-1)
    return torch.stack([c * x - s * y, s * x + c * y], dim=-1)


def to_local_xy(
    x: torch.Tensor, y: torch.Tensor, origin: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``to_local`` on separate coordinates: (x, y) [...] and ``origin`` [..., 3]."""
    ox, oy, oyaw = origin.unbind(-1)
    c, s = cos_sin(-oyaw)
    dx, dy = x - ox, y - oy
    return c * dx - s * dy, s * dx + c * dy


def rotate_by(d: torch.Tensor, c: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """Vectors ``d`` [..., 2] rotated by the angle of (cos, sin) = (``c``, ``s``) [..., 1]:
    (c dx - s dy, s dx + c dy), bit for bit ``to_local_xy``'s arithmetic (with the origin's
    c = cos(-yaw), s = sin(-yaw)), as a few operations on the pair instead of one per
    coordinate: ``d * c`` plus the swapped ``d * s`` signed (-1, 1) (sums commute, and
    ``a + (-b)`` is ``a - b``)."""
    return d * c + d.flip(-1) * (s * const((-1.0, 1.0), s))


def to_local(xy: torch.Tensor, origin: torch.Tensor) -> torch.Tensor:
    """Express points in the frame of ``origin`` poses.

    Args:
        xy: [..., 2] points in the world frame.
        origin: [..., 3] (x, y, yaw) broadcastable to ``xy``.

    Returns:
        [..., 2] ``R(yaw)^T (xy - origin_xy)``.
    """
    x, y = xy.unbind(-1)
    return torch.stack(to_local_xy(x, y, origin), dim=-1)


def relative_pose(query: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Pose of ``target`` in the frame of ``query`` (dx, dy, dyaw), dyaw wrapped.

    Args:
        query: [..., 3] (x, y, yaw).
        target: [..., 3] (x, y, yaw), broadcastable against ``query``.

    Returns:
        [..., 3].

    From ``COMPONENT_POSES_MIN`` targets on (eagerly), a component at a time into the result
    (``to_local_xy``'s arithmetic, the same bits as ``rotate_by``'s).
    """
    many = target.numel() // 3 >= C.COMPONENT_POSES_MIN
    if many and not torch.compiler.is_compiling():
        shape = torch.broadcast_shapes(query.shape, target.shape)
        out = torch.empty(shape, dtype=target.dtype, device=target.device)
        x, y, yaw = target.unbind(-1)
        local = to_local_xy(x, y, query)
        out[..., 0], out[..., 1] = local
        out[..., 2] = wrap_angle(yaw - query[..., 2])
        return out
    yaw = query[..., 2:]
    c, s = cos_sin(-yaw)
    local = rotate_by(target[..., :2] - query[..., :2], c, s)
    return torch.cat([local, wrap_angle(target[..., 2:] - yaw)], -1)


def segment_projection(
    q: torch.Tensor, a: torch.Tensor, ab: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Projection of points on segments: (t, distance), broadcast over [..., 2] inputs.

    Args:
        q: [..., 2] points.
        a: [..., 2] segment starts.
        ab: [..., 2] segment vectors (end - start).

    Returns:
        (t [...]: the projection parameter along ab, not clamped, 0 for a zero-length
        segment; distance [...] m from q to the nearest point of the segment).
    """
    # The vector layout: a compiled graph's scan over every segment runs faster so than
    # with x and y apart (``segment_projection_xy``, the same values, faster eagerly).
    len2 = (ab * ab).sum(-1)
    t = ((q - a) * ab).sum(-1) / len2.clamp_min(1e-12)
    t = torch.where(len2 > 0, t, torch.zeros_like(t))
    offset = q - (a + t.clamp(0.0, 1.0).unsqueeze(-1) * ab)
    return t, torch.hypot(offset[..., 0], offset[..., 1])


def segment_projection_xy(
    qx: torch.Tensor,
    qy: torch.Tensor,
    ax: torch.Tensor,
    ay: torch.Tensor,
    bx: torch.Tensor,
    by: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``segment_projection`` of coordinates given apart (broadcast [...] tensors: point q,
    segment start a, segment vector b), with the same values (a sum of two products is their
    one addition; tested): no sums over a dim of 2, half the time of the vector layout
    eagerly on gathered candidates (``edge_grid``'s lookup), though slower compiled."""
    len2 = bx * bx + by * by
    t = ((qx - ax) * bx + (qy - ay) * by) / len2.clamp_min(1e-12)
    t = torch.where(len2 > 0, t, torch.zeros_like(t))
    inside = t.clamp(0.0, 1.0)
    return t, torch.hypot(qx - (ax + inside * bx), qy - (ay + inside * by))
