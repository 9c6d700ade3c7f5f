"""Leaders along the route (torch, per step): for every agent, the most constraining agent
whose box reaches into the corridor ahead of it, of any controller (external, learned,
log-replayed, IDM), crossing agents included.

The route ahead (``IDMConfig.horizon`` metres from the agent's progress) is cut into
``CHORDS`` straight pieces; the corridor is the agent's width plus ``lateral_margin`` on each
side of them. Agent j is in agent i's corridor when j's centre lies along a chord (0 to its
length) and j's box reaches within the corridor across it (its half extent across the chord,
from its length, width and heading, counts). The gap is the bumper gap along the route, the
leader's speed its velocity along the chord (0 for oncoming agents).

Cost: the pairs are first narrowed to the agents whose path's disc (around the midpoint of
their path over the crossing horizon) meets a disc around the route's midpoint ahead (which
holds every point of the corridor), over each row's valid slots only; the chord test then runs
on the surviving pairs alone, on the chords of the corridor's quarters their path comes near.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import torch

from policies.idm.params import (
    CHORDS,
    CROSSING_HORIZON,
    CROSSING_SIN,
    DISC_SLACK,
    FAR_AWAY,
    MOVING_SPEED,
    YIELD_SLACK,
    IDMConfig,
)
from policies.idm.tracking import points_at
from tbsim_env.core.torch_utils import below_zero, true_index, valid_order
from tbsim_env.sim.idm import IDMTerms, crowding, terms_at


@dataclass(frozen=True)
class Corridor:
    """The route ahead of each of L agents as ``CHORDS`` straight pieces.

    Attributes:
        origin: [L, M, 2] m, chord starts.
        direction: [L, M, 2] unit chord directions.
        length: [L, M] m.
        offset: [L, M] m, arc length from the agent's progress to each chord's start.
    """

    origin: torch.Tensor
    direction: torch.Tensor
    length: torch.Tensor
    offset: torch.Tensor


def corridor(
    route: torch.Tensor, agent: torch.Tensor, progress: torch.Tensor, horizon: torch.Tensor
) -> Corridor:
    """The chords of the next ``horizon`` metres of the agents' routes.

    Args:
        route: [B, N, P, 2] m; agent: [L] int64 flat slot indices; progress: [L] m;
        horizon: [L] m.
    """
    steps = horizon.unsqueeze(-1) * torch.linspace(0.0, 1.0, CHORDS + 1, device=route.device)
    pts = points_at(route, agent, progress.unsqueeze(-1) + steps)  # [L, M + 1, 2]
    vec = pts[:, 1:] - pts[:, :-1]
    length = torch.hypot(vec[..., 0], vec[..., 1])
    direction = vec / length.clamp_min(1e-6).unsqueeze(-1)
    return Corridor(pts[:, :-1], direction, length, steps[:, :-1])


def candidate_pairs(
    xy: torch.Tensor,
    valid: torch.Tensor,
    query: torch.Tensor,
    disc: torch.Tensor,
    reach: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pairs (query agent i, valid agent j != i) with j's centre within i's disc widened by
    j's reach (and up to ``DISC_SLACK`` more: a superset for the exact tests that follow).

    Args:
        xy: [B, N, 2] m; valid: [B, N] bool; query: [B, N] bool (a subset of ``valid``).
        disc: [B, N, 3] (centre x, centre y, radius) m of each query agent.
        reach: [B, N] m, how far each agent's tested boxes lie from its centre.

    Returns:
        (row, i, j), three [Q] int64 tensors of batch rows and agent slots.
    """
    if valid.device.type == "cpu":  # each row's valid (asking) slots first
        cols, asks = valid_order(valid), valid_order(query)
    else:  # every slot (a GPU: no host sync for the counts)
        cols = torch.arange(valid.shape[1], device=valid.device).expand_as(valid)
        asks = cols
    take = lambda x, c: x.gather(1, c)  # noqa: E731  [B, C]
    # Invalid columns sit at +inf (never near); a row that does not ask has no radius.
    far = torch.full_like(xy[..., 0], float("inf"))
    x, y = (take(torch.where(valid, v, far), cols) for v in (xy[..., 0], xy[..., 1]))
    reach = take(reach, cols)
    cx, cy, r = (take(disc[..., k], asks) for k in range(3))
    r = torch.where(take(query, asks), r, float("-inf"))
    near = _near_discs((x, y, reach), (cx, cy, r))  # [B, Ci, Cj]
    ci, cj = near.shape[1:]
    f = true_index(near)
    ask = f // cj  # row * Ci + i's column
    row = ask // ci
    i = asks.reshape(-1).index_select(0, ask)
    j = cols.reshape(-1).index_select(0, row * cj + (f - ask * cj))
    keep = true_index(i != j)
    return row.index_select(0, keep), i.index_select(0, keep), j.index_select(0, keep)


