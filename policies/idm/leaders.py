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

from policies.idm.params import CHORDS, CROSSING_SIN, GHOST_TIMES, YIELD_SLACK, IDMConfig
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
    xy: torch.Tensor,
    valid: torch.Tensor,
    query: torch.Tensor,
    disc: torch.Tensor,
    reach: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pairs (query agent i, valid agent j != i) with j's centre within i's disc widened by
    j's reach.

    Args:
        xy: [B, N, 2] m; valid: [B, N] bool; query: [B, N] bool (a subset of ``valid``).
        disc: [B, N, 3] (centre x, centre y, radius) m of each query agent.
        reach: [B, N] m, how far each agent's tested boxes lie from its centre.

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
    r = r.unsqueeze(2) + take(reach).unsqueeze(1)
    near = (dx * dx + dy * dy) < r * r
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
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Bumper gap along i's route to j and j's speed along it, and the gap to where j will
    cross i's route, of every pair.

    Besides j's box now, its boxes ``GHOST_TIMES`` ahead (constant velocity) are tested when
    j crosses i's route (more than ``CROSSING_ANGLE`` off the route's direction): such a box
    in the corridor is a standing obstacle for i unless i would be past it well before j
    (``YIELD_SLACK``), so that i yields to crossing traffic instead of meeting it.

    Args:
        pairs: (row, i, j) [Q] each.
        agents: every slot's pose, speed and size.
        lanes: every slot's corridor.
        half_width: [B, N] m, half the corridor's width of each agent (half its width plus
            the margin).

    Returns:
        (gap [Q] m, +inf where j is not in i's corridor; lead speed [Q] m/s, >= 0; gap [Q] m
        to j's crossing, +inf where none is yielded to).
    """
    row, i, j = pairs
    n = agents.speed.shape[1]
    fi, fj = row * n + i, row * n + j
    yaw = agents.pose[..., 2]
    own = torch.stack([agents.size[..., 0], half_width, agents.speed], -1)
    own = own.flatten(0, 1)[fi].unsqueeze(-1)  # [Q, 3, 1]
    cols = [*agents.pose[..., :2].unbind(-1), yaw.cos(), yaw.sin(), agents.speed]
    other = torch.stack([*cols, *agents.size.unbind(-1)], -1).flatten(0, 1)[fj]  # [Q, 7]
    chords = torch.cat(
        [lanes.origin, lanes.direction, lanes.length.unsqueeze(-1), lanes.offset.unsqueeze(-1)], -1
    ).flatten(0, 1)[fi]  # [Q, M, 6]
    ox, oy, ux, uy, length, offset = (c.unsqueeze(1) for c in chords.unbind(-1))  # [Q, 1, M]
    xj, yj, cj, sj, vj, lj, wj = (c.view(-1, 1, 1) for c in other.unbind(-1))
    tau = torch.tensor((0.0, *GHOST_TIMES), device=xj.device).view(1, -1, 1)  # [1, G, 1]
    dx = xj + (vj * cj) * tau - ox  # [Q, G, M]
    dy = yj + (vj * sj) * tau - oy
    along, across = dx * ux + dy * uy, dy * ux - dx * uy
    cos_rel, sin_rel = (cj * ux + sj * uy), (sj * ux - cj * uy)  # [Q, 1, M]
    half_along = 0.5 * (lj * cos_rel.abs() + wj * sin_rel.abs())
    half_across = 0.5 * (lj * sin_rel.abs() + wj * cos_rel.abs())
    inside = (along >= 0) & (along < length) & (across.abs() < own[:, 1:2] + half_across)
    gap = torch.where(inside, offset + along - half_along - 0.5 * own[:, 0:1], float("inf"))
    now, m = gap[:, 0].min(-1)
    lead = (vj[:, 0, 0] * cos_rel[:, 0].gather(-1, m.unsqueeze(-1))[:, 0]).clamp_min(0.0)
    crossing = sin_rel.abs() > CROSSING_SIN
    late = gap[:, 1:] >= own[:, 2:3].clamp_min(1.0) * (tau[:, 1:] - YIELD_SLACK)
    ghost = torch.where(crossing & late, gap[:, 1:], float("inf")).flatten(1).amin(-1)
    return now, lead, ghost


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
    # Every corridor point lies within horizon / 2 of the route point horizon / 2 ahead, and
    # j's boxes ahead in time within its speed times the last ghost time of j's centre.
    radius = 0.5 * cfg.horizon + half_width + far + 1.0
    disc = torch.cat([lanes.origin[..., CHORDS // 2, :], radius.unsqueeze(-1)], -1)
    reach = agents.speed.abs() * GHOST_TIMES[-1]
    pairs = candidate_pairs(agents.pose[..., :2], valid, asks, disc, reach)
    gap, lead, ghost = pair_gaps(pairs, agents, lanes, half_width)
    row, i, _ = pairs
    fi = row * n + i
    pick = lambda x: x.flatten()[fi] if isinstance(x, torch.Tensor) else x  # noqa: E731
    pair_terms = IDMTerms(*(pick(getattr(terms, f)) for f in _TERM_FIELDS))
    v = pick(agents.speed)
    ratio = crowding(v, gap, lead, pair_terms, cfg.min_gap)
    ratio = torch.maximum(ratio, crowding(v, ghost, torch.zeros_like(v), pair_terms, cfg.min_gap))
    out = torch.zeros(b * n, dtype=agents.speed.dtype, device=agents.speed.device)
    return out.scatter_reduce(0, fi, ratio, "amax").view(b, n)


_TERM_FIELDS = ("max_accel", "comfort_decel", "time_headway", "standstill_gap", "exponent")


__all__ = ["Agents", "Corridor", "candidate_pairs", "corridor", "leader_crowding", "pair_gaps"]
