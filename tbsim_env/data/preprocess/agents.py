"""Agent attributes and gap filling (TrafficBots V1.5, docs/model.md §1.4)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tbsim_env.core.constants import DT
from tbsim_env.data.scenario import Tracks, wrap_angle_np


@dataclass(frozen=True)
class AgentStates:
    """Per-step agent states after gap filling, N agents over T steps.

    Attributes:
        valid: [N, T] bool, one contiguous interval per agent (first..last valid step).
        pos: [N, T, 3] float64 metres.
        vel: [N, T, 2] float64 m/s.
        speed: [N, T] float64 signed speed, m/s.
        yaw: [N, T] float64 unwrapped yaw, radians.
        accel: [N, T] float64 m/s^2, (speed[t] - speed[t-1]) / DT, 0 at the first valid step.
        yaw_rate: [N, T] float64 rad/s, (yaw[t] - yaw[t-1]) / DT, 0 at the first valid step.
    """

    valid: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    speed: np.ndarray
    yaw: np.ndarray
    accel: np.ndarray
    yaw_rate: np.ndarray


@dataclass(frozen=True)
class AgentAttributes:
    """Static attributes and filled states of selected agents.

    Attributes:
        track_index: [N] int64 row in ``Scenario.tracks``.
        object_type: [N] int64 ``ObjectType`` value.
        size: [N, 3] float64 mean (length, width, height) over valid steps, metres.
        states: the gap-filled per-step states (positions shifted by the origin).
    """

    track_index: np.ndarray
    object_type: np.ndarray
    size: np.ndarray
    states: AgentStates


def signed_speed(velocity: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """Speed with the sign of the velocity's projection on the heading.

    Args:
        velocity: [..., 2] (vx, vy) m/s.
        heading: [...] yaw, radians.

    Returns:
        [...] float64 m/s: sign(cos(psi) vx + sin(psi) vy) * |v| (0 when the projection is 0).
    """
    velocity = np.asarray(velocity, np.float64)
    heading = np.asarray(heading, np.float64)
    along = np.cos(heading) * velocity[..., 0] + np.sin(heading) * velocity[..., 1]
    return np.sign(along) * np.linalg.norm(velocity, axis=-1)


def mean_size(size: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Mean (length, width, height) over valid steps.

    Args:
        size: [N, T, 3] metres.
        valid: [N, T] bool.

    Returns:
        [N, 3] float64, 0 for agents never valid.
    """
    count = valid.sum(axis=1)[:, None]
    total = np.where(valid[..., None], size, 0.0).sum(axis=1)
    return total / np.maximum(count, 1)