def _near_discs(
    columns: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    discs: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
) -> torch.Tensor:
    """[B, Ci, Cj] bool: column j's centre lies within disc i widened by j's reach, and by
    ``DISC_SLACK`` for the rounding of the product form below.

    |c_i - p_j|^2 - (r_i + reach_j)^2 = (|c_i|^2 - r_i^2) + (|p_j|^2 - reach_j^2)
    - 2 (c_i . p_j + r_i reach_j): one batched product of [B, Ci, 5] and [B, 5, Cj] (the two
    squared terms ride along as a column of ones on either side) instead of eight elementwise
    passes over [B, Ci, Cj] (the dense test is bound by memory bandwidth). Coordinates are
    taken from a per-row origin (the mean of its asking discs' centres), so that the squares
    stay small.

    Args:
        columns: (x, y, reach) [B, Cj] m; invalid columns at x = y = +inf.
        discs: (centre x, centre y, radius) [B, Ci] m; a radius of -inf asks for nothing.
    """
    x, y, reach = columns
    cx, cy, r = discs
    asks = torch.isfinite(r)
    count = asks.sum(1, keepdim=True).clamp_min(1)  # [B, 1]
    ox = torch.where(asks, cx, 0.0).sum(1, keepdim=True) / count
    oy = torch.where(asks, cy, 0.0).sum(1, keepdim=True) / count
    xj = torch.where(torch.isfinite(x), x - ox, FAR_AWAY)
    yj = torch.where(torch.isfinite(y), y - oy, FAR_AWAY)
    ri = torch.where(asks, r + DISC_SLACK, 0.0)
    xi, yi = cx - ox, cy - oy
    own = torch.where(asks, xi * xi + yi * yi - ri * ri, FAR_AWAY * FAR_AWAY)  # [B, Ci]
    other = xj * xj + yj * yj - reach * reach  # [B, Cj]
    one_i, one_j = torch.ones_like(own), torch.ones_like(other)
    u = torch.stack([xi, yi, ri, own, one_i], -1)  # [B, Ci, 5]
    v = torch.stack([-2.0 * xj, -2.0 * yj, -2.0 * reach, one_j, other], 1)  # [B, 5, Cj]
    return below_zero(torch.bmm(u, v))


@dataclass(frozen=True)
class Agents:
    """What the corridor test reads of every agent slot.

    Attributes:
        pose: [B, N, 3] (x m, y m, yaw rad).
        speed: [B, N] m/s.
        size: [B, N, 2] (length, width) m.
        pedestrian: [B, N] bool, or None: no pair is left out for its types
            (``IDMConfig.pedestrian_gaps``: pedestrian pairs are).
    """

    pose: torch.Tensor
    speed: torch.Tensor
    size: torch.Tensor
    pedestrian: torch.Tensor | None = None


def slot_table(agents: Agents) -> torch.Tensor:
    """[7, B N] (x, y, cos yaw, sin yaw, speed, length, width) of every slot, a row each.

    The per-pair tests lay pairs along the last, contiguous dimension ([7, Q], [M / 2, Q],
    [C, E]): ATen's elementwise loops broadcast a pair's value over a leading dimension at
    full vector width, and over a trailing one of 2 or 4 several times slower."""
    yaw = agents.pose[..., 2]
    cols = [*agents.pose[..., :2].unbind(-1), yaw.cos(), yaw.sin(), agents.speed]
    return torch.stack([*cols, *agents.size.unbind(-1)], 0).view(7, -1)


