"""Synthetic but valid ``SceneTokens`` (straight multi-lane road, TLs, agents on lanes).

Used by tests, benchmarks and smoke runs when no real data is at hand. Deterministic for a seed.
"""

from __future__ import annotations

import numpy as np

from tbsim_env import constants as C
from tbsim_env.constants import MapClass, ObjectType, TLState
from tbsim_env.data.tokens import SceneTokens

LANE_WIDTH = 3.5
PIECE_LEN = C.MAP_PIECE_SEGMENTS  # 20 segments of 1 m


def make_synthetic_tokens(
    n_agents: int = 16,
    n_map: int = 96,
    n_tl: int = 8,
    n_steps: int = C.NUM_STEPS,
    seed: int = 0,
) -> SceneTokens:
    """Build a scene: ``n_rows`` parallel rows of 20 m pieces (road edges outside, a bike lane,
    alternating-direction vehicle lanes), TLs on some lane pieces, agents moving along rows.

    Args:
        n_agents: agents (agent 0 is the SDC).
        n_map: map pieces.
        n_tl: TL tokens.
        n_steps: steps.
        seed: random seed.

    Returns:
        ``SceneTokens`` (arrays sized exactly by the arguments, no padding).
    """
    rng = np.random.default_rng(seed)
    n_rows = 8
    row_cls = [MapClass.ROAD_EDGE_BOUNDARY, MapClass.BIKE_LANE, MapClass.SURFACE_STREET,
               MapClass.SURFACE_STREET, MapClass.SURFACE_STREET, MapClass.STOP_SIGN,
               MapClass.BROKEN, MapClass.ROAD_EDGE_BOUNDARY]  # fmt: skip
    n_cols = -(-n_map // n_rows)
    x_start = -PIECE_LEN * n_cols / 2
    rows = np.arange(n_map) % n_rows
    cols = np.arange(n_map) // n_rows
    row_y = (np.arange(n_rows) - (n_rows - 1) / 2) * LANE_WIDTH
    heading = np.where(rows % 2 == 0, 0.0, np.pi)  # [M]
    # Nodes of each piece, direction given by the row, with a small bend.
    k = np.arange(PIECE_LEN + 1)
    bend = rng.normal(0.0, 0.002, size=(n_map, 1)) * k**2
    along = np.where(heading[:, None] == 0.0, k[None], PIECE_LEN - k[None])
    # Jitter the piece starts so that no two distances tie exactly (KNN ties are arbitrary).
    jitter = rng.uniform(-0.3, 0.3, size=(n_map, 2))
    px = x_start + cols[:, None] * PIECE_LEN + along + jitter[:, :1]
    py = row_y[rows][:, None] + bend + jitter[:, 1:]
    pts = np.stack([px, py, np.zeros_like(px)], axis=-1)  # [M, 21, 3]
    map_pos = pts[:, :-1].astype(np.float32)
    map_dir = (pts[:, 1:] - pts[:, :-1]).astype(np.float32)
    n_valid = rng.integers(12, PIECE_LEN + 1, size=n_map)
    map_valid = k[None, :-1] < n_valid[:, None]
    map_pos = np.where(map_valid[..., None], map_pos, 0.0).astype(np.float32)
    map_dir = np.where(map_valid[..., None], map_dir, 0.0).astype(np.float32)
    map_class = np.asarray(row_cls, dtype=np.int64)[rows]
    nodes = map_pos[map_valid][:, :2]
    boundary = np.array(
        [nodes[:, 0].min(), nodes[:, 0].max(), nodes[:, 1].min(), nodes[:, 1].max()],
        dtype=np.float32,
    )

    # Traffic lights on vehicle-lane pieces, switching phase every few seconds.
    lane_rows = np.flatnonzero(np.isin(map_class, [MapClass.SURFACE_STREET, MapClass.STOP_SIGN]))
    tl_piece = rng.choice(lane_rows, size=min(n_tl, lane_rows.size), replace=False)
    tl_piece = np.concatenate([tl_piece, -np.ones(n_tl - tl_piece.size, dtype=np.int64)])
    phase = rng.integers(0, 40, size=(n_tl, 1))
    cycle = (np.arange(n_steps)[None] + phase) // 30 % 3
    tl_state = np.array([TLState.GO, TLState.CAUTION, TLState.STOP], dtype=np.int64)[cycle]
    tl_valid = np.broadcast_to((tl_piece >= 0)[:, None], (n_tl, n_steps)).copy()
    tl_valid[:, :3] &= rng.random((n_tl, 1)) > 0.2  # some appear late
    tl_state = np.where(tl_valid, tl_state, TLState.UNKNOWN)

    # Agents.
    types = rng.choice(
        [ObjectType.VEHICLE, ObjectType.PEDESTRIAN, ObjectType.CYCLIST],
        size=n_agents,
        p=[0.7, 0.2, 0.1],
    ).astype(np.int64)
    types[0] = ObjectType.VEHICLE
    lane_row_ids = np.array([2, 3, 4, 5])
    agent_row = np.where(
        types == ObjectType.VEHICLE,
        rng.choice(lane_row_ids, size=n_agents),
        np.where(types == ObjectType.CYCLIST, 1, rng.choice([0, n_rows - 1], size=n_agents)),
    )
    agent_row[0] = 2
    base_speed = np.where(
        types == ObjectType.VEHICLE, 8.0, np.where(types == ObjectType.CYCLIST, 4.0, 1.3)
    )
    speed0 = base_speed * rng.uniform(0.5, 1.3, size=n_agents)
    accel = rng.uniform(-0.3, 0.3, size=n_agents)
    x_span = PIECE_LEN * n_cols
    x0 = rng.uniform(-0.35 * x_span, 0.2 * x_span, size=n_agents)
    x0[0] = 0.0
    direction = np.where(agent_row % 2 == 0, 1.0, -1.0)
    t = np.arange(n_steps) * C.DT
    speed = speed0[:, None] + accel[:, None] * t[None]  # [N, T]
    dist = speed0[:, None] * t[None] + 0.5 * accel[:, None] * t[None] ** 2
    x = x0[:, None] + direction[:, None] * dist
    y = np.broadcast_to(row_y[agent_row][:, None], x.shape) + rng.normal(0, 0.2, (n_agents, 1))
    yaw = np.broadcast_to(np.where(direction > 0, 0.0, np.pi)[:, None], x.shape)
    pos = np.stack([x, y, np.zeros_like(x)], axis=-1)
    vel = np.stack([direction[:, None] * speed, np.zeros_like(speed)], axis=-1)
    start = np.where(rng.random(n_agents) < 0.15, rng.integers(1, 9, n_agents), 0)
    start[0] = 0
    if n_agents > 2:
        start[-1] = 40  # never valid in history: must never be spawned
    valid = np.arange(n_steps)[None] >= start[:, None]
    size = np.where(
        (types == ObjectType.VEHICLE)[:, None],
        [4.6, 1.9, 1.6],
        np.where((types == ObjectType.CYCLIST)[:, None], [1.8, 0.7, 1.6], [0.6, 0.6, 1.8]),
    )
    role = np.zeros((n_agents, 3), dtype=bool)
    role[0, 0] = True
    role[1 : min(4, n_agents), 2] = True

    # Destination: nearest allowed node to the final position (same rule families as 1.7).
    allowed = {
        ObjectType.VEHICLE: [MapClass.SURFACE_STREET, MapClass.STOP_SIGN],
        ObjectType.PEDESTRIAN: [MapClass.ROAD_EDGE_BOUNDARY],
        ObjectType.CYCLIST: [MapClass.BIKE_LANE],
    }
    dest = np.full(n_agents, -1, dtype=np.int64)
    for ty, classes in allowed.items():
        pieces = np.flatnonzero(np.isin(map_class, classes))
        agents = np.flatnonzero(types == ty)
        if pieces.size == 0 or agents.size == 0:
            continue
        d = np.linalg.norm(
            map_pos[pieces][None, :, :, :2] - pos[agents, -1][:, None, None, :2], axis=-1
        )
        d = np.where(map_valid[pieces][None], d, np.inf).min(-1)  # [A, pieces]
        dest[agents] = pieces[d.argmin(-1)]

    f32 = np.float32
    return SceneTokens(
        scenario_id=f"synthetic-{seed}",
        origin=np.zeros(2),
        frame_yaw=np.zeros(()),
        map_pos=map_pos,
        map_dir=map_dir,
        map_valid=map_valid,
        map_class=map_class,
        map_feature_id=np.arange(n_map, dtype=np.int64),
        map_boundary=boundary,
        tl_piece=tl_piece.astype(np.int64),
        tl_state=tl_state.astype(np.int64),
        tl_valid=tl_valid,
        agent_track_index=np.arange(n_agents, dtype=np.int64),
        agent_valid=valid,
        agent_pos=np.where(valid[..., None], pos, 0).astype(f32),
        agent_vel=np.where(valid[..., None], vel, 0).astype(f32),
        agent_speed=np.where(valid, speed, 0).astype(f32),
        agent_accel=np.where(
            valid & (np.arange(n_steps) > start[:, None]), accel[:, None], 0
        ).astype(f32),
        agent_yaw=np.where(valid, yaw, 0).astype(f32),
        agent_yaw_rate=np.zeros((n_agents, n_steps), dtype=f32),
        agent_type=types,
        agent_size=size.astype(f32),
        agent_role=role,
        agent_dest=dest,
    )
