"""A small synthetic WOSAC test case: a straight multi-lane road with traffic and a red light.

Used by tests and the benchmark when no real WOMD data is available. The road runs along +x;
lane k has its centre at y = (k - (lanes - 1) / 2) * lane_width; the road edges are the lines
y = -half_width (pointing +x) and y = +half_width (pointing -x), so the road is on their left.
Lane 0 (the lowest) is a surface street controlled by a signal that is red over the whole
scenario, with its stop point at x = ``stop_x``.
"""

from __future__ import annotations

import numpy as np
import torch

from tbsim_env.core.constants import (
    CURRENT_INDEX,
    DT,
    NUM_FUTURE,
    NUM_STEPS,
    LaneType,
    MapFeatureType,
    ObjectType,
    RoadEdgeType,
    SignalState,
)
from tbsim_env.data.scenario import RoadMap, Scenario, Tracks, TrafficSignals
from tbsim_env.metrics.wosac.config import NUM_ROLLOUTS
from tbsim_env.metrics.wosac.rollouts import Rollouts, log_replay_rollouts

LANE_WIDTH = 3.5
"""Metres."""
VEHICLE_SIZE = (4.5, 2.0, 1.6)
"""Length, width, height in metres."""


def straight_road_map(
    num_lanes: int = 4, x_min: float = -200.0, x_max: float = 1200.0, spacing: float = 0.5
) -> RoadMap:
    """Two road edges and ``num_lanes`` surface-street lane centres along +x (ids 1, 2, 100+k).

    Points are ``spacing`` metres apart, like WOMD polylines.
    """
    xs = np.arange(x_min, x_max + spacing / 2, spacing)
    half = num_lanes * LANE_WIDTH / 2.0

    def line(y: float, reverse: bool = False) -> np.ndarray:
        pts = np.stack([xs, np.full_like(xs, y), np.zeros_like(xs)], -1)
        return pts[::-1].copy() if reverse else pts

    polylines = [line(-half), line(half, reverse=True)]
    ids = [1, 2]
    types = [int(MapFeatureType.ROAD_EDGE)] * 2
    subtypes = [int(RoadEdgeType.BOUNDARY)] * 2
    for k in range(num_lanes):
        polylines.append(line((k - (num_lanes - 1) / 2.0) * LANE_WIDTH))
        ids.append(100 + k)
        types.append(int(MapFeatureType.LANE))
        subtypes.append(int(LaneType.SURFACE_STREET))
    return RoadMap.from_polylines(ids, types, subtypes, polylines)


def synthetic_scenario(
    num_agents: int = 50,
    num_lanes: int = 4,
    seed: int = 0,
    stop_x: float = 400.0,
    scenario_id: str = "synthetic0000000",
) -> Scenario:
    """Vehicles at constant speed on a straight road, 91 steps, the last one is the SDC.

    Agents are spread over the lanes 20 m apart with speeds 5-15 m/s; tracks to predict are
    agents 0, 1 and 2 (plus the SDC). All agents are valid at every step.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(NUM_STEPS) * DT
    lane = np.arange(num_agents) % num_lanes
    y0 = (lane - (num_lanes - 1) / 2.0) * LANE_WIDTH
    x0 = (np.arange(num_agents) // num_lanes) * 20.0 + rng.uniform(-2.0, 2.0, num_agents)
    speed = rng.uniform(5.0, 15.0, num_agents)
    xyz = np.zeros((num_agents, NUM_STEPS, 3))
    xyz[..., 0] = x0[:, None] + speed[:, None] * t[None]
    xyz[..., 1] = y0[:, None]
    velocity = np.zeros((num_agents, NUM_STEPS, 2), np.float32)
    velocity[..., 0] = speed[:, None]
    size = np.broadcast_to(np.array(VEHICLE_SIZE, np.float32), (num_agents, NUM_STEPS, 3))
    tracks = Tracks(
        id=np.arange(1000, 1000 + num_agents, dtype=np.int64),
        object_type=np.full(num_agents, int(ObjectType.VEHICLE), np.int8),
        xyz=xyz,
        heading=np.zeros((num_agents, NUM_STEPS), np.float32),
        velocity=velocity,
        size=size.copy(),
        valid=np.ones((num_agents, NUM_STEPS), bool),
    )
    signals = TrafficSignals(
        lane_id=np.array([100], np.int64),
        state=np.full((1, NUM_STEPS), int(SignalState.STOP), np.int8),
        valid=np.ones((1, NUM_STEPS), bool),
        stop_point=np.array([[stop_x, y0.min(), 0.0]]),
    )
    return Scenario(
        scenario_id=scenario_id,
        timestamps=t,
        current_index=CURRENT_INDEX,
        tracks=tracks,
        road_map=straight_road_map(num_lanes),
        signals=signals,
        sdc_index=num_agents - 1,
        tracks_to_predict=np.arange(min(3, num_agents - 1), dtype=np.int64),
        predict_difficulty=np.ones(min(3, num_agents - 1), np.int8),
        objects_of_interest=np.zeros(0, np.int64),
    ).validate()


def noisy_rollouts(
    scenario: Scenario,
    num_rollouts: int = NUM_ROLLOUTS,
    noise_std: float = 0.1,
    seed: int = 0,
) -> Rollouts:
    """The logged future plus cumulative Gaussian position noise (m per step), per rollout."""
    log = log_replay_rollouts(scenario, num_rollouts)
    gen = torch.Generator().manual_seed(seed)
    shape = (num_rollouts, log.num_objects, NUM_FUTURE)

    def walk() -> torch.Tensor:
        return torch.cumsum(torch.randn(shape, generator=gen) * noise_std, dim=-1)

    return Rollouts(
        scenario_id=log.scenario_id,
        object_id=log.object_id,
        x=log.x + walk(),
        y=log.y + walk(),
        z=log.z,
        heading=log.heading,
    )
