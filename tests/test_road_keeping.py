"""The road-keeping rule of the TrafficBots NPC (policies/trafficbots/road_keeping.py)."""

from __future__ import annotations

import math

import pytest
import torch

from policies.trafficbots.config import RoadKeeping
from policies.trafficbots.map_encoder import MapTokens
from policies.trafficbots.road_keeping import (
    front_corner_paths,
    keep_on_road,
    leaves_road,
    nearest_edge_segments,
)
from tbsim_env.core import constants as C

pytestmark = [pytest.mark.usefixtures("torch_one_thread"), pytest.mark.float_sensitive]

VEH, PED = int(C.ObjectType.VEHICLE), int(C.ObjectType.PEDESTRIAN)
EDGE, LANE = int(C.MapClass.ROAD_EDGE_BOUNDARY), int(C.MapClass.SURFACE_STREET)


def _map(angle: float = 0.0, shift: tuple[float, float] = (0.0, 0.0)) -> MapTokens:
    """A road edge along the x axis from x = -50 to 50 (pointing +x: the road is y > 0) in
    five 20-node pieces, and a lane along y = 3 that the rule must ignore; the whole world
    rotated by ``angle`` and shifted by ``shift``."""
    xs = torch.linspace(-50.0, 50.0, 96)
    pieces = []
    for y, n in ((0.0, 5), (3.0, 5)):
        for i in range(n):
            seg = xs[i * 19 : i * 19 + 20]
            pieces.append(torch.stack([seg, torch.full_like(seg, y), torch.zeros_like(seg)], -1))
    pose = _moved(torch.stack(pieces)[None], angle, shift)  # [1, 10, 20, 3]
    cls = torch.tensor([[EDGE] * 5 + [LANE] * 5])
    valid = torch.ones(1, 10, 20, dtype=torch.bool)
    return MapTokens(
        feat=torch.zeros(1, 10, 8),
        pose=pose[:, :, 0],
        valid=valid[..., 0],
        node_pose=pose,
        node_valid=valid,
        cls=cls,
    )


def _moved(pose: torch.Tensor, angle: float, shift: tuple[float, float]) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    x, y, yaw = pose.unbind(-1)
    return torch.stack([c * x - s * y + shift[0], s * x + c * y + shift[1], yaw + angle], -1)


# Vehicles: heading for the edge from the road; along the road; from the lot onto the road;
# a pedestrian heading for the edge; a slow vehicle heading for it.
POSE = torch.tensor([[[0.0, 2.6, -0.15], [0.0, 6.0, 0.0], [10.0, -4.0, 0.6], [20.0, 2.0, -1.2],
                      [-20.0, 2.5, -0.6]]])  # fmt: skip
SPEED = torch.tensor([[10.0, 10.0, 8.0, 1.5, 0.5]])
TYPE = torch.tensor([[VEH, VEH, VEH, PED, VEH]])
SIZE = torch.tensor([[4.5, 2.0]]).expand(1, 5, 2)
VALID = torch.ones(1, 5, dtype=torch.bool)


def _leaving(pose: torch.Tensor, mp: MapTokens, action: torch.Tensor) -> torch.Tensor:
    now, then = front_corner_paths(pose, SPEED, action[:, :, None], SIZE, 1.0)
    mid = front_corner_paths(pose, SPEED, action[:, :, None], SIZE, 0.5)[1][:, :, 0].mean(-2)
    return leaves_road(now, then, nearest_edge_segments(mp, mid, 8))[..., 0]


def test_only_a_path_from_the_road_across_an_edge_leaves_it():
    zero = torch.zeros(1, 5, 2)
    assert _leaving(POSE, _map(), zero).tolist() == [[True, False, False, True, False]]


def test_keep_on_road_steers_the_leaving_vehicle_back_and_leaves_the_others_alone():
    action = torch.tensor([[[1.0, -0.1]] * 5])
    out = keep_on_road(action, SPEED, (POSE, VALID), (TYPE, SIZE, _map()), RoadKeeping())
    assert out[0, 0, 1] > action[0, 0, 1]  # turns left, away from the edge
    assert out[0, 0, 0] == action[0, 0, 0]
    assert not _leaving(POSE, _map(), out)[0, 0]
    assert torch.equal(out[0, 1:], action[0, 1:])  # along the road, entering, pedestrian, slow


def test_keep_on_road_brakes_when_no_yaw_rate_keeps_the_vehicle_in():
    pose = torch.tensor([[[0.0, 4.5, -1.2]]])  # steeply at the edge, its corners 2-2.8 m away
    out = keep_on_road(
        torch.tensor([[[0.5, 0.0]]]),
        torch.tensor([[12.0]]),
        (pose, torch.ones(1, 1, dtype=torch.bool)),
        (torch.tensor([[VEH]]), SIZE[:, :1], _map()),
        RoadKeeping(yaw_offsets=(0.05,)),
    )
    assert out[0, 0].tolist() == [-5.0, 0.0]  # the vehicle's braking limit, heading kept


def test_road_keeping_is_invariant_to_a_rigid_motion_of_the_world():
    action = torch.tensor([[[1.0, -0.1], [0.0, 0.0], [2.0, 0.3], [0.0, 0.0], [0.0, -0.2]]])
    rule = RoadKeeping()
    out = keep_on_road(action, SPEED, (POSE, VALID), (TYPE, SIZE, _map()), rule)
    moved = _moved(POSE, 2.2, (4000.0, -2500.0))
    out2 = keep_on_road(
        action, SPEED, (moved, VALID), (TYPE, SIZE, _map(2.2, (4000.0, -2500.0))), rule
    )
    assert torch.allclose(out, out2)


def test_road_keeping_parameters_are_checked_and_parsed():
    with pytest.raises(ValueError):
        RoadKeeping(horizon=0.0)
    with pytest.raises(ValueError):
        RoadKeeping(yaw_offsets=())
    assert RoadKeeping.parse("off") is None
    assert RoadKeeping.parse("horizon=1.5,yaw_offsets=0.1/0.3") == RoadKeeping(
        horizon=1.5, yaw_offsets=(0.1, 0.3)
    )
