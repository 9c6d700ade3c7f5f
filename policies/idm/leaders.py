"""Leaders along the route (torch, per step): for every agent, the most constraining agent
whose box reaches into the corridor ahead of it, of any controller (external, learned,
log-replayed, IDM), crossing agents included.

The route ahead (``IDMConfig.horizon`` metres from the agent's progress) is cut into
``CHORDS`` straight pieces; the corridor is the agent's width plus ``lateral_margin`` on each
side of them. Agent j is in agent i's corridor when j's centre lies along a chord (0 to its
length) and j's box reaches within the corridor across it (its half extent across the chord,
from its length, width and heading, counts). The gap is the bumper gap along the route, the
leader's speed its velocity along the chord (0 for oncoming agents).

Cost: the pairs are first narrowed to the agents within a disc around the route's midpoint
ahead (which holds every point of the corridor), over each row's valid slots only; the chord
test then runs on the surviving pairs alone.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from policies.idm.params import CHORDS, IDMConfig
from policies.idm.tracking import points_at
from tbsim_env.sim.idm import IDMTerms, crowding
from tbsim_env.torch_utils import valid_order


@dataclass(frozen=True)
class Corridor:
    """The route ahead of each agent as ``CHORDS`` straight pieces.

    Attributes:
        origin: [B, N, M, 2] m, chord starts.
        direction: [B, N, M, 2] unit chord directions.
        length: [B, N, M] m.
        offset: [B, N, M] m, arc length from the agent's progress to each chord's start.
    """

    origin: torch.Tensor
    direction: torch.Tensor
    length: torch.Tensor
    offset: torch.Tensor


def corridor(route: torch.Tensor, progress: torch.Tensor, horizon: float) -> Corridor:
    """The chords of the next ``horizon`` metres of every route.

    Args:
        route: [B, N, P, 2] m; progress: [B, N] m; horizon: m.
    """
    steps = torch.linspace(0.0, horizon, CHORDS + 1, device=route.device)
    pts = points_at(route, progress.unsqueeze(-1) + steps)  # [B, N, M + 1, 2]
    vec = pts[..., 1:, :] - pts[..., :-1, :]
    length = torch.linalg.vector_norm(vec, dim=-1)
    direction = vec / length.clamp_min(1e-6).unsqueeze(-1)
    offset = steps[:-1].expand_as(length)
    return Corridor(pts[..., :-1, :], direction, length, offset)


def candidate_pairs(
    xy: torch.Tensor, valid: torch.Tensor, query: torch.Tensor, disc: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pairs (query agent i, valid agent j != i) with j's centre inside i's disc.

    Args:
        xy: [B, N, 2] m; valid: [B, N] bool; query: [B, N] bool (a subset of ``valid``).
        disc: [B, N, 3] (centre x, centre y, radius) m of each query agent.

    Returns:
        (row, i, j), three [Q] int64 tensors of batch rows and agent slots.
    """
    cols = valid_order(valid) if valid.device.type == "cpu" else None
    if cols is None:  # every slot (a GPU: no host sync for the counts)
        cols = torch.arange(valid.shape[1], device=valid.device).expand_as(valid)
    take = lambda x: x.gather(1, cols)  # noqa: E731  [B, C]
    x, y, ok, q = take(xy[..., 0]), take(xy[..., 1]), take(valid), take(query)
    cx, cy, r = (take(disc[..., k]) for k in range(3))
    dx = x.unsqueeze(1) - cx.unsqueeze(2)  # [B, C (i), C (j)]
    dy = y.unsqueeze(1) - cy.unsqueeze(2)
    near = (dx * dx + dy * dy) < (r * r).unsqueeze(2)
    near = near & ok.unsqueeze(1) & q.unsqueeze(2)
    near.diagonal(dim1=1, dim2=2).zero_()
    row, qi, cj = near.nonzero(as_tuple=True)
    return row, cols[row, qi], cols[row, cj]


@dataclass(frozen=True)
class Agents:
    """What the corridor test reads of every agent slot.

    Attributes:
        pose: [B, N, 3] (x m, y m, yaw rad).
        speed: [B, N] m/s.
        size: [B, N, 2] (length, width) m.
    """

    pose: torch.Tensor
    speed: torch.Tensor
    size: torch.Tensor


