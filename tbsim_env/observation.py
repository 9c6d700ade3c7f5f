"""Pairwise-relative observations (TrafficBots V1.5, docs/model.md §2), batched and pure.

Every token is described in its own local frame, and its relation to the observer only by its
relative pose (dx, dy, dyaw) in the observer's frame. Nothing is expressed in scenario
coordinates, so observations do not change when a whole scenario is rotated and translated.

The keys of an observer's observation, their shapes, bounds and meaning are declared once in
``tbsim_env.observation_spec.OBS_KEYS``. Neighbours are the nearest by 2-D distance, within a
radius; invalid slots are zero with mask 0.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from tbsim_env import constants as C
from tbsim_env.config import TokenConfig
from tbsim_env.data.preprocess.map_filter import filter_map_pieces
from tbsim_env.data.preprocess.map_pieces import build_map_pieces
from tbsim_env.data.preprocess.selection import relevant_positions
from tbsim_env.data.preprocess.traffic_lights import attach_traffic_lights
from tbsim_env.data.scenario import Scenario
from tbsim_env.map_knn import PieceGrid, build_piece_grid, nearest_pieces
from tbsim_env.observation_spec import (
    ATTRIBUTE_FEATURES,
    HISTORY_FEATURES,
    NODE_FEATURES,
    ObsConfig,
    observation_shapes,
    observation_space,
)
from tbsim_env.sim.collision import agent_distances
from tbsim_env.sim.geometry import cos_sin, relative_pose, to_local_xy
from tbsim_env.sim.knn import k_nearest, planar_distances
from tbsim_env.sim.state import SimState
from tbsim_env.torch_utils import (
    cached_arange,
    const,
    gather_rows,
    listed,
    valid_first,
    valid_order,
)


@dataclass(frozen=True)
class MapContext:
    """Static map and traffic-light tokens of a batch, computed once per scenario.

    Attributes:
        pose: [B, M, 3] piece pose (node 0 position, first segment heading).
        nodes: [B, M, P, 4] node features in the piece frame.
        nodes_valid: [B, M, P] bool.
        map_class: [B, M] int64 (``MapClass``), 0 for padding.
        valid: [B, M] bool.
        tl_pose: [B, L, 3] pose of the controlled lane piece.
        tl_state: [B, L, T] int64 ``TLState`` from the log.
        tl_valid: [B, L, T] bool.
        tokens: [B, M, P * 4 + P + NUM_MAP_CLASSES] float32, derived: what an observation
            shows of a piece in its own frame, concatenated (``nodes``, ``nodes_valid``, the
            ``map_class`` one-hot), so that a step gathers it in one operation.
        invalid: [B, 1, M] bool, derived: not ``valid`` (padding pieces).
        tl_tokens: [B, T, L, NUM_TL_STATES] float32, derived: one-hot of ``tl_state``
            (step-major, so that a step's lights are one view).
        tl_invalid: [B, T, 1, L] bool, derived: not ``tl_valid``, step-major.
        knn_xy: [B, 1, M + L, 2] float32, derived: the positions the nearest-token searches
            measure to (piece starts, +inf for padding pieces, then light poses).
        grid: derived: the valid pieces' ``PieceGrid`` for the nearest-piece search
            (``tbsim_env.map_knn``); its tables are shared by the rows of a bank.
    """

    pose: torch.Tensor
    nodes: torch.Tensor
    nodes_valid: torch.Tensor
    map_class: torch.Tensor
    valid: torch.Tensor
    tl_pose: torch.Tensor
    tl_state: torch.Tensor
    tl_valid: torch.Tensor
    tokens: torch.Tensor
    invalid: torch.Tensor
    tl_tokens: torch.Tensor
    tl_invalid: torch.Tensor
    knn_xy: torch.Tensor
    grid: PieceGrid


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
    return MapContext(
        **t,
        tokens=tokens,
        invalid=~t["valid"][:, None],
        tl_tokens=_dense(tl_tokens.transpose(1, 2)),
        tl_invalid=_dense(~t["tl_valid"].transpose(1, 2)[:, :, None]),
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
    n_b, n_t = state.batch_size, state.log.valid.shape[-1]
    steps = state.step[:, None] - torch.arange(length - 1, -1, -1, device=state.device)  # [B, H]
    inside = steps >= 0
    rows = cached_arange(n_b, state.device)[:, None] * n_t + steps.clamp(0, n_t - 1)
    blocks = state.log.by_step.flatten(0, 1).index_select(0, rows.reshape(-1))  # [B H, N, 5]
    data = blocks.view(n_b, length, -1, 5).transpose(1, 2).contiguous()  # [B, N, H, 5]
    data[..., 4] *= inside[:, None, :]
    data[..., -1, :] = _history_row(state)[..., 0, :]
    return History(data=data)


def _history_row(state: SimState) -> torch.Tensor:
    """[B, N, 1, 5] the state's current step as a ``History.data`` entry."""
    row = [state.pose, state.speed.unsqueeze(-1), state.valid.unsqueeze(-1).float()]
    return torch.cat(row, -1).unsqueeze(2)


def push_history(history: History, state: SimState) -> History:
    """Drop the oldest step and append the state's current one."""
    return History(data=torch.cat([history.data[:, :, 1:], _history_row(state)], dim=2))


def _history_features(
    x: torch.Tensor, y: torch.Tensor, yaw: torch.Tensor, speed: torch.Tensor, frame: torch.Tensor
) -> torch.Tensor:
    """[..., H, 5] history (x, y, yaw, speed [..., H]) in ``frame`` ([..., 3]): x, y, cos, sin,
    speed."""
    frame = frame.unsqueeze(-2)
    lx, ly = to_local_xy(x, y, frame)
    c, s = cos_sin(yaw - frame[..., 2])
    return torch.stack([lx, ly, c, s, speed], -1)


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
        map_tokens: [B, M, P * 4 + P + NUM_MAP_CLASSES] float32, map pieces (nodes in the
            piece frame, node mask, class one-hot); fixed for an episode.
        light_tokens: [B, L, NUM_TL_STATES] float32, traffic-light state one-hot this step.
        ego: [B, Q] int64, each observer's own row of ``agent_tokens``.
        index: [B, Q, Ka + Km + Kt] int64, the tokens each observer sees: Ka rows of
            ``agent_tokens``, Km map pieces, Kt lights, nearest first.
        pose: [B, Q, Ka + Km + Kt, 3] float32, their poses (dx m, dy m, dyaw rad) in the
            observer's frame, zero where masked.
        mask: [B, Q, Ka + Km + Kt] float32, 1 where a token is seen (0 for padding and tokens
            beyond the radius); ``index`` is 0 where it is 0.
        sizes: (Ka, Km, Kt).
    """

    agent_tokens: torch.Tensor
    map_tokens: torch.Tensor
    light_tokens: torch.Tensor
    ego: torch.Tensor
    index: torch.Tensor
    pose: torch.Tensor
    mask: torch.Tensor
    sizes: tuple[int, int, int]


def agent_tokens(
    state: SimState,
    history: History,
    static: torch.Tensor,
    slots: torch.Tensor | None = None,
) -> torch.Tensor:
    """Agent tokens: each agent's history in its own current frame (zero where invalid), the
    history mask, its attributes (static features, speed).

    Args:
        state: current state.
        history: ``History`` ending at the current step.
        static: [B, N, 6] ``agent_static_features``.
        slots: optional [B, S] int64 slots to describe (every slot by default).

    Returns:
        [B, N or S, H * 5 + H + 7] float32.
    """
    data, pose, speed_now = history.data, state.pose, state.speed
    if slots is not None:
        data, pose = gather_rows(data, slots), gather_rows(pose, slots)
        static, speed_now = gather_rows(static, slots), gather_rows(speed_now, slots)
    x, y, yaw, speed, valid = data.unbind(-1)  # [B, S, H], valid as 0 / 1
    hist = _history_features(x, y, yaw, speed, pose) * valid.unsqueeze(-1)
    return torch.cat([hist.flatten(-2), valid, static, speed_now[..., None]], -1)


def _seen_tokens(
    state: SimState,
    ctx: MapContext,
    observers: torch.Tensor,
    dist: torch.Tensor,
    cfg: ObsConfig,
    rows: torch.Tensor | None = None,
    columns: tuple[torch.Tensor, torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The tokens observers see, before masking: (index [B, Q, Ka + Km + Kt] int64 (agent
    slots, map pieces, lights, nearest first), relative poses [B, Q, K, 3], mask [B, Q, K]
    float32: 1 within the radius).

    Args:
        observers: [B, Q] int64 agent slots; dist: [B, Q, C] their centre distances to every
            slot (C = N), or to the ``columns``.
        rows: optional [B] int64: observer row b is in state / context row ``rows[b]``
            (observers gathered from several rows); row b itself by default.
        columns: optional (slot [B, Q or 1, C] int64, usable [B, Q or 1, C] bool): the slot of
            each column of ``dist`` and whether it holds a valid agent (the others are
            padding); the same neighbours as over every slot, ranked by slot.
    """
    n, ka = state.num_agents, cfg.num_agents
    me = gather_rows(state.pose, observers, rows)  # [B, Q, 3]
    if columns is None:
        valid = state.valid if rows is None else state.valid.index_select(0, rows)
        # Not another valid agent: invalid (valid <= itself is ~valid | itself), or itself.
        itself = cached_arange(n, state.device) == observers.unsqueeze(-1)
        a_idx, a_top = k_nearest(dist, valid.unsqueeze(1) <= itself, ka, cfg.agent_radius)
    else:
        slot, usable = columns
        skip = ~usable | (slot == observers.unsqueeze(-1))  # not another valid agent
        a_idx, a_top = k_nearest(dist, skip, ka, cfg.agent_radius, ids=(slot.expand_as(dist), n))
    pieces = ctx.knn_xy[:, :, : ctx.pose.shape[1]]  # [B, 1, M, 2]
    m_idx, m_top = nearest_pieces(pieces, ctx.grid, me[..., :2], cfg.num_map, cfg.map_radius, rows)
    light_xy = ctx.knn_xy[:, :, ctx.pose.shape[1] :]  # [B, 1, L, 2]
    tl_invalid = _lights_at(ctx, state.step)[0]  # [B, 1, L]
    if rows is not None:
        light_xy, tl_invalid = light_xy[rows], tl_invalid[rows]
    tl_dist = planar_distances(light_xy, me)  # [B, Q, L]
    t_idx, t_top = k_nearest(tl_dist, tl_invalid, cfg.num_traffic_lights, cfg.traffic_light_radius)

    sizes = (cfg.num_agents, cfg.num_map, cfg.num_traffic_lights)
    radii = (cfg.agent_radius,) * sizes[0] + (cfg.map_radius,) * sizes[1]
    radii += (cfg.traffic_light_radius,) * sizes[2]
    top = torch.cat([a_top, m_top, t_top], -1)  # [B, Q, Ka + Km + Kt]
    poses = [
        gather_rows(state.pose, a_idx, rows),
        gather_rows(ctx.pose, m_idx, rows),
        gather_rows(ctx.tl_pose, t_idx, rows),
    ]
    rel = relative_pose(me[:, :, None], torch.cat(poses, 2))
    index = torch.cat([a_idx, m_idx, t_idx], -1)
    return index, rel, (top <= const(radii, top)).float()


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
    for part in (index, rel, mask):
        full = part.new_zeros(observers.numel(), *part.shape[2:])
        full.index_copy_(0, flat, part[:, 0])
        out.append(full.view(*observers.shape, *part.shape[2:]))
    return out[0], out[1], out[2]


def _masked(
    index: torch.Tensor, rel: torch.Tensor, mask: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``_seen_tokens``' output with index and pose zero where the mask is."""
    return torch.where(mask > 0, index, torch.zeros_like(index)), rel * mask[..., None], mask


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
    q, ka = observers.shape[1], cfg.num_agents
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
        index, rel, mask = _seen_tokens(state, ctx, observers, near, cfg, columns=columns)
        if observer_mask is not None:
            mask = mask * observer_mask.unsqueeze(-1)
        if compact:
            # Tokens of the seen slots only, each observer's own row and then its neighbours'.
            slots = torch.cat([observers.unsqueeze(-1), index[..., :ka]], -1).flatten(1)
            tokens = agent_tokens(state, history, static, slots)  # [B, Q (1 + Ka), F]
            observers = cached_arange(q, state.device).expand_as(observers) * (1 + ka)
            a_rows = observers.unsqueeze(-1) + 1 + cached_arange(ka, state.device)
            index = torch.cat([a_rows, index[..., ka:]], -1)
        else:
            tokens = agent_tokens(state, history, static)
        index, rel, mask = _masked(index, rel, mask)
    return IndexedObservation(
        agent_tokens=tokens,
        map_tokens=ctx.tokens,
        light_tokens=_lights_at(ctx, state.step)[1],
        ego=observers,
        index=index,
        pose=rel,
        mask=mask,
        sizes=(cfg.num_agents, cfg.num_map, cfg.num_traffic_lights),
    )


def densify(obs: IndexedObservation, piece_segments: int) -> dict[str, torch.Tensor]:
    """The dense per-observer layout of ``observe``: every seen token copied per observer.

    Args:
        obs: indexed observations.
        piece_segments: P, nodes per map piece (``ObsConfig.tokens.piece_segments``).

    Returns:
        dict of float32 tensors [B, Q, ...] (masks as 0/1 float); keys as the module
        docstring.
    """
    h = (obs.agent_tokens.shape[-1] - ATTRIBUTE_FEATURES) // (HISTORY_FEATURES + 1)
    widths = [h * HISTORY_FEATURES, h, ATTRIBUTE_FEATURES]
    a_idx, m_idx, t_idx = obs.index.split_with_sizes(obs.sizes, -1)
    a_f, m_f, t_f = obs.mask.split_with_sizes(obs.sizes, -1)
    a_pose, m_pose, t_pose = obs.pose.split_with_sizes(obs.sizes, 2)
    ego_hist, ego_valid, ego_attrs = gather_rows(obs.agent_tokens, obs.ego).split_with_sizes(
        widths, -1
    )
    nb = gather_rows(obs.agent_tokens, a_idx) * a_f[..., None]
    nb_hist, nb_valid, nb_attrs = nb.split_with_sizes(widths, -1)
    p = piece_segments
    m_nodes, m_nodes_mask, m_class = (
        gather_rows(obs.map_tokens, m_idx) * m_f[..., None]
    ).split_with_sizes([p * NODE_FEATURES, p, C.NUM_MAP_CLASSES], -1)
    return {
        "ego_history": ego_hist.unflatten(-1, (h, HISTORY_FEATURES)),
        "ego_history_mask": ego_valid,
        "ego_attributes": ego_attrs,
        "agents": nb_hist.unflatten(-1, (h, HISTORY_FEATURES)),
        "agents_history_mask": nb_valid,
        "agents_attributes": nb_attrs,
        "agents_pose": a_pose,
        "agents_mask": a_f,
        "map": m_nodes.unflatten(-1, (p, NODE_FEATURES)),
        "map_nodes_mask": m_nodes_mask,
        "map_class": m_class,
        "map_pose": m_pose,
        "map_mask": m_f,
        "traffic_lights": gather_rows(obs.light_tokens, t_idx) * t_f[..., None],
        "traffic_lights_pose": t_pose,
        "traffic_lights_mask": t_f,
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
    under ``torch.compile``, where reading it would break the graph.
    """
    n_t = ctx.tl_tokens.shape[1]
    if step.shape[0] == 1 and step.device.type == "cpu" and not torch.compiler.is_compiling():
        t = min(int(step.item()), n_t - 1)
        return ctx.tl_invalid[:, t], ctx.tl_tokens[:, t]
    at = (cached_arange(step.shape[0], step.device), step.clamp(max=n_t - 1))
    return ctx.tl_invalid[at], ctx.tl_tokens[at]


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
