"""Pairwise-relative observations (TrafficBots V1.5, docs/model.md §2), batched and pure.

Every token is described in its own local frame, and its relation to the observer only by its
relative pose (dx, dy, dyaw) in the observer's frame. Nothing is expressed in scenario
coordinates, so observations do not change when a whole scenario is rotated and translated.

The keys of an observer's observation, their shapes, bounds and meaning are declared once in
``tbsim_env.observation.spec.OBS_KEYS``. Neighbours are the nearest by 2-D distance, within a
radius; invalid slots are zero with mask 0.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from tbsim_env.core import constants as C
from tbsim_env.core.config import TokenConfig
from tbsim_env.core.torch_utils import (
    cached,
    cached_arange,
    cast,
    const,
    gather_rows,
    listed,
    row_offsets,
    scalar,
    select_rows,
    true_index,
    valid_first,
    valid_order,
)
from tbsim_env.data.preprocess.map_filter import filter_map_pieces
from tbsim_env.data.preprocess.map_pieces import build_map_pieces
from tbsim_env.data.preprocess.selection import relevant_positions
from tbsim_env.data.preprocess.traffic_lights import attach_traffic_lights
from tbsim_env.data.scenario import Scenario
from tbsim_env.observation.map_knn import PieceGrid, build_piece_grid, nearest_pieces, uses_index
from tbsim_env.observation.spec import (
    ATTRIBUTE_FEATURES,
    HISTORY_FEATURES,
    NODE_FEATURES,
    ObsConfig,
    observation_shapes,
    observation_space,
)
from tbsim_env.sim.collision import agent_distances
from tbsim_env.sim.geometry import cos_sin, relative_pose, rotate_by, to_local_xy
from tbsim_env.sim.knn import k_nearest, planar_distances
from tbsim_env.sim.state import Shared, SimState


@dataclass(frozen=True)
class MapContext:
    """Static map and traffic-light tokens of a batch, computed once per scenario.

    The large tables (``Shared``, K rows) are read by batch row b at row ``row[b]`` (the
    piece grid's row map): rows of a bank share them, so that starting a new episode in a
    row copies none of them (about half a megabyte per real scene).

    Attributes:
        pose: [B, M, 3] piece pose (node 0 position, first segment heading).
        nodes: Shared [K, M, P, 4] node features in the piece frame.
        nodes_valid: Shared [K, M, P] bool.
        map_class: [B, M] int64 (``MapClass``), 0 for padding.
        valid: [B, M] bool.
        tl_pose: [B, L, 3] pose of the controlled lane piece.
        tl_state: Shared [K, L, T] int64 ``TLState`` from the log.
        tl_valid: Shared [K, L, T] bool.
        tokens: Shared [K, M, P * 4 + P + NUM_MAP_CLASSES] float32, derived: what an
            observation shows of a piece in its own frame, concatenated (``nodes``,
            ``nodes_valid``, the ``map_class`` one-hot), so that a step gathers it in one
            operation.
        invalid: [B, 1, M] bool, derived: not ``valid`` (padding pieces).
        tl_tokens: [B, T, L, NUM_TL_STATES] float32, derived: one-hot of ``tl_state``
            (step-major, so that a step's lights are one view).
        tl_invalid: [B, T, 1, L] bool, derived: not ``tl_valid``, step-major.
        knn_xy: [B, 1, M + L, 2] float32, derived: the positions the nearest-token searches
            measure to (piece starts, +inf for padding pieces, then light poses).
        grid: derived: the valid pieces' ``PieceGrid`` for the nearest-piece search
            (``tbsim_env.observation.map_knn``); its tables are shared by the rows of a bank.
    """

    pose: torch.Tensor
    nodes: Shared
    nodes_valid: Shared
    map_class: torch.Tensor
    valid: torch.Tensor
    tl_pose: torch.Tensor
    tl_state: Shared
    tl_valid: Shared
    tokens: Shared
    invalid: torch.Tensor
    tl_tokens: torch.Tensor
    tl_invalid: torch.Tensor
    knn_xy: torch.Tensor
    grid: PieceGrid

    @property
    def row(self) -> torch.Tensor:
        """[B] int64, each batch row's row of the ``Shared`` tables."""
        return self.grid.row


@dataclass(frozen=True)
class History:
    """The last H simulated states of every agent slot (oldest first).

    Attributes:
        data: [B, N, H, 5] float32 (x m, y m, yaw rad, speed m/s, valid 0/1), packed so that
            a step appends with one concatenation.
    """

    data: torch.Tensor

    @property
    def pose(self) -> torch.Tensor:
        """[B, N, H, 3] (x, y, yaw) (a view)."""
        return self.data[..., :3]

    @property
    def speed(self) -> torch.Tensor:
        """[B, N, H] m/s (a view)."""
        return self.data[..., 3]

    @property
    def valid(self) -> torch.Tensor:
        """[B, N, H] bool."""
        return self.data[..., 4] != 0


def _scene_map_numpy(scenario: Scenario, origin: np.ndarray, cfg: TokenConfig) -> dict:
    """Map pieces and TL tokens of one scenario, frame shifted by ``origin`` (numpy)."""
    n_hist = scenario.current_index + 1
    hist = np.zeros_like(scenario.tracks.valid)
    hist[:, :n_hist] = scenario.tracks.valid[:, :n_hist]
    reference = relevant_positions(scenario, origin, hist)
    pieces = build_map_pieces(scenario.road_map, origin, cfg)
    pieces = pieces.take(filter_map_pieces(pieces, reference, cfg))
    lights = attach_traffic_lights(scenario.signals, pieces, reference, cfg)
    d = pieces.dir[..., :2]
    yaw = np.arctan2(d[..., 1], d[..., 0])
    pose = np.concatenate([pieces.pos[:, 0, :2], yaw[:, :1]], axis=-1)
    rel = pieces.pos[..., :2] - pose[:, None, :2]
    c, s = np.cos(pose[:, 2])[:, None], np.sin(pose[:, 2])[:, None]
    local = np.stack([c * rel[..., 0] + s * rel[..., 1], -s * rel[..., 0] + c * rel[..., 1]], -1)
    dyaw = yaw - pose[:, None, 2]
    nodes = np.concatenate([local, np.cos(dyaw)[..., None], np.sin(dyaw)[..., None]], -1)
    nodes = np.where(pieces.valid[..., None], nodes, 0.0)
    return {
        "pose": pose,
        "nodes": nodes,
        "nodes_valid": pieces.valid,
        "map_class": pieces.map_class,
        "tl_pose": pose[lights.piece] if lights.num_tokens else np.zeros((0, 3)),
        "tl_state": lights.state,
        "tl_valid": lights.valid,
    }


def build_map_context(
    scenarios: list[Scenario], origins: torch.Tensor, cfg: ObsConfig
) -> MapContext:
    """Static observation context of a batch (map pieces and traffic lights).

    Args:
        scenarios: the B scenarios.
        origins: [B, 2] float64, the frame origin of each scenario (``SimState.origin``).
        cfg: observation configuration.
    """
    parts = [
        _scene_map_numpy(sc, origins[i].cpu().numpy(), cfg.tokens) for i, sc in enumerate(scenarios)
    ]
    b = len(parts)
    m = max(max(len(p["pose"]) for p in parts), 1)
    n_l = max(max(len(p["tl_pose"]) for p in parts), 1)
    n_t = scenarios[0].num_steps
    p_n = cfg.tokens.piece_segments
    out = {
        "pose": np.zeros((b, m, 3), np.float32),
        "nodes": np.zeros((b, m, p_n, NODE_FEATURES), np.float32),
        "nodes_valid": np.zeros((b, m, p_n), bool),
        "map_class": np.zeros((b, m), np.int64),
        "valid": np.zeros((b, m), bool),
        "tl_pose": np.zeros((b, n_l, 3), np.float32),
        "tl_state": np.zeros((b, n_l, n_t), np.int64),
        "tl_valid": np.zeros((b, n_l, n_t), bool),
    }
    for i, p in enumerate(parts):
        k, lt = len(p["pose"]), len(p["tl_pose"])
        for key in ("pose", "nodes", "nodes_valid", "map_class"):
            out[key][i, :k] = p[key]
        out["valid"][i, :k] = p["nodes_valid"][:, 0] if k else False
        for key in ("tl_pose", "tl_state", "tl_valid"):
            out[key][i, :lt] = p[key]
    dev = origins.device
    t = {k: torch.from_numpy(v).to(dev) for k, v in out.items()}
    tokens = torch.cat(
        [
            t["nodes"].flatten(-2),
            t["nodes_valid"].float(),
            _MAP_EYE.to(dev)[t["map_class"]],
        ],
        dim=-1,
    )
    tl_tokens = _TL_EYE.to(dev)[t["tl_state"]]  # [B, L, T, NUM_TL_STATES]
    map_xy = t["pose"][..., :2].masked_fill(~t["valid"][..., None], float("inf"))
    for key in ("nodes", "nodes_valid", "tl_state", "tl_valid"):
        t[key] = Shared(t[key])
    return MapContext(
        **t,
        tokens=Shared(tokens),
        invalid=~t["valid"][:, None],
        tl_tokens=_dense(tl_tokens.transpose(1, 2)),
        tl_invalid=_dense(~t["tl_valid"].value.transpose(1, 2)[:, :, None]),
        knn_xy=_dense(torch.cat([map_xy, t["tl_pose"][..., :2]], 1)[:, None]),
        grid=build_piece_grid(t["pose"][..., :2], t["valid"]),
    )


def _dense(x: torch.Tensor) -> torch.Tensor:
    """``x`` in row-major memory with the standard strides even along size-1 dims (which
    ``contiguous()`` leaves as they were): ``torch.compile`` guards on strides, so a scene with
    one traffic light would otherwise compile a graph of its own."""
    return x.clone(memory_format=torch.contiguous_format)


def init_history(state: SimState, length: int) -> History:
    """History window ending at the state's step, filled from the log (oldest first).

    The log's time-major ``by_step`` blocks already hold a step's (x, y, yaw, speed, valid) in
    ``History.data``'s layout: one ``index_select`` of the H steps of every row, then a
    transpose, instead of a gather per field.
    """
    n_b, n_t = state.batch_size, state.log.num_steps
    steps = state.step[:, None] - torch.arange(length - 1, -1, -1, device=state.device)  # [B, H]
    inside = steps >= 0
    rows = state.log.row_steps[:, None] + steps.clamp(0, n_t - 1)
    blocks = state.log.by_step.value.flatten(0, 1).index_select(0, rows.reshape(-1))  # [B H, N, 5]
    data = blocks.view(n_b, length, -1, 5).transpose(1, 2).contiguous()  # [B, N, H, 5]
    data[..., 4] *= inside[:, None, :]
    data[..., -1, :] = _history_row(state)[..., 0, :]
    return History(data=data)


def _history_row(state: SimState) -> torch.Tensor:
    """[B, N, 1, 5] the state's current step as a ``History.data`` entry."""
    b, n = state.valid.shape
    valid = cast(state.valid, state.pose.dtype).view(b, n, 1)
    return torch.cat([state.pose, state.speed.view(b, n, 1), valid], -1).view(b, n, 1, 5)


def push_history(history: History, state: SimState) -> History:
    """Drop the oldest step and append the state's current one."""
    return History(data=torch.cat([history.data[:, :, 1:], _history_row(state)], dim=2))


def agent_static_features(state: SimState) -> torch.Tensor:
    """[B, N, 6] length, width, type one-hot (vehicle, pedestrian, cyclist, other)."""
    t = state.agents.object_type
    onehot = torch.stack(
        [
            t == C.ObjectType.VEHICLE,
            t == C.ObjectType.PEDESTRIAN,
            t == C.ObjectType.CYCLIST,
            (t == C.ObjectType.OTHER) | (t == C.ObjectType.UNSET),
        ],
        dim=-1,
    ).float()
    return torch.cat([state.agents.size[..., :2], onehot], dim=-1)


@dataclass(frozen=True)
class IndexedObservation:
    """Pairwise-relative observations of Q observers per row, by reference to shared tokens.

    The same facts as ``observe``'s dense dict, without copying a token for every observer
    that sees it: every token is described once, in its own frame, and each observer holds
    the indices of the tokens it sees with their relative poses (docs/environments.md, "Indexed
    layout").
    ``densify`` gathers the dense layout from it, so the two never disagree.

    Attributes:
        agent_tokens: [B, R, H * 5 + H + 7] float32, agent tokens this step: the history in
            the agent's own current frame, the history mask, its attributes (length, width,
            type one-hot, speed). A row per agent slot (R = N), or per observer and seen
            neighbour (R = Q (1 + Ka), when that is fewer: ``observe_indexed``).
        map_tokens: [K, M, P * 4 + P + NUM_MAP_CLASSES] float32, map pieces (nodes in the
            piece frame, node mask, class one-hot) of the maps the rows read (``map_rows``);
            fixed for an episode.
        light_tokens: [B, L, NUM_TL_STATES] float32, traffic-light state one-hot this step.
        ego: [B, Q] int64, each observer's own row of ``agent_tokens``.
        index: [B, Q, Ka + Km + Kt] int64, the tokens each observer sees: Ka rows of
            ``agent_tokens``, Km map pieces, Kt lights, nearest first.
        pose: [B, Q, Ka + Km + Kt, 3] float32, their poses (dx m, dy m, dyaw rad) in the
            observer's frame, zero where masked.
        mask: [B, Q, Ka + Km + Kt] float32, 1 where a token is seen (0 for padding and tokens
            beyond the radius); ``index`` is 0 where it is 0.
        sizes: (Ka, Km, Kt).
        grouped: ``agent_tokens`` has a row per observer and neighbour, grouped by observer:
            observer q's own row ``q (1 + Ka)``, then its Ka neighbours' in order (what
            ``index`` refers to, masked entries aside), so ``densify`` reads them as views.
        map_rows: [B] int64, each row's row of ``map_tokens`` (None: row b, K = B).
    """

    agent_tokens: torch.Tensor
    map_tokens: torch.Tensor
    light_tokens: torch.Tensor
    ego: torch.Tensor
    index: torch.Tensor
    pose: torch.Tensor
    mask: torch.Tensor
    sizes: tuple[int, int, int]
    grouped: bool = False
    map_rows: torch.Tensor | None = None


def agent_tokens(
    state: SimState,
    history: History,
    static: torch.Tensor,
    slots: torch.Tensor | None = None,
) -> torch.Tensor:
    """Agent tokens: each agent's history in its own current frame (zero where invalid), the
    history mask, its attributes (static features, speed).

    The current frame and speed are the history's last entry, which is the state's current
    pose and speed (``push_history`` and ``init_history`` write them there).

    Args:
        state: current state.
        history: ``History`` ending at the current step.
        static: [B, N, 6] ``agent_static_features``.
        slots: optional [B, S] int64 slots to describe (every slot by default).

    Returns:
        [B, N or S, H * 5 + H + 7] float32.
    """
    data = history.data
    if slots is not None:
        data, static = gather_rows(data, slots), gather_rows(static, slots)
    b, n, h = data.shape[:3]
    if b * n * h >= C.COMPONENT_POSES_MIN and not torch.compiler.is_compiling():
        return _agent_tokens_by_component(data, static)
    now = data[:, :, -1:]  # [B, S, 1, 5]
    yaw = now[..., 2:3]
    c, s = cos_sin(-yaw)
    xy = rotate_by(data[..., :2] - now[..., :2], c, s)  # [B, S, H, 2] in its own frame
    turn = data[..., 2:3] - yaw
    # Contiguous pieces: a concatenation of contiguous floats is one operation, while one
    # strided piece makes it copy piece by piece (three operations each).
    speed = data[..., 3:4].contiguous()
    hist = torch.cat([xy, torch.cos(turn), torch.sin(turn), speed], -1)
    hist = (hist * data[..., 4:]).view(b, n, h * HISTORY_FEATURES)
    valid, speed_now = data[..., 4].contiguous(), now[:, :, 0, 3:4].contiguous()
    return torch.cat([hist, valid, static, speed_now], -1)


def _agent_tokens_by_component(data: torch.Tensor, static: torch.Tensor) -> torch.Tensor:
    """``agent_tokens``' values from ``History.data`` [B, S, H, 5] and ``static`` [B, S, 6],
    a component at a time, each written into the result (``COMPONENT_POSES_MIN``): the same
    arithmetic (``to_local_xy``'s is ``rotate_by``'s, bit for bit)."""
    b, n, h = data.shape[:3]
    x, y, yaw, speed, valid = data.unbind(-1)  # [B, S, H]
    now = data[:, :, -1:, :3]  # [B, S, 1, 3]
    width = h * HISTORY_FEATURES
    out = torch.empty(b, n, width + h + static.shape[-1] + 1, dtype=data.dtype, device=data.device)
    hist = out[..., :width].view(b, n, h, HISTORY_FEATURES)
    turn = yaw - now[..., 2]
    parts = (*to_local_xy(x, y, now), torch.cos(turn), torch.sin(turn), speed)
    for k, part in enumerate(parts):
        torch.mul(part, valid, out=hist[..., k])
    out[..., width : width + h] = valid
    out[..., width + h : -1] = static
    out[..., -1] = speed[..., -1]
    return out


def _seen_tokens(
    state: SimState,
    ctx: MapContext,
    observers: torch.Tensor,
    dist: torch.Tensor,
    cfg: ObsConfig,
    rows: torch.Tensor | None = None,
    columns: tuple[torch.Tensor, torch.Tensor] | None = None,
    tl_invalid: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The tokens observers see, before masking: (index [B, Q, Ka + Km + Kt] int64 (agent
    slots, map pieces, lights, nearest first), relative poses [B, Q, K, 3], seen [B, Q, K]
    bool: within the radius).

    Args:
        observers: [B, Q] int64 agent slots; dist: [B, Q, C] their centre distances to every
            slot (C = N), or to the ``columns``.
        rows: optional [B] int64: observer row b is in state / context row ``rows[b]``
            (observers gathered from several rows); row b itself by default.
        columns: optional (slot [B, Q or 1, C] int64, usable [B, Q or 1, C] bool): the slot of
            each column of ``dist`` and whether it holds a valid agent (the others are
            padding); the same neighbours as over every slot, ranked by slot.
        tl_invalid: optional [B', 1, L] ``_lights_at(ctx, state.step)[0]`` (state rows).
    """
    n, ka = state.num_agents, cfg.num_agents
    b, q = observers.shape
    me = gather_rows(state.pose, observers, rows)  # [B, Q, 3]
    if columns is None:
        valid = state.valid if rows is None else state.valid.index_select(0, rows)
        # Not another valid agent: invalid (valid <= itself is ~valid | itself), or itself.
        itself = cached_arange(n, state.device) == observers.view(b, q, 1)
        a_idx, a_top = k_nearest(dist, valid.view(-1, 1, n) <= itself, ka, cfg.agent_radius)
    else:
        slot, usable = columns
        skip = ~usable | (slot == observers.view(b, q, 1))  # not another valid agent
        a_idx, a_top = k_nearest(dist, skip, ka, cfg.agent_radius, ids=(slot.expand_as(dist), n))
    m = ctx.pose.shape[1]
    me_xy = me[..., :2]
    if tl_invalid is None:
        tl_invalid = _lights_at(ctx, state.step)[0]  # [B, 1, L]
    if rows is not None:
        tl_invalid = tl_invalid[rows]
    if uses_index(ctx.grid, m, me_xy):
        m_idx, m_top = nearest_pieces(ctx.knn_xy[:, :, :m], ctx.grid, me_xy, cfg.num_map,
                                      cfg.map_radius, rows)  # fmt: skip
        light_xy = ctx.knn_xy[:, :, m:] if rows is None else ctx.knn_xy[rows, :, m:]
        tl_dist = planar_distances(light_xy, me)  # [B, Q, L]
    else:  # pieces and lights measured at once
        targets = ctx.knn_xy if rows is None else ctx.knn_xy.index_select(0, rows)
        both = planar_distances(targets, me)  # [B, Q, M + L]
        m_idx, m_top = k_nearest(both[..., :m], None, cfg.num_map, cfg.map_radius)
        tl_dist = both[..., m:]
    t_idx, t_top = k_nearest(tl_dist, tl_invalid, cfg.num_traffic_lights, cfg.traffic_light_radius)
    radii = _radii(cfg)
    seen = torch.cat([a_top, m_top, t_top], -1) <= const(radii, me)  # [B, Q, Ka + Km + Kt]
    index = torch.cat([a_idx, m_idx, t_idx], -1)
    # The poses of every kind from one table (agents, pieces, lights): one gather.
    table = torch.cat([state.pose, ctx.pose, ctx.tl_pose], 1)  # [B', N + M + L, 3]
    at = index + _token_offsets((ka, cfg.num_map, cfg.num_traffic_lights), n, m, me.device)
    rel = relative_pose(me.view(b, q, 1, 3), gather_rows(table, at, rows))
    return index, rel, seen


def _token_offsets(
    sizes: tuple[int, int, int], n: int, m: int, device: torch.device
) -> torch.Tensor:
    """[Ka + Km + Kt] int64: each token column's first row in the pose table of
    ``_seen_tokens`` (0 for agents, N for pieces, N + M for lights); cached (built anew under
    ``torch.compile``)."""

    def build() -> torch.Tensor:
        starts = torch.tensor([0, n, n + m], device=device)
        return starts.repeat_interleave(torch.tensor(sizes, device=device))

    return cached(("token_offsets", sizes, n, m, device), build)


def _radii(cfg: ObsConfig) -> tuple[float, ...]:
    """The radius of each of the Ka + Km + Kt token columns, m."""
    sizes = (cfg.num_agents, cfg.num_map, cfg.num_traffic_lights)
    radii = (cfg.agent_radius,) * sizes[0] + (cfg.map_radius,) * sizes[1]
    return radii + (cfg.traffic_light_radius,) * sizes[2]


def _seen_by_listed(
    state: SimState,
    ctx: MapContext,
    observers: torch.Tensor,
    dist: tuple[torch.Tensor, torch.Tensor | None],
    cfg: ObsConfig,
    pairs: tuple[torch.Tensor, torch.Tensor],
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``_masked(_seen_tokens(...))`` of the observers ``pairs`` (rows [R], columns [R] of
    ``observers``) only, gathered from every row into one list and scattered back; the others
    get index 0, pose 0 and mask 0. ``dist``: ``observe_indexed``'s ``agent_distance``."""
    b, q = pairs
    dist, slots = dist
    flat = b * observers.shape[1] + q
    if slots is None:  # distances to every slot: their columns of each row's valid slots
        slot = valid_order(state.valid).index_select(0, b)  # [R, C]
        at = flat.unsqueeze(1) * state.num_agents + slot
        near = dist.reshape(-1).index_select(0, at.flatten()).view(slot.shape)
    else:
        slot, near = slots.index_select(0, b), dist.flatten(0, 1).index_select(0, flat)
    columns = (slot.unsqueeze(1), gather_rows(state.valid, slot, b).unsqueeze(1))  # [R, 1, C]
    index, rel, mask = _masked(
        *_seen_tokens(state, ctx, observers[b, q].unsqueeze(1), near.unsqueeze(1), cfg, b, columns)
    )
    out = []
    # The rows of the observers not listed are zero: written once each (no zero fill of rows
    # that the listed ones then overwrite).
    rest = None
    if flat.numel() < observers.numel():
        listed = torch.zeros(observers.numel(), dtype=torch.bool, device=flat.device)
        rest = true_index(~listed.index_fill_(0, flat, True))
    for part in (index, rel, mask):
        full = part.new_empty(observers.numel(), *part.shape[2:]).index_copy_(0, flat, part[:, 0])
        if rest is not None:
            full.index_fill_(0, rest, 0)
        out.append(full.view(*observers.shape, *part.shape[2:]))
    return out[0], out[1], out[2]


def _masked(
    index: torch.Tensor, rel: torch.Tensor, seen: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``_seen_tokens``' output with index and pose zero where a token is not ``seen``, and
    the mask as float32 0 / 1."""
    mask = cast(seen, torch.float32)
    index = torch.where(seen, index, scalar(0, index.dtype, index.device))
    return index, rel * mask.view(*mask.shape, 1), mask


def observe_indexed(
    state: SimState,
    history: History,
    ctx: MapContext,
    observers: torch.Tensor,
    cfg: ObsConfig,
    agent_static: torch.Tensor | None = None,
    agent_distance: tuple[torch.Tensor, torch.Tensor | None] | None = None,
    observer_mask: torch.Tensor | None = None,
) -> IndexedObservation:
    """Observations of the ``observers`` agents, by token index (see ``IndexedObservation``).

    When the observers see fewer agent slots than there are (Q (1 + Ka) < N), only the seen
    slots get agent tokens: ``agent_tokens`` then has a row per observer and neighbour instead
    of per slot (``ego`` and the agent part of ``index`` refer to those rows); ``densify``
    gives the same dense observation either way.

    Args:
        state: current state.
        history: ``History`` ending at the current step.
        ctx: static map context of the batch.
        observers: [B, Q] int64 agent-slot indices.
        cfg: observation sizes.
        agent_static: optional precomputed ``agent_static_features(state)`` (it does not
            change within an episode).
        agent_distance: optional (distances [B, Q, C], slots [B, C] or None): centre distances
            of the observers to the agent slots ``slots`` (``torch_utils.valid_first``), or to
            every slot where ``slots`` is None, at the current poses
            (``StepMetrics.agent_distance`` with the observers as query); computed when None.
        observer_mask: optional [B, Q] bool, the observers to describe (the env's active
            agents); the others see no token (index 0, pose 0, mask 0). Where that pays
            (``torch_utils.listed``), the searches run on the described observers only.
    """
    static = agent_static_features(state) if agent_static is None else agent_static
    dist = agent_distance
    if dist is None:
        slots = valid_first(state.valid, observers.shape[1])
        pose = state.pose if slots is None else gather_rows(state.pose, slots)
        dist = (agent_distances(gather_rows(state.pose, observers), pose), slots)
    (b, q), ka = observers.shape, cfg.num_agents
    lights = _lights_at(ctx, state.step)
    compact = q * (1 + ka) < state.num_agents
    # Compact tokens follow the observers' rows: those are never listed.
    pairs = None if compact or observer_mask is None else listed(observer_mask)
    if pairs is not None:
        index, rel, mask = _seen_by_listed(state, ctx, observers, dist, cfg, pairs)
        tokens = agent_tokens(state, history, static)
    else:
        near, slots = dist
        columns = None
        if slots is not None:
            columns = (slots.unsqueeze(1), gather_rows(state.valid, slots).unsqueeze(1))
        index, rel, seen = _seen_tokens(state, ctx, observers, near, cfg, None, columns, lights[0])
        if observer_mask is not None:
            seen = torch.bitwise_and(seen, observer_mask.view(b, q, 1))
        if compact:
            # Tokens of the seen slots only, each observer's own row and then its neighbours'.
            slots = torch.cat([observers.view(b, q, 1), index[..., :ka]], -1).view(b, -1)
            tokens = agent_tokens(state, history, static, slots)  # [B, Q (1 + Ka), F]
            ego, rows, of_agent = _grouped_rows(q, ka, state.device, index.shape[-1])
            observers = ego.expand(b, q)
            index = torch.where(of_agent, rows, index)  # the agent columns name the rows
        else:
            tokens = agent_tokens(state, history, static)
        index, rel, mask = _masked(index, rel, seen)
    return IndexedObservation(
        agent_tokens=tokens,
        map_tokens=ctx.tokens.value,
        light_tokens=lights[1],
        ego=observers,
        index=index,
        pose=rel,
        mask=mask,
        sizes=(cfg.num_agents, cfg.num_map, cfg.num_traffic_lights),
        grouped=compact,
        map_rows=ctx.row,
    )


def _grouped_rows(
    q: int, ka: int, device: torch.device, k: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rows of compact agent tokens: (ego [Q] int64, observer j's own row ``j (1 + Ka)``;
    neighbours [Q, K] int64, its Ka neighbours' rows in the first Ka of K token columns, 0 in
    the others; of_agent [K] bool, the first Ka columns); cached (built anew under
    ``torch.compile``)."""

    def build() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        ego = torch.arange(q, device=device) * (1 + ka)
        rows = torch.zeros((q, k), dtype=torch.int64, device=device)
        rows[:, :ka] = ego[:, None] + 1 + torch.arange(ka, device=device)
        return ego, rows, torch.arange(k, device=device) < ka

    return cached(("grouped_rows", q, ka, device, k), build)


def densify(obs: IndexedObservation, piece_segments: int) -> dict[str, torch.Tensor]:
    """The dense per-observer layout of ``observe``: every seen token copied per observer.

    Args:
        obs: indexed observations.
        piece_segments: P, nodes per map piece (``ObsConfig.tokens.piece_segments``).

    Returns:
        dict of float32 tensors [B, Q, ...] (masks as 0/1 float); keys as the module
        docstring. They are views of one [B, Q, D] tensor (``densify_flat``).
    """
    return dense_views(densify_flat(obs, piece_segments), obs.sizes, piece_segments)


def densify_flat(obs: IndexedObservation, piece_segments: int) -> torch.Tensor:
    """[B, Q, D] float32: ``densify``'s keys of each observer in one row (``dense_views``
    reads them from it): its own token, its neighbours' tokens, the map pieces' and the
    lights' (each zero where masked), the relative poses and the masks."""
    b, q = obs.ego.shape
    ka, km, kt = obs.sizes
    a_idx, m_idx, t_idx = obs.index.split_with_sizes(obs.sizes, -1)
    a_f, m_f, t_f = obs.mask.view(b, q, -1, 1).split_with_sizes(obs.sizes, 2)
    if obs.grouped:  # rows of each observer in order: views
        tokens = obs.agent_tokens.view(b, q, 1 + ka, -1)
        ego, nb = tokens[:, :, 0], tokens[:, :, 1:] * a_f
    else:
        ego = gather_rows(obs.agent_tokens, obs.ego)
        nb = gather_rows(obs.agent_tokens, a_idx) * a_f
    parts = [
        ego,
        nb.view(b, q, -1),
        (gather_rows(obs.map_tokens, m_idx, obs.map_rows) * m_f).view(b, q, -1),
        (gather_rows(obs.light_tokens, t_idx) * t_f).view(b, q, -1),
        obs.pose.view(b, q, -1),
        obs.mask,
    ]
    return torch.cat(parts, -1)


def dense_views(flat: Any, sizes: tuple[int, int, int], piece_segments: int) -> dict[str, Any]:
    """``densify``'s dict of views of a ``densify_flat`` row ``flat`` [..., D] (a torch tensor
    or a numpy array: the same slicing).

    Args:
        flat: [..., D] rows of ``densify_flat``.
        sizes: (Ka, Km, Kt).
        piece_segments: P.
    """
    ka, km, kt = sizes
    k, p, lead = ka + km + kt, piece_segments, tuple(flat.shape[:-1])
    f_m = p * NODE_FEATURES + p + C.NUM_MAP_CLASSES
    f_t = C.NUM_TL_STATES
    f_a = (flat.shape[-1] - km * f_m - kt * f_t - k * 4) // (1 + ka)
    h = (f_a - ATTRIBUTE_FEATURES) // (HISTORY_FEATURES + 1)
    hist, ends = h * HISTORY_FEATURES, h * (HISTORY_FEATURES + 1)
    at = np.cumsum([0, f_a, ka * f_a, km * f_m, kt * f_t, k * 3, k])
    ego = flat[..., at[0] : at[1]]
    nb = flat[..., at[1] : at[2]].reshape(*lead, ka, f_a)
    mp = flat[..., at[2] : at[3]].reshape(*lead, km, f_m)
    pose = flat[..., at[4] : at[5]].reshape(*lead, k, 3)
    mask = flat[..., at[5] : at[6]]
    return {
        "ego_history": ego[..., :hist].reshape(*lead, h, HISTORY_FEATURES),
        "ego_history_mask": ego[..., hist:ends],
        "ego_attributes": ego[..., ends:],
        "agents": nb[..., :hist].reshape(*lead, ka, h, HISTORY_FEATURES),
        "agents_history_mask": nb[..., hist:ends],
        "agents_attributes": nb[..., ends:],
        "agents_pose": pose[..., :ka, :],
        "agents_mask": mask[..., :ka],
        "map": mp[..., : p * NODE_FEATURES].reshape(*lead, km, p, NODE_FEATURES),
        "map_nodes_mask": mp[..., p * NODE_FEATURES : p * (NODE_FEATURES + 1)],
        "map_class": mp[..., p * (NODE_FEATURES + 1) :],
        "map_pose": pose[..., ka : ka + km, :],
        "map_mask": mask[..., ka : ka + km],
        "traffic_lights": flat[..., at[3] : at[4]].reshape(*lead, kt, f_t),
        "traffic_lights_pose": pose[..., ka + km :, :],
        "traffic_lights_mask": mask[..., ka + km :],
    }


def observe(
    state: SimState,
    history: History,
    ctx: MapContext,
    observers: torch.Tensor,
    cfg: ObsConfig,
    agent_static: torch.Tensor | None = None,
    agent_distance: tuple[torch.Tensor, torch.Tensor | None] | None = None,
) -> dict[str, torch.Tensor]:
    """Dense observations of the ``observers`` agents: ``densify`` of ``observe_indexed``
    (same arguments).

    Returns:
        dict of float32 tensors [B, Q, ...] (masks as 0/1 float); keys as the module docstring.
    """
    ind = observe_indexed(state, history, ctx, observers, cfg, agent_static, agent_distance)
    return densify(ind, cfg.tokens.piece_segments)


def _lights_at(ctx: MapContext, step: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The lights at ``step`` [B] (clamped to T - 1): (invalid [B, 1, L], tokens [B, L, F]).

    A batch of one on the CPU reads the step as a number (views instead of indexing), except
    under ``torch.compile``, where reading it would break the graph; otherwise one
    ``index_select`` of each row's step from each step-major table.
    """
    b, n_t = step.shape[0], ctx.tl_tokens.shape[1]
    if b == 1 and step.device.type == "cpu" and not torch.compiler.is_compiling():
        t = min(int(step), n_t - 1)
        return ctx.tl_invalid[:, t], ctx.tl_tokens[:, t]
    at = step.clamp(max=n_t - 1) + row_offsets(b, n_t, 1, step.device)
    invalid = select_rows(ctx.tl_invalid, at).view(b, *ctx.tl_invalid.shape[2:])
    return invalid, select_rows(ctx.tl_tokens, at).view(b, *ctx.tl_tokens.shape[2:])


_MAP_EYE = torch.eye(C.NUM_MAP_CLASSES)
_TL_EYE = torch.eye(C.NUM_TL_STATES)


__all__ = [
    "History",
    "IndexedObservation",
    "MapContext",
    "ObsConfig",
    "build_map_context",
    "densify",
    "init_history",
    "observation_shapes",
    "observation_space",
    "observe",
    "observe_indexed",
    "push_history",
]
