"""The road-keeping rule of the TrafficBots NPC (policies/trafficbots/road_keeping.py)."""

from __future__ import annotations

import math

import pytest
import torch

from policies.trafficbots.config import RoadKeeping
from policies.trafficbots.map_encoder import MapTokens
from policies.trafficbots.road_keeping import front_corner_paths, keep_on_road
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


def _end_corners(pose: torch.Tensor, action: torch.Tensor, t: float = 2.0) -> torch.Tensor:
    """[B, N, 2 corners, 2] where the front corners are after ``t`` s of constant action."""
    return front_corner_paths(pose, SPEED, action[:, :, None], SIZE, t)[1][:, :, 0]


def test_keep_on_road_turns_the_vehicle_heading_for_the_edge_and_leaves_the_others_alone():
    action = torch.tensor([[[1.0, -0.1]] * 5])
    out = keep_on_road(action, SPEED, (POSE, VALID), (TYPE, SIZE, _map()), RoadKeeping())
    assert out[0, 0, 1] > action[0, 0, 1] + 0.1  # turns left, back towards the road (y > 0)
    assert out[0, 0, 0] <= action[0, 0, 0]  # and slows, if at all
    before, after = _end_corners(POSE, action), _end_corners(POSE, out)
    assert after[0, 0, :, 1].min() > before[0, 0, :, 1].min()  # its corners end further in
    # Along the road 6 m in, from the lot onto the road, a pedestrian, a slow vehicle.
    assert torch.equal(out[0, 1:], action[0, 1:])


def test_keep_on_road_brakes_a_vehicle_heading_straight_at_the_edge():
    pose = torch.tensor([[[0.0, 4.5, -math.pi / 2]]])  # square to the edge, 2.25 m from it
    out = keep_on_road(
        torch.tensor([[[0.5, 0.0]]]),
        torch.tensor([[12.0]]),
        (pose, torch.ones(1, 1, dtype=torch.bool)),
        (torch.tensor([[VEH]]), SIZE[:, :1], _map()),
        RoadKeeping(),
    )
    assert torch.isclose(out[0, 0, 0], torch.tensor(0.5 - 5.0))  # less the full braking limit
    assert abs(float(out[0, 0, 1])) < 0.01  # no side to turn to


def test_keep_on_road_acts_continuously_so_rounding_cannot_tip_it():
    """The action moves by about as much as the state: a 1e-4 m / 1e-5 rad nudge (rounding in
    another world frame) changes it by far less than a threshold rule's jump (0.05 rad/s)."""
    action = torch.tensor([[[1.0, -0.1]] * 5])
    rule = RoadKeeping()
    out = keep_on_road(action, SPEED, (POSE, VALID), (TYPE, SIZE, _map()), rule)
    for nudge in ((1e-4, 0.0, 0.0), (0.0, -1e-4, 0.0), (0.0, 0.0, 1e-5)):
        pose = POSE + torch.tensor(nudge)
        moved = keep_on_road(action, SPEED, (pose, VALID), (TYPE, SIZE, _map()), rule)
        assert (moved - out).abs().max() < 1e-3, nudge


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
    with pytest.raises(ValueError, match="horizon"):
        RoadKeeping(horizon=0.0)
    with pytest.raises(ValueError, match="margin"):
        RoadKeeping(margin=0.0)
    assert RoadKeeping.parse("off") is None
    assert RoadKeeping.parse("horizon=1.5,max_offset=0.2") == RoadKeeping(
        horizon=1.5, max_offset=0.2
    )
