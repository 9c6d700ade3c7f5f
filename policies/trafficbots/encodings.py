"""Parameter-free encodings: sinusoidal pose encodings, relative poses, map-node geometry.

docs/model.md §2.3. ``PE_D(u)`` uses frequencies ``base^(-2k/D)``, k = 0..D/2-1, laid out as
[cos(w_0 u) .. cos(w_{D/2-1} u), sin(w_0 u) .. sin(w_{D/2-1} u)]; the angle encoding uses
integer harmonics 1..D/2 in the same cos/sin layout, so it is 2*pi periodic and the yaw never
needs wrapping.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from tbsim_env.sim.geometry import to_local

if TYPE_CHECKING:
    from policies.trafficbots.config import TrafficBotsConfig


def sinusoid_pe(u: torch.Tensor, dim: int, base: float) -> torch.Tensor:
    """Sinusoidal encoding of a scalar.

    Args:
        u: [...] values (metres).
        dim: output width D (even).
        base: frequency base (1000).

    Returns:
        [..., D].
    """
    k = torch.arange(dim // 2, device=u.device, dtype=u.dtype)
    freq = base ** (-2.0 * k / dim)
    arg = u[..., None] * freq
    return torch.cat([torch.cos(arg), torch.sin(arg)], dim=-1)


def angle_pe(phi: torch.Tensor, dim: int) -> torch.Tensor:
    """Integer-harmonic encoding of an angle: [cos(1 phi) .. cos(D/2 phi), sin(..)].

    Args:
        phi: [...] radians (any wrapping).
        dim: output width D (even).

    Returns:
        [..., D].
    """
    k = torch.arange(1, dim // 2 + 1, device=phi.device, dtype=phi.dtype)
    arg = phi[..., None] * k
    return torch.cat([torch.cos(arg), torch.sin(arg)], dim=-1)


def pose_encoding(pose: torch.Tensor, xy_dim: int, yaw_dim: int, base: float) -> torch.Tensor:
    """``[PE_xy(x), PE_xy(y), PEtheta_yaw(yaw)]``: the RPE (32/32/64) and agent input (16/16/32).

    Args:
        pose: [..., 3] (x m, y m, yaw rad), usually a relative pose.
        xy_dim: width of each position part.
        yaw_dim: width of the angle part.
        base: frequency base.

    Returns:
        [..., 2 * xy_dim + yaw_dim].
    """
    return torch.cat(
        [
            sinusoid_pe(pose[..., 0], xy_dim, base),
            sinusoid_pe(pose[..., 1], xy_dim, base),
            angle_pe(pose[..., 2], yaw_dim),
        ],
        dim=-1,
    )


def relative_pose(query: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Pose of ``target`` in the frame of ``query``: (R(q_yaw)^T (p_t - p_q), yaw_t - yaw_q).

    The yaw difference is not wrapped (docs/model.md §2.2): every consumer encodes it periodically.

    Args:
        query: [..., 3] (x, y, yaw), broadcastable against ``target``.
        target: [..., 3].

    Returns:
        [..., 3].
    """
    dxy = to_local(target[..., :2], query)
    return torch.cat([dxy, (target[..., 2] - query[..., 2])[..., None]], dim=-1)


def map_node_geometry(node_local: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """The 7-d node geometry of a map piece (``mpa_pl``, docs/model.md §2.3).

    With s the node position and u = (cos th', sin th') the unit direction, both in the piece
    frame, c the point of the segment s + t u (t in [0, 1]) closest to the origin and r = |c|:
    ``[r, c / r (2), u / |u| (2), |u|, |s + u - c|]``.

    Args:
        node_local: [..., 3] node pose in the piece frame (x, y, yaw).

    Returns:
        [..., 7].
    """
    s = node_local[..., :2]
    u = torch.stack([torch.cos(node_local[..., 2]), torch.sin(node_local[..., 2])], dim=-1)
    u_norm = torch.linalg.vector_norm(u, dim=-1, keepdim=True)
    t = (-(s * u).sum(-1, keepdim=True) / u_norm.square().clamp_min(eps)).clamp(0.0, 1.0)
    c = s + t * u
    r = torch.linalg.vector_norm(c, dim=-1, keepdim=True)
    c_dir = c / r.clamp_min(eps)
    far = torch.linalg.vector_norm(s + u - c, dim=-1, keepdim=True)
    return torch.cat([r, c_dir, u / u_norm.clamp_min(eps), u_norm, far], dim=-1)


def rpe(rel_pose: torch.Tensor, cfg: TrafficBotsConfig) -> torch.Tensor:
    """The shared relative pose encoding RPE(dx, dy, dyaw) of a config (paper 32/32/64).

    Args:
        rel_pose: [..., 3] relative pose.
        cfg: ``TrafficBotsConfig``.

    Returns:
        [..., cfg.rpe_dim].
    """
    return pose_encoding(rel_pose, cfg.rpe_xy_dim, cfg.rpe_yaw_dim, cfg.pe_base)