def _quarter_discs(lanes: Corridor, half_width: torch.Tensor, li: torch.Tensor) -> torch.Tensor:
    """[3, M / 2, Q] (centre x, y, radius) m of discs that hold the corridor's quarters of
    the followers ``li`` [Q]: chords 2k and 2k + 1 lie within the longer one's length of the
    start of chord 2k + 1, the corridor within its half width ``half_width`` [L] m more."""
    longer = torch.maximum(lanes.length[:, 0::2], lanes.length[:, 1::2])
    radius = longer + half_width.unsqueeze(-1)
    table = torch.stack([*lanes.origin[:, 1::2].unbind(-1), radius], 0)  # [3, L, M / 2]
    quarters = table.shape[-1]
    return table.transpose(1, 2).reshape(3 * quarters, -1).index_select(1, li).view(3, quarters, -1)


def _chord_table(lanes: Corridor) -> torch.Tensor:
    """[12, L M / 2]: the two chords of each corridor quarter (quarter k of follower l at
    column l M / 2 + k), row 2c + h the chord component c (origin x, y, direction x, y,
    length, offset) of its chord h."""
    columns = (*lanes.origin.unbind(-1), *lanes.direction.unbind(-1), lanes.length, lanes.offset)
    table = torch.stack(columns, 0)  # [6, L, M]
    n, m = table.shape[1:]
    return table.view(6, n * m // 2, 2).transpose(1, 2).reshape(12, -1)


def _near_quarters(discs: torch.Tensor, other: torch.Tensor) -> torch.Tensor:
    """[M / 2, Q] bool: j's path over the crossing horizon (constant velocity, backwards for
    a negative speed) comes within the disc around a quarter of i's corridor
    (``_quarter_discs``) widened by j's half diagonal: only then can j's box, now or on that
    path, be in that quarter's chords.

    Args:
        discs: [3, M / 2, Q] i's quarter discs (centre x, y, radius) m.
        other: [7, Q] j (columns of ``slot_table``).
    """
    cx, cy, radius = discs.unbind(0)  # [M / 2, Q]
    xj, yj, cj, sj, vj, lj, wj = other.unbind(0)  # [Q]
    travel = vj * CROSSING_HORIZON  # j's centre moves along (cj, sj) by this
    rx, ry = cx - xj, cy - yj
    t = (rx * cj + ry * sj).clamp(min=travel.clamp_max(0.0), max=travel.clamp_min(0.0))
    dx, dy = rx - t * cj, ry - t * sj
    reach = radius + 0.5 * torch.sqrt(lj * lj + wj * wj)
    return dx * dx + dy * dy < reach * reach


def _chord_gaps(
    chords: torch.Tensor, other: torch.Tensor, mine: torch.Tensor, horizon: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The corridor test of j's box now, and of the first time within ``horizon`` s that
    j's box, moving at constant velocity across i's route, enters i's corridor (see
    ``pair_gaps``).

    Args:
        chords: [6, C, E] the chords of i tested (origin x, y, direction x, y, length,
            offset).
        other: [7, E] j (columns of ``slot_table``).
        mine: [3, E] i's (length, half corridor width, speed).
        horizon: [E] s ahead j's path is tested (0: its box now only).

    Returns:
        (gap now [E] m, lead speed [E] m/s, gap to the crossing yielded to [E] m), the
        nearest over the C chords.
    """
    ox, oy, ux, uy, length, offset = chords.unbind(0)  # [C, E]
    xj, yj, cj, sj, vj, lj, wj = other.unbind(0)  # [E]
    half_len_i, half_width_i, speed_i = mine[0] * 0.5, mine[1], mine[2]
    dx, dy = xj - ox, yj - oy
    along, across = dx * ux + dy * uy, dy * ux - dx * uy
    cos_rel, sin_rel = cj * ux + sj * uy, sj * ux - cj * uy
    half_along = 0.5 * (lj * cos_rel.abs() + wj * sin_rel.abs())
    reach = half_width_i + 0.5 * (lj * sin_rel.abs() + wj * cos_rel.abs())
    inside = (along >= 0) & (along < length) & (across.abs() < reach)
    gap = torch.where(inside, offset + along - half_along - half_len_i, float("inf"))
    now, m = gap.min(0)
    lead = (vj * cos_rel.gather(0, m.unsqueeze(0))[0]).clamp_min(0.0)
    # The time j's box starts to overlap the corridor across: |across + rate t| < reach.
    rate = vj * sin_rel
    crossing = sin_rel.abs() > CROSSING_SIN
    safe = torch.where(crossing, rate, torch.ones_like(rate))
    t_in = torch.minimum((-reach - across) / safe, (reach - across) / safe)
    along_in = along + vj * cos_rel * t_in
    gap_in = offset + along_in - half_along - half_len_i
    enters = crossing & (t_in > 0) & (t_in <= horizon) & (along_in >= 0) & (along_in < length)
    # i goes first only if it clears the crossing (its gap, j's extent along the route and
    # its own length) well before j's box arrives; else it yields.
    clear = gap_in + 2.0 * (half_along + half_len_i)
    late = clear >= speed_i.clamp_min(1.0) * (t_in - YIELD_SLACK)
    ghost = torch.where(enters & late, gap_in, float("inf")).amin(0)
    return now, lead, ghost


def pair_gaps(
    pairs: tuple[torch.Tensor, torch.Tensor],
    slots: torch.Tensor,
    lanes: Corridor,
    own: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Bumper gap along i's route to j and j's speed along it, and the gap to where j will
    cross i's route, of the pairs whose j comes near i's corridor.

    Besides j's box now, when j moves and crosses i's route (more than 30 deg off the
    route's direction, ``CROSSING_SIN``) its path over the next ``CROSSING_HORIZON`` s
    (constant velocity) is tested: where its box first enters the corridor is a standing
    obstacle for i unless i would be past it well before j (``YIELD_SLACK``), so that i
    yields to crossing traffic instead of meeting it. Pairs whose j comes nowhere near the
    corridor are left out first, and of the others only the chords of the corridor's
    quarters that j's path comes near are tested (``_near_quarters``; j cannot be in the
    others): the same gaps as testing all ``CHORDS``, on about a third of the work.

    Args:
        pairs: (i [Q] row of the L agents, j [Q] flat slot index b * N + n).
        slots: [7, B N] every slot's pose, speed and size (``slot_table``).
        lanes: the L agents' corridors.
        own: [3, L] (length m, half the corridor's width m, speed m/s) of the L agents.

    Returns:
        (near [K] int64: the pairs tested, indices into the Q pairs; gap [K] m, +inf where j
        is not in i's corridor; lead speed [K] m/s, >= 0; gap [K] m to j's crossing, +inf
        where none is yielded to).
    """
    li, fj = pairs
    other = slots.index_select(1, fj)  # [7, Q]
    half = CHORDS // 2
    quarters = _near_quarters(_quarter_discs(lanes, own[1], li), other)  # [M / 2, Q]
    near = functools.reduce(torch.bitwise_or, quarters.unbind(0))  # ATen's any(0): ~20x slower
    k = true_index(near)
    # One entry per (quarter, pair) j comes near: only those chords are tested.
    entry = true_index(quarters)
    quarter, q = entry // li.shape[0], entry % li.shape[0]
    lq = li.index_select(0, q)
    chords = _chord_table(lanes).index_select(1, lq * half + quarter).view(6, 2, -1)
    mine, near_j = own.index_select(1, lq), other.index_select(1, q)
    # Standing agents' paths are not tested ahead in time: a horizon of 0 s.
    moving = near_j[4].abs() > MOVING_SPEED
    horizon = torch.where(moving, CROSSING_HORIZON, 0.0)
    now_e, lead_e, ghost_e = _chord_gaps(chords, near_j, mine, horizon)
    pair = (near.cumsum(0) - 1).index_select(0, q)  # [E] the entry's pair among the K
    inf = torch.full((k.shape[0],), float("inf"), dtype=now_e.dtype, device=now_e.device)
    gap = inf.scatter_reduce(0, pair, now_e, "amin")
    ghost = inf.scatter_reduce(0, pair, ghost_e, "amin")
    nearest = (now_e == gap.index_select(0, pair)) & torch.isfinite(now_e)
    best = true_index(nearest)  # the entry of the pair's nearest chord
    lead_at = (pair.index_select(0, best),)
    lead = torch.zeros_like(gap).index_put(lead_at, lead_e.index_select(0, best))
    return k, gap, lead, ghost


@dataclass(frozen=True)
class Leader:
    """The most constraining leader of each of L followers.

    Attributes:
        gap: [L] m bumper gap along the route to the leader (+inf: none).
        speed: [L] m/s, the leader's speed along the route.
        crossing: [L] m to where a crossing agent will be that the follower yields to
            (+inf: none).
    """

    gap: torch.Tensor
    speed: torch.Tensor
    crossing: torch.Tensor


def find_leaders(
    agents: Agents,
    followers: tuple[torch.Tensor, torch.Tensor],
    lanes: Corridor,
    terms: IDMTerms,
    cfg: IDMConfig,
) -> Leader:
    """Each follower's most constraining leader: of the agents in its corridor, the one whose
    IDM ``crowding`` (s* / s)^2 is largest; and the nearest crossing it yields to.

    Args:
        agents: every slot's pose, speed and size (leaders: the slots with ``valid``).
        followers: (valid [B, N] bool: the slots that can lead; agent [L] int64 flat slot
            indices of the agents that look for leaders, valid ones).
        lanes: the L followers' corridors (``corridor``).
        terms: the L followers' IDM parameters ([L] tensors or floats).
        cfg: the corridor's margin and the smallest gap.
    """
    valid, agent = followers
    b, n = valid.shape
    length, width = agents.size.flatten(0, 1).index_select(0, agent).unbind(-1)  # [L]
    half_width = 0.5 * width + cfg.lateral_margin
    # Every corridor point lies within horizon / 2 of the route point horizon / 2 ahead.
    horizon = lanes.offset[:, -1] * CHORDS / (CHORDS - 1)
    radius = 0.5 * horizon + half_width + 0.5
    disc = torch.zeros(b * n, 3, device=valid.device, dtype=agents.speed.dtype)
    disc.index_copy_(0, agent, torch.cat([lanes.origin[:, CHORDS // 2], radius.unsqueeze(-1)], -1))
    asks = torch.zeros(b * n, dtype=torch.bool, device=valid.device)
    asks.index_fill_(0, agent, True)
    # j's box over its path of the crossing horizon (``_near_quarters``) lies within a disc
    # around the path's midpoint: half its length plus the half diagonal.
    slots = slot_table(agents)
    x, y, c, s, v, length_j, width_j = slots.view(7, b, n).unbind(0)
    half_travel = 0.5 * CROSSING_HORIZON * v
    mid = torch.stack([x + half_travel * c, y + half_travel * s], -1)
    reach = 0.5 * torch.hypot(length_j, width_j) + half_travel.abs()
    discs = (asks.view(b, n), disc.view(b, n, 3), reach)
    row, i, j = candidate_pairs(mid, valid, *discs)
    index = torch.full((b * n,), -1, dtype=torch.long, device=valid.device)
    index.index_copy_(0, agent, torch.arange(agent.shape[0], device=valid.device))
    fi, fj = row * n + i, row * n + j
    if agents.pedestrian is not None:  # groups of pedestrians keep no gaps between them
        ped = agents.pedestrian.flatten()
        apart = true_index(~(ped.index_select(0, fi) & ped.index_select(0, fj)))
        fi, fj = fi.index_select(0, apart), fj.index_select(0, apart)
    li = index.index_select(0, fi)
    speed = agents.speed.flatten().index_select(0, agent)
    own = torch.stack([length, half_width, speed], 0)
    near, gap, lead, ghost = pair_gaps((li, fj), slots, lanes, own)
    li = li.index_select(0, near)
    sel = true_index(torch.isfinite(gap) | torch.isfinite(ghost))  # the others: no constraint
    li, gap, lead, ghost = (x.index_select(0, sel) for x in (li, gap, lead, ghost))
    ratio = crowding(speed.index_select(0, li), gap, lead, terms_at(terms, li), cfg.min_gap)
    worst = torch.full_like(speed, -1.0).scatter_reduce(0, li, ratio, "amax")
    top = true_index((ratio >= worst.index_select(0, li)) & torch.isfinite(gap))
    inf = torch.full_like(speed, float("inf"))
    lt = li.index_select(0, top)
    return Leader(
        gap=inf.index_put((lt,), gap.index_select(0, top)),
        speed=torch.zeros_like(speed).index_put((lt,), lead.index_select(0, top)),
        crossing=inf.scatter_reduce(0, li, ghost, "amin"),
    )


__all__ = [
    "Agents",
    "Corridor",
    "Leader",
    "candidate_pairs",
    "corridor",
    "find_leaders",
    "pair_gaps",
    "slot_table",
]