def unwrap_valid(yaw: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Unwrap yaw along time over the valid steps only (gaps are bridged by the shortest turn).

    Args:
        yaw: [N, T] radians.
        valid: [N, T] bool.

    Returns:
        [N, T] float64: at valid steps a continuous yaw equal to ``yaw`` modulo 2 pi, starting at
        the first valid value; at invalid steps the value of the previous valid step (or the
        first valid value before it).
    """
    yaw = np.asarray(yaw, np.float64)
    steps = np.arange(yaw.shape[1])
    prev = np.maximum.accumulate(np.where(valid, steps, -1), axis=1)
    prev_strict = np.concatenate([np.full((yaw.shape[0], 1), -1), prev[:, :-1]], axis=1)
    rows = np.arange(yaw.shape[0])[:, None]
    has_prev = valid & (prev_strict >= 0)
    delta = np.where(has_prev, wrap_angle_np(yaw - yaw[rows, np.maximum(prev_strict, 0)]), 0.0)
    first = np.argmax(valid, axis=1)
    return yaw[np.arange(yaw.shape[0]), first][:, None] + np.cumsum(delta, axis=1)


def _interpolate(values: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Linear interpolation in time between steps ``lo`` and ``hi``.

    Args:
        values: [N, T, D] float64.
        lo: [N, T] int64 previous valid step (<= t).
        hi: [N, T] int64 next valid step (>= t).

    Returns:
        [N, T, D] float64.
    """
    rows = np.arange(values.shape[0])[:, None]
    t = np.arange(values.shape[1])[None, :]
    span = np.maximum(hi - lo, 1)
    w = ((t - lo) / span)[..., None]
    return values[rows, lo] * (1.0 - w) + values[rows, hi] * w


def fill_gaps(
    valid: np.ndarray,
    pos: np.ndarray,
    vel: np.ndarray,
    speed: np.ndarray,
    yaw: np.ndarray,
    dt: float = DT,
) -> AgentStates:
    """Linear gap filling between the first and last valid step, then acc and yaw rate.

    pos, vel, speed and the *unwrapped* yaw are interpolated over invalid steps inside each
    agent's valid interval; outside it everything is 0 and invalid (docs/model.md §1.4). Agents with
    a single valid step are copied with acc = yaw_rate = 0.

    Args:
        valid: [N, T] bool.
        pos: [N, T, 3] metres.
        vel: [N, T, 2] m/s.
        speed: [N, T] signed speed, m/s.
        yaw: [N, T] radians (any wrapping).
        dt: step in seconds.

    Returns:
        The filled states.
    """
    valid = np.asarray(valid, bool)
    n, t_len = valid.shape
    steps = np.arange(t_len)
    any_valid = valid.any(axis=1)
    first = np.where(any_valid, np.argmax(valid, axis=1), t_len)
    last = np.where(any_valid, t_len - 1 - np.argmax(valid[:, ::-1], axis=1), -1)
    inside = (steps[None] >= first[:, None]) & (steps[None] <= last[:, None])
    lo = np.maximum.accumulate(np.where(valid, steps, 0), axis=1)
    hi_src = np.where(valid, steps, t_len - 1)
    hi = np.minimum.accumulate(hi_src[:, ::-1], axis=1)[:, ::-1]
    lo, hi = np.where(inside, lo, 0), np.where(inside, hi, 0)
    stacked = np.concatenate(
        [
            np.asarray(pos, np.float64),
            np.asarray(vel, np.float64),
            np.asarray(speed, np.float64)[..., None],
            unwrap_valid(yaw, valid)[..., None],
        ],
        axis=-1,
    )
    filled = np.where(inside[..., None], _interpolate(stacked, lo, hi), 0.0)
    f_speed, f_yaw = filled[..., 5], filled[..., 6]
    both = inside[:, 1:] & inside[:, :-1]
    accel = np.zeros((n, t_len))
    yaw_rate = np.zeros((n, t_len))
    accel[:, 1:] = np.where(both, (f_speed[:, 1:] - f_speed[:, :-1]) / dt, 0.0)
    yaw_rate[:, 1:] = np.where(both, (f_yaw[:, 1:] - f_yaw[:, :-1]) / dt, 0.0)
    return AgentStates(
        valid=inside,
        pos=filled[..., 0:3],
        vel=filled[..., 3:5],
        speed=f_speed,
        yaw=f_yaw,
        accel=accel,
        yaw_rate=yaw_rate,
    )


def agent_attributes(
    tracks: Tracks, track_index: np.ndarray, origin: np.ndarray
) -> AgentAttributes:
    """Type, mean size and gap-filled states of the given tracks, positions shifted by origin.

    Args:
        tracks: all tracks of the scenario (file coordinates).
        track_index: [N] int64 rows to take.
        origin: [2] float64 xy subtracted from positions (metres).

    Returns:
        The agents' attributes in the order of ``track_index``.
    """
    idx = np.asarray(track_index, np.int64)
    valid = tracks.valid[idx]
    heading = tracks.heading[idx].astype(np.float64)
    velocity = tracks.velocity[idx].astype(np.float64)
    shift = np.array([origin[0], origin[1], 0.0], np.float64)
    pos = np.where(valid[..., None], tracks.xyz[idx].astype(np.float64) - shift, 0.0)
    states = fill_gaps(valid, pos, velocity, signed_speed(velocity, heading), heading)
    return AgentAttributes(
        track_index=idx,
        object_type=tracks.object_type[idx].astype(np.int64),
        size=mean_size(tracks.size[idx].astype(np.float64), valid),
        states=states,
    )
