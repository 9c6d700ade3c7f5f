"""Corners of oriented boxes: the one rule that the simulator's collision and off-road checks,
the WOSAC features, the benchmark, the renderer and the scene generator all use.

A box is a centre (x, y) m, a heading yaw rad (counter-clockwise from +x), a length m along
the heading and a width m across it. Its corners run counter-clockwise from the front-left:
(+l/2, +w/2), (-l/2, +w/2), (-l/2, -w/2), (+l/2, -w/2) in the box frame.
"""

from __future__ import annotations

import numpy as np
import torch

from tbsim_env.core.torch_utils import const

_HALF_SIGNS_X = (0.5, -0.5, -0.5, 0.5)
_HALF_SIGNS_Y = (0.5, 0.5, -0.5, -0.5)


def cos_sin(angle: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """(cos, sin) of ``angle``.

    The input is made contiguous first: on CPU with several threads, torch's cos/sin of a
    strided view (e.g. ``pose[..., 2]``) can be ~1000x slower than of a contiguous tensor.
    """
    a = angle.contiguous()
    return torch.cos(a), torch.sin(a)


def corner_offsets(length: torch.Tensor, width: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Box corners in the box frame, counter-clockwise from front-left: (along [..., 4],
    across [..., 4]) m, from ``length`` and ``width`` [...]."""
    # (+-0.5 * length) is exactly +-(0.5 * length).
    return (
        length.unsqueeze(-1) * const(_HALF_SIGNS_X, length),
        width.unsqueeze(-1) * const(_HALF_SIGNS_Y, width),
    )


def corners_from_offsets(
    x0: torch.Tensor,
    y0: torch.Tensor,
    cos_sin_yaw: tuple[torch.Tensor, torch.Tensor],
    offsets: tuple[torch.Tensor, torch.Tensor],
) -> tuple[torch.Tensor, torch.Tensor]:
    """Corners (x [..., 4], y [..., 4]) of boxes at centres ``x0``, ``y0`` [..., 1] with heading
    (cos, sin) [..., 1], from their ``corner_offsets``."""
    c, s = cos_sin_yaw
    lx, ly = offsets
    return x0 + c * lx - s * ly, y0 + s * lx + c * ly


def box_corner_xy(
    pose: torch.Tensor, length: torch.Tensor, width: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """``box_corners`` as separate coordinates: (x [..., 4], y [..., 4])."""
    x0, y0, yaw = pose.unsqueeze(-2).unbind(-1)  # [..., 1]
    return corners_from_offsets(x0, y0, cos_sin(yaw), corner_offsets(length, width))


def box_corners(pose: torch.Tensor, length: torch.Tensor, width: torch.Tensor) -> torch.Tensor:
    """Corners of oriented boxes, counter-clockwise from front-left.

    Args:
        pose: [..., 3] (x m, y m, yaw rad) of the box centre.
        length: [...] m along the heading.
        width: [...] m across.

    Returns:
        [..., 4, 2] m.
    """
    return torch.stack(box_corner_xy(pose, length, width), dim=-1)


def box_corners_numpy(
    xy: np.ndarray, yaw: np.ndarray, length: np.ndarray, width: np.ndarray
) -> np.ndarray:
    """``box_corners`` of numpy boxes: centres ``xy`` [..., 2] m, ``yaw`` [...] rad, ``length``
    and ``width`` [...] m, in their common float dtype -> [..., 4, 2] m."""
    dtype = np.result_type(xy, yaw, length, width, np.float32)
    pose = np.concatenate([np.asarray(xy, dtype), np.asarray(yaw, dtype)[..., None]], -1)
    sizes = [torch.from_numpy(np.array(v, dtype)) for v in (length, width)]
    return box_corners(torch.from_numpy(pose), *sizes).numpy()
