"""The one box-corner rule (``tbsim_env.core.boxes``): geometry, order, and every user of it."""

from __future__ import annotations

import math

import numpy as np
import torch

from tbsim_env.core.boxes import box_corner_xy, box_corners, box_corners_numpy


def test_corners_run_counter_clockwise_from_the_front_left():
    pose = torch.tensor([[10.0, -3.0, math.pi / 2]], dtype=torch.float64)
    c = box_corners(
        pose, torch.tensor([4.0], dtype=torch.float64), torch.tensor([2.0], dtype=torch.float64)
    )
    # Heading +y: front-left is (x - 1, y + 2), then rear-left, rear-right, front-right.
    want = [[9.0, -1.0], [9.0, -5.0], [11.0, -5.0], [11.0, -1.0]]
    torch.testing.assert_close(c[0], torch.tensor(want, dtype=torch.float64), atol=1e-12, rtol=0)
    # Counter-clockwise: positive signed area (shoelace), equal to length x width.
    x, y = c[0, :, 0], c[0, :, 1]
    area = 0.5 * float((x * y.roll(-1) - x.roll(-1) * y).sum())
    assert abs(area - 8.0) < 1e-9


def test_corners_are_the_box_under_a_rigid_motion():
    gen = torch.Generator().manual_seed(0)
    pose = torch.rand(64, 3, generator=gen, dtype=torch.float64) * torch.tensor([200.0, 200.0, 7.0])
    length = 1.0 + 5.0 * torch.rand(64, generator=gen, dtype=torch.float64)
    width = 0.5 + 2.0 * torch.rand(64, generator=gen, dtype=torch.float64)
    c = box_corners(pose, length, width)
    side = (c.roll(-1, dims=-2) - c).norm(dim=-1)  # [64, 4]: left, rear, right, front edges
    torch.testing.assert_close(side[:, 0::2], length[:, None].expand(-1, 2), atol=1e-9, rtol=0)
    torch.testing.assert_close(side[:, 1::2], width[:, None].expand(-1, 2), atol=1e-9, rtol=0)
    torch.testing.assert_close(c.mean(-2), pose[:, :2], atol=1e-9, rtol=0)
    x, y = box_corner_xy(pose, length, width)
    assert torch.equal(torch.stack([x, y], -1), c)


def test_numpy_boxes_take_the_same_rule():
    xy = np.array([[1.0, 2.0], [-5.0, 0.5]])
    yaw = np.array([0.3, -2.0])
    size = np.array([[4.5, 2.0], [0.8, 0.8]])
    got = box_corners_numpy(xy, yaw, size[:, 0], size[:, 1])
    pose = torch.from_numpy(np.concatenate([xy, yaw[:, None]], 1))
    want = box_corners(pose, torch.from_numpy(size[:, 0]), torch.from_numpy(size[:, 1])).numpy()
    assert got.shape == (2, 4, 2) and got.dtype == np.float64
    np.testing.assert_allclose(got, want, atol=1e-12)
    one = box_corners_numpy(xy[0], np.float64(yaw[0]), size[0, 0], size[0, 1])
    np.testing.assert_allclose(one, want[0], atol=1e-12)
