"""Synthetic but valid ``SceneTokens`` (straight multi-lane road, TLs, agents on lanes).

Used by tests, benchmarks and smoke runs when no real data is at hand. Deterministic for a seed.
"""

from __future__ import annotations

import numpy as np

from tbsim_env.core import constants as C
from tbsim_env.core.constants import MapClass, ObjectType, TLState
from tbsim_env.data.tokens import SceneTokens

LANE_WIDTH = 3.5
PIECE_LEN = C.MAP_PIECE_SEGMENTS  # 20 segments of 1 m


N_ROWS = 8
ROW_CLASSES = (
    MapClass.ROAD_EDGE_BOUNDARY, MapClass.BIKE_LANE, MapClass.SURFACE_STREET,
    MapClass.SURFACE_STREET, MapClass.SURFACE_STREET, MapClass.STOP_SIGN, MapClass.BROKEN,
    MapClass.ROAD_EDGE_BOUNDARY,
)  # fmt: skip
"""Map class of each row of pieces, from the right road edge to the left one."""
ROW_Y = (np.arange(N_ROWS) - (N_ROWS - 1) / 2) * LANE_WIDTH
"""m, the lateral position of each row."""


def _synthetic_map(rng: np.random.Generator, n_map: int) -> dict[str, np.ndarray]:
    """``n_map`` 20 m pieces in ``N_ROWS`` rows (alternating directions, a small bend, jittered
    starts so that no two distances tie exactly, 12-20 valid segments each)."""
    n_cols = -(-n_map // N_ROWS)
    x_start = -PIECE_LEN * n_cols / 2
    rows = np.arange(n_map) % N_ROWS
    cols = np.arange(n_map) // N_ROWS
    heading = np.where(rows % 2 == 0, 0.0, np.pi)  # [M]
    k = np.arange(PIECE_LEN + 1)
    bend = rng.normal(0.0, 0.002, size=(n_map, 1)) * k**2
    along = np.where(heading[:, None] == 0.0, k[None], PIECE_LEN - k[None])
    jitter = rng.uniform(-0.3, 0.3, size=(n_map, 2))
    px = x_start + cols[:, None] * PIECE_LEN + along + jitter[:, :1]
    py = ROW_Y[rows][:, None] + bend + jitter[:, 1:]
    pts = np.stack([px, py, np.zeros_like(px)], axis=-1)  # [M, 21, 3]
    n_valid = rng.integers(12, PIECE_LEN + 1, size=n_map)
    valid = k[None, :-1] < n_valid[:, None]
    pos = np.where(valid[..., None], pts[:, :-1].astype(np.float32), 0.0).astype(np.float32)
    direction = (pts[:, 1:] - pts[:, :-1]).astype(np.float32)
    direction = np.where(valid[..., None], direction, 0.0).astype(np.float32)
    nodes = pos[valid][:, :2]
    boundary = np.array(
        [nodes[:, 0].min(), nodes[:, 0].max(), nodes[:, 1].min(), nodes[:, 1].max()],
        dtype=np.float32,
    )
    map_class = np.asarray(ROW_CLASSES, dtype=np.int64)[rows]
    return {"pos": pos, "dir": direction, "valid": valid, "class": map_class,
            "boundary": boundary, "n_cols": np.int64(n_cols)}  # fmt: skip


def _synthetic_lights(
    rng: np.random.Generator, map_class: np.ndarray, n_tl: int, n_steps: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(piece [L], state [L, T], valid [L, T]) of lights on vehicle-lane pieces, switching
    phase every few seconds; some appear late."""
    lane_rows = np.flatnonzero(np.isin(map_class, [MapClass.SURFACE_STREET, MapClass.STOP_SIGN]))
    piece = rng.choice(lane_rows, size=min(n_tl, lane_rows.size), replace=False)
    piece = np.concatenate([piece, -np.ones(n_tl - piece.size, dtype=np.int64)])
    phase = rng.integers(0, 40, size=(n_tl, 1))
    cycle = (np.arange(n_steps)[None] + phase) // 30 % 3
    state = np.array([TLState.GO, TLState.CAUTION, TLState.STOP], dtype=np.int64)[cycle]
    valid = np.broadcast_to((piece >= 0)[:, None], (n_tl, n_steps)).copy()
    valid[:, :3] &= rng.random((n_tl, 1)) > 0.2  # some appear late
    return piece, np.where(valid, state, TLState.UNKNOWN), valid


def _synthetic_agents(
    rng: np.random.Generator, n_agents: int, n_steps: int, n_cols: int
) -> dict[str, np.ndarray]:
    """Agents moving along rows at constant acceleration: vehicles on the vehicle lanes,
    cyclists on the bike lane, pedestrians on the road edges; agent 0 (the SDC) a vehicle
    at the origin; a few appear late, the last one only after the history."""
    types = rng.choice(
        [ObjectType.VEHICLE, ObjectType.PEDESTRIAN, ObjectType.CYCLIST],
        size=n_agents,
        p=[0.7, 0.2, 0.1],
    ).astype(np.int64)
    types[0] = ObjectType.VEHICLE
    lane_row_ids = np.array([2, 3, 4, 5])
    row = np.where(
        types == ObjectType.VEHICLE,
        rng.choice(lane_row_ids, size=n_agents),
        np.where(types == ObjectType.CYCLIST, 1, rng.choice([0, N_ROWS - 1], size=n_agents)),
    )
    row[0] = 2
    base_speed = np.where(
        types == ObjectType.VEHICLE, 8.0, np.where(types == ObjectType.CYCLIST, 4.0, 1.3)
    )
    speed0 = base_speed * rng.uniform(0.5, 1.3, size=n_agents)
    accel = rng.uniform(-0.3, 0.3, size=n_agents)
    x_span = PIECE_LEN * n_cols
    x0 = rng.uniform(-0.35 * x_span, 0.2 * x_span, size=n_agents)
    x0[0] = 0.0
    direction = np.where(row % 2 == 0, 1.0, -1.0)
    t = np.arange(n_steps) * C.DT
    speed = speed0[:, None] + accel[:, None] * t[None]  # [N, T]
    dist = speed0[:, None] * t[None] + 0.5 * accel[:, None] * t[None] ** 2
    x = x0[:, None] + direction[:, None] * dist
    y = np.broadcast_to(ROW_Y[row][:, None], x.shape) + rng.normal(0, 0.2, (n_agents, 1))
    yaw = np.broadcast_to(np.where(direction > 0, 0.0, np.pi)[:, None], x.shape)
    start = np.where(rng.random(n_agents) < 0.15, rng.integers(1, 9, n_agents), 0)
    start[0] = 0
    if n_agents > 2:
        start[-1] = 40  # never valid in history: must never be spawned
    return {
        "types": types,
        "pos": np.stack([x, y, np.zeros_like(x)], axis=-1),
        "vel": np.stack([direction[:, None] * speed, np.zeros_like(speed)], axis=-1),
        "speed": speed,
        "accel": accel,
        "yaw": yaw,
        "start": start,
    }


def _destinations(types: np.ndarray, final_xy: np.ndarray, m: dict[str, np.ndarray]) -> np.ndarray:
    """[N] destination piece: the nearest allowed node to the final position (the rule
    families of docs/model.md §1.7), -1 without one."""
    allowed = {
        ObjectType.VEHICLE: [MapClass.SURFACE_STREET, MapClass.STOP_SIGN],
        ObjectType.PEDESTRIAN: [MapClass.ROAD_EDGE_BOUNDARY],
        ObjectType.CYCLIST: [MapClass.BIKE_LANE],
    }
    dest = np.full(len(types), -1, dtype=np.int64)
    for ty, classes in allowed.items():
        pieces = np.flatnonzero(np.isin(m["class"], classes))
        agents = np.flatnonzero(types == ty)
        if pieces.size == 0 or agents.size == 0:
            continue
        d = np.linalg.norm(
            m["pos"][pieces][None, :, :, :2] - final_xy[agents][:, None, None, :2], axis=-1
        )
        d = np.where(m["valid"][pieces][None], d, np.inf).min(-1)  # [A, pieces]
        dest[agents] = pieces[d.argmin(-1)]
    return dest


def make_synthetic_tokens(
    n_agents: int = 16,
    n_map: int = 96,
    n_tl: int = 8,
    n_steps: int = C.NUM_STEPS,
    seed: int = 0,
) -> SceneTokens:
    """Build a scene: ``N_ROWS`` parallel rows of 20 m pieces (road edges outside, a bike
    lane, alternating-direction vehicle lanes), TLs on some lane pieces, agents moving along
    rows.

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
    m = _synthetic_map(rng, n_map)
    tl_piece, tl_state, tl_valid = _synthetic_lights(rng, m["class"], n_tl, n_steps)
    a = _synthetic_agents(rng, n_agents, n_steps, int(m["n_cols"]))
    types, start = a["types"], a["start"]
    valid = np.arange(n_steps)[None] >= start[:, None]
    size = np.where(
        (types == ObjectType.VEHICLE)[:, None],
        [4.6, 1.9, 1.6],
        np.where((types == ObjectType.CYCLIST)[:, None], [1.8, 0.7, 1.6], [0.6, 0.6, 1.8]),
    )
    role = np.zeros((n_agents, 3), dtype=bool)
    role[0, 0] = True
    role[1 : min(4, n_agents), 2] = True
    moving = valid & (np.arange(n_steps) > start[:, None])
    f32 = np.float32
    return SceneTokens(
        scenario_id=f"synthetic-{seed}",
        origin=np.zeros(2),
        frame_yaw=np.zeros(()),
        map_pos=m["pos"],
        map_dir=m["dir"],
        map_valid=m["valid"],
        map_class=m["class"],
        map_feature_id=np.arange(n_map, dtype=np.int64),
        map_boundary=m["boundary"],
        tl_piece=tl_piece.astype(np.int64),
        tl_state=tl_state.astype(np.int64),
        tl_valid=tl_valid,
        agent_track_index=np.arange(n_agents, dtype=np.int64),
        agent_valid=valid,
        agent_pos=np.where(valid[..., None], a["pos"], 0).astype(f32),
        agent_vel=np.where(valid[..., None], a["vel"], 0).astype(f32),
        agent_speed=np.where(valid, a["speed"], 0).astype(f32),
        agent_accel=np.where(moving, a["accel"][:, None], 0).astype(f32),
        agent_yaw=np.where(valid, a["yaw"], 0).astype(f32),
        agent_yaw_rate=np.zeros((n_agents, n_steps), dtype=f32),
        agent_type=types,
        agent_size=size.astype(f32),
        agent_role=role,
        agent_dest=_destinations(types, a["pos"][:, -1], m),
    )