def pair_gaps(
    pairs: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    agents: Agents,
    lanes: Corridor,
    half_width: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Bumper gap along i's route to j, and j's speed along it, of every pair.

    Args:
        pairs: (row, i, j) [Q] each.
        agents: every slot's pose, speed and size.
        lanes: every slot's corridor.
        half_width: [B, N] m, half the corridor's width of each agent (half its width plus
            the margin).

    Returns:
        (gap [Q] m, +inf where j is not in i's corridor; lead speed [Q] m/s, >= 0).
    """
    row, i, j = pairs
    n = agents.speed.shape[1]
    fi, fj = row * n + i, row * n + j
    yaw = agents.pose[..., 2]
    own = torch.stack([agents.size[..., 0], half_width], -1).flatten(0, 1)[fi]  # [Q, 2]
    cols = [*agents.pose[..., :2].unbind(-1), yaw.cos(), yaw.sin(), agents.speed]
    other = torch.stack([*cols, *agents.size.unbind(-1)], -1).flatten(0, 1)[fj]  # [Q, 7]
    chords = torch.cat(
        [lanes.origin, lanes.direction, lanes.length.unsqueeze(-1), lanes.offset.unsqueeze(-1)], -1
    ).flatten(0, 1)[fi]  # [Q, M, 6]
    ox, oy, ux, uy, length, offset = chords.unbind(-1)
    xj, yj, cj, sj, vj, lj, wj = (c.unsqueeze(-1) for c in other.unbind(-1))
    dx, dy = xj - ox, yj - oy
    along, across = dx * ux + dy * uy, dy * ux - dx * uy
    cos_rel, sin_rel = (cj * ux + sj * uy), (sj * ux - cj * uy)
    half_along = 0.5 * (lj * cos_rel.abs() + wj * sin_rel.abs())
    half_across = 0.5 * (lj * sin_rel.abs() + wj * cos_rel.abs())
    inside = (along >= 0) & (along < length) & (across.abs() < own[:, 1:2] + half_across)
    gap = offset + along - half_along - 0.5 * own[:, 0:1]
    gap = torch.where(inside, gap, float("inf"))
    best, m = gap.min(-1)
    lead = (vj[:, 0] * cos_rel.gather(-1, m.unsqueeze(-1))[:, 0]).clamp_min(0.0)
    return best, lead


def leader_crowding(
    agents: Agents,
    lanes: Corridor,
    query: tuple[torch.Tensor, torch.Tensor],
    terms: IDMTerms,
    cfg: IDMConfig,
) -> torch.Tensor:
    """The IDM ``crowding`` (s* / s)^2 of every agent's most constraining leader (0: none).

    Args:
        agents: every slot's pose, speed and size (valid or not).
        lanes: every slot's corridor (``corridor`` over ``cfg.horizon``).
        query: (valid [B, N] bool: agents that can lead; asks [B, N] bool: agents that look
            for leaders, a subset).
        terms: IDM parameters, [B, N] tensors (or floats).
        cfg: the corridor's margin, the horizon and the smallest gap.

    Returns:
        [B, N] >= 0.
    """
    valid, asks = query
    b, n = valid.shape
    size = agents.size
    reach = 0.5 * torch.linalg.vector_norm(size, dim=-1)  # half diagonal of each box
    far = (reach * valid).amax(1, keepdim=True)  # the largest box of each row
    half_width = 0.5 * size[..., 1] + cfg.lateral_margin
    # Every corridor point lies within horizon / 2 of the route point horizon / 2 ahead.
    radius = 0.5 * cfg.horizon + half_width + far + 1.0
    disc = torch.cat([lanes.origin[..., CHORDS // 2, :], radius.unsqueeze(-1)], -1)
    pairs = candidate_pairs(agents.pose[..., :2], valid, asks, disc)
    gap, lead = pair_gaps(pairs, agents, lanes, half_width)
    row, i, _ = pairs
    fi = row * n + i
    pick = lambda x: x.flatten()[fi] if isinstance(x, torch.Tensor) else x  # noqa: E731
    pair_terms = IDMTerms(*(pick(getattr(terms, f)) for f in _TERM_FIELDS))
    ratio = crowding(pick(agents.speed), gap, lead, pair_terms, cfg.min_gap)
    out = torch.zeros(b * n, dtype=agents.speed.dtype, device=agents.speed.device)
    return out.scatter_reduce(0, fi, ratio, "amax").view(b, n)


_TERM_FIELDS = ("max_accel", "comfort_decel", "time_headway", "standstill_gap", "exponent")


__all__ = ["Agents", "Corridor", "candidate_pairs", "corridor", "leader_crowding", "pair_gaps"]
