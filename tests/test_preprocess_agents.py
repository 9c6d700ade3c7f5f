"""Agent attributes and gap filling (docs/model.md §1.4)."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from tbsim_env.core.constants import DT
from tbsim_env.data.preprocess import fill_gaps, mean_size, signed_speed
from tbsim_env.data.preprocess.agents import unwrap_valid
from tbsim_env.data.scenario import wrap_angle_np


def test_signed_speed_sign_follows_heading():
    vel = np.array([[3.0, 4.0], [-3.0, -4.0], [0.0, 0.0], [0.0, 2.0]])
    heading = np.array([np.arctan2(4, 3)] * 3 + [0.0])
    np.testing.assert_allclose(signed_speed(vel, heading), [5.0, -5.0, 0.0, 0.0], atol=1e-12)


def test_mean_size_over_valid_steps_only():
    size = np.array([[[4.0, 2.0, 1.5], [6.0, 2.0, 1.5], [99.0, 99.0, 99.0]]])
    valid = np.array([[True, True, False]])
    np.testing.assert_allclose(mean_size(size, valid), [[5.0, 2.0, 1.5]])
    np.testing.assert_allclose(mean_size(size, np.zeros((1, 3), bool)), [[0.0, 0.0, 0.0]])


def test_unwrap_valid_crosses_pi_and_gaps():
    yaw = np.array([[0.0, 3.0, -3.0, 0.0, 3.1, 0.0]])
    valid = np.array([[False, True, True, False, True, False]])
    got = unwrap_valid(yaw, valid)
    two_pi = 2 * np.pi
    np.testing.assert_allclose(got[0, [1, 2, 4]], [3.0, two_pi - 3.0, 3.1])


def test_fill_gaps_interpolates_and_differentiates():
    t_len = 8
    valid = np.zeros((1, t_len), bool)
    valid[0, [1, 2, 5]] = True
    pos = np.zeros((1, t_len, 3))
    pos[0, [1, 2, 5], 0] = [0.0, 1.0, 4.0]
    vel = np.zeros((1, t_len, 2))
    vel[0, [1, 2, 5], 0] = [10.0, 10.0, 13.0]
    speed = vel[..., 0].copy()
    yaw = np.zeros((1, t_len))
    yaw[0, [1, 2, 5]] = [3.0, -3.0, -2.7]  # crosses +-pi
    s = fill_gaps(valid, pos, vel, speed, yaw)
    np.testing.assert_array_equal(s.valid[0], [0, 1, 1, 1, 1, 1, 0, 0])
    np.testing.assert_allclose(s.pos[0, 1:6, 0], [0, 1, 2, 3, 4])
    np.testing.assert_allclose(s.speed[0, 1:6], [10, 10, 11, 12, 13])
    np.testing.assert_allclose(s.accel[0], [0, 0, 0, 10, 10, 10, 0, 0], atol=1e-9)
    y2 = 2 * np.pi - 3.0
    np.testing.assert_allclose(s.yaw[0, 2:6], y2 + np.arange(4) * 0.1, atol=1e-9)
    np.testing.assert_allclose(s.yaw_rate[0, 3:6], 1.0, atol=1e-9)
    np.testing.assert_allclose(s.yaw_rate[0, 2], (y2 - 3.0) / DT, atol=1e-9)
    assert s.yaw_rate[0, 1] == 0.0 and s.accel[0, 1] == 0.0
    assert (s.pos[0, [0, 6, 7]] == 0).all()


def test_fill_gaps_single_and_no_valid_step():
    valid = np.array([[False, True, False], [False, False, False]])
    pos = np.ones((2, 3, 3))
    s = fill_gaps(valid, pos, np.ones((2, 3, 2)), np.ones((2, 3)), np.ones((2, 3)))
    np.testing.assert_array_equal(s.valid, valid)
    np.testing.assert_allclose(s.pos[0, 1], 1.0)
    assert (s.accel == 0).all() and (s.yaw_rate == 0).all()
    assert (s.pos[1] == 0).all()


@settings(max_examples=60, deadline=None)
@given(
    mask=st.lists(st.lists(st.booleans(), min_size=12, max_size=12), min_size=1, max_size=5),
    seed=st.integers(0, 2**16),
)
def test_fill_gaps_properties(mask, seed):
    valid = np.array(mask, bool)
    n, t_len = valid.shape
    rng = np.random.default_rng(seed)
    pos = rng.normal(size=(n, t_len, 3)) * 10
    vel = rng.normal(size=(n, t_len, 2))
    speed = rng.normal(size=(n, t_len))
    yaw = rng.uniform(-np.pi, np.pi, size=(n, t_len))
    s = fill_gaps(valid, pos, vel, speed, yaw)
    for a in range(n):
        idx = np.flatnonzero(valid[a])
        expect = np.zeros(t_len, bool)
        if idx.size:
            expect[idx[0] : idx[-1] + 1] = True
        np.testing.assert_array_equal(s.valid[a], expect)  # one contiguous interval
    np.testing.assert_allclose(s.pos[valid], pos[valid])
    np.testing.assert_allclose(s.vel[valid], vel[valid])
    np.testing.assert_allclose(s.speed[valid], speed[valid])
    np.testing.assert_allclose(wrap_angle_np(s.yaw[valid] - yaw[valid]), 0.0, atol=1e-9)
    # The unwrapped yaw never jumps by more than pi between consecutive filled steps.
    both = s.valid[:, 1:] & s.valid[:, :-1]
    assert (np.abs(np.diff(s.yaw, axis=1))[both] <= np.pi + 1e-9).all()
    # Differences integrate back: speed[t] = speed[first] + cumsum(acc) * DT.
    for a in range(n):
        if s.valid[a].any():
            first = np.argmax(s.valid[a])
            rebuilt = s.speed[a, first] + np.cumsum(s.accel[a]) * DT
            np.testing.assert_allclose(rebuilt[s.valid[a]], s.speed[a, s.valid[a]], atol=1e-9)
    assert (s.accel[~s.valid] == 0).all() and (s.yaw_rate[~s.valid] == 0).all()
