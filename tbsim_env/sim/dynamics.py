"""Unicycle dynamics: the one source of truth for how agents move (docs/model.md §4).

State per agent: pose (x m, y m, yaw rad) and signed speed v (m/s). Action: acceleration a (m/s^2)
and yaw rate w (rad/s), bounded per object type by ``constants.MAX_ACCEL`` / ``MAX_YAW_RATE``.
Midpoint integration with step ``dt``::

    v_mid = v + dt/2 * a          yaw_mid = yaw + dt/2 * w
    x' = x + dt * v_mid * cos(yaw_mid)      y' = y + dt * v_mid * sin(yaw_mid)
    yaw' = yaw + dt * w           v' = v + dt * a

There is no speed limit and reverse speeds are allowed, as in the spec. Yaw is wrapped to
[-pi, pi) after each step (the spec leaves it unwrapped; wrapping changes nothing downstream
because every consumer uses sin/cos or wrapped differences, and it keeps float32 precise).

All functions are pure, batched over any leading shape ``[...]`` and differentiable (the policy's
training back-propagates through ``unicycle_step``).
"""

from __future__ import annotations

import torch

from tbsim_env.core import constants as C
from tbsim_env.core.torch_utils import const
from tbsim_env.sim.geometry import cos_sin, wrap_angle


def action_limits(object_type: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-agent action bounds.

    Args:
        object_type: [...] int, ``ObjectType`` values.

    Returns:
        (max_accel [...] m/s^2, max_yaw_rate [...] rad/s), float32 on the input's device.
    """
    idx = object_type.long().clamp(0, C.NUM_OBJECT_TYPES - 1)
    table = _limit_table(object_type.device)
    return table[0][idx], table[1][idx]


_LIMIT_TABLES: dict[torch.device, torch.Tensor] = {}


def _limit_table(device: torch.device) -> torch.Tensor:
    """[2, NUM_OBJECT_TYPES] (max accel, max yaw rate), cached per device (built once)."""
    if device not in _LIMIT_TABLES:
        _LIMIT_TABLES[device] = torch.tensor(
            [C.MAX_ACCEL, C.MAX_YAW_RATE], dtype=torch.float32, device=device
        )
    return _LIMIT_TABLES[device]


def clip_action(action: torch.Tensor, object_type: torch.Tensor) -> torch.Tensor:
    """Clip physical actions to the type limits.

    Args:
        action: [..., 2] (acceleration m/s^2, yaw rate rad/s).
        object_type: [...] ``ObjectType`` values.

    Returns:
        [..., 2] clipped action.
    """
    max_acc, max_yaw = action_limits(object_type)
    limit = torch.stack([max_acc, max_yaw], dim=-1).to(action.dtype)
    return torch.maximum(torch.minimum(action, limit), -limit)


def squash_action(raw: torch.Tensor, object_type: torch.Tensor) -> torch.Tensor:
    """Map an unbounded policy output to a physical action: ``limit * tanh(raw)``.

    Args:
        raw: [..., 2] unbounded (u_acc, u_yaw).
        object_type: [...] ``ObjectType`` values.

    Returns:
        [..., 2] (acceleration m/s^2, yaw rate rad/s) inside the limits.
    """
    max_acc, max_yaw = action_limits(object_type)
    limit = torch.stack([max_acc, max_yaw], dim=-1).to(raw.dtype)
    return limit * torch.tanh(raw)


def unicycle_planes(
    pose: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    speed: torch.Tensor,
    action: tuple[torch.Tensor, torch.Tensor],
    dt: float = C.DT,
) -> tuple[torch.Tensor, ...]:
    """``unicycle_step`` on separate components, each [...]: (x, y, yaw) m, m, rad, signed
    speed m/s, (acceleration m/s^2, yaw rate rad/s) -> (x', y', yaw' wrapped, speed').

    The one implementation of the rule: a caller that merges the new pose with others by
    component (``sim.core.step``) skips interleaving it into [..., 3] first."""
    x, y, yaw = pose
    acc, yaw_rate = action
    half_dt, dt_ = const(0.5 * dt, speed), const(dt, speed)
    v_mid = speed + half_dt * acc
    c, s = cos_sin(yaw + half_dt * yaw_rate)
    step = dt_ * v_mid
    return x + step * c, y + step * s, wrap_angle(yaw + dt_ * yaw_rate), speed + dt_ * acc


def unicycle_step(
    pose: torch.Tensor, speed: torch.Tensor, action: torch.Tensor, dt: float = C.DT
) -> tuple[torch.Tensor, torch.Tensor]:
    """Advance the unicycle by one step (midpoint integration).

    Args:
        pose: [..., 3] (x m, y m, yaw rad).
        speed: [...] signed speed m/s.
        action: [..., 2] (acceleration m/s^2, yaw rate rad/s); not clipped here.
        dt: step in seconds.

    Returns:
        (pose' [..., 3] with wrapped yaw, speed' [...]).
    """
    *xy_yaw, next_speed = unicycle_planes(pose.unbind(-1), speed, action.unbind(-1), dt)
    return torch.stack(xy_yaw, dim=-1), next_speed


def signed_speed(velocity: torch.Tensor, yaw: torch.Tensor) -> torch.Tensor:
    """Signed speed: ``sign(cos(yaw) vx + sin(yaw) vy) * |v|`` (docs/model.md §1.4).

    Args:
        velocity: [..., 2] (vx, vy) m/s.
        yaw: [...] rad.

    Returns:
        [...] m/s, negative when moving backwards.
    """
    c, s = cos_sin(yaw)
    along = c * velocity[..., 0] + s * velocity[..., 1]
    sign = torch.where(along < 0, -1.0, 1.0).to(velocity.dtype)
    return sign * torch.linalg.vector_norm(velocity, dim=-1)


def inverse_step(
    pose: torch.Tensor,
    speed: torch.Tensor,
    target_pose: torch.Tensor,
    target_speed: torch.Tensor,
    max_accel: torch.Tensor,
    max_yaw_rate: torch.Tensor,
    dt: float = C.DT,
    position_gain: float = 0.5,
) -> torch.Tensor:
    """One step of inverse dynamics: the action that moves a state towards a target state.

    The yaw rate closes the yaw gap; the acceleration reaches the target speed plus
    ``position_gain`` times the along-track position error of that feed-forward step.

    Args:
        pose: [..., 3] current (x, y, yaw); speed: [...] current signed speed m/s.
        target_pose: [..., 3] pose to reach after ``dt``; target_speed: [...] m/s.
        max_accel: [...] m/s^2; max_yaw_rate: [...] rad/s (limits, see ``action_limits``).
        dt: step in seconds.
        position_gain: fraction of the along-track position error corrected.

    Returns:
        [..., 2] (acceleration, yaw rate), within the limits.
    """
    yaw_rate = (wrap_angle(target_pose[..., 2] - pose[..., 2]) / dt).clamp(
        -max_yaw_rate, max_yaw_rate
    )
    yaw_mid = pose[..., 2] + 0.5 * dt * yaw_rate
    heading = torch.stack(cos_sin(yaw_mid), dim=-1)
    acc = (target_speed - speed) / dt
    v_mid = speed + 0.5 * dt * acc
    pred_xy = pose[..., :2] + dt * v_mid[..., None] * heading
    err = ((target_pose[..., :2] - pred_xy) * heading).sum(-1)
    acc = (acc + position_gain * 2.0 * err / dt**2).clamp(-max_accel, max_accel)
    return torch.stack([acc, yaw_rate], dim=-1)


def inverse_unicycle(
    pose: torch.Tensor,
    speed: torch.Tensor,
    valid: torch.Tensor,
    object_type: torch.Tensor,
    dt: float = C.DT,
    position_gain: float = 0.5,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Expert actions that make ``unicycle_step`` track a logged trajectory.

    The inverse runs the forward model in closed loop along the log (a loop over the T-1
    steps, batched over everything else): at each step the yaw rate closes the yaw gap to the
    next logged yaw, and the acceleration reaches the next logged speed plus a correction of
    ``position_gain`` times the along-track position error. The simulated state restarts from
    the log after every gap, exactly as ``rollout_from_log`` does, so that
    ``rollout_from_log(log, inverse_unicycle(log))`` reproduces the log wherever the log is
    dynamically feasible under the limits (on real WOMD vehicle logs: centimetres).

    Args:
        pose: [..., T, 3] logged (x m, y m, yaw rad).
        speed: [..., T] logged signed speed m/s (``signed_speed`` of the logged velocity).
        valid: [..., T] bool.
        object_type: [...] ``ObjectType`` values (for the limits).
        dt: step in seconds.
        position_gain: fraction of the along-track position error corrected per step.

    Returns:
        (action [..., T-1, 2] clipped to the limits, action_valid [..., T-1] bool: both t and
        t+1 valid). Invalid actions are zero.
    """
    n_t = pose.shape[-2]
    max_acc, max_yaw = action_limits(object_type)
    max_acc, max_yaw = max_acc.to(pose.dtype), max_yaw.to(pose.dtype)
    cur_pose, cur_speed = pose[..., 0, :], speed[..., 0]
    actions = []
    for t in range(n_t - 1):
        # Restart from the log where the previous step was not simulated.
        restart = valid[..., t] & ~(valid[..., t - 1] if t > 0 else torch.zeros_like(valid[..., 0]))
        cur_pose = torch.where(restart[..., None], pose[..., t, :], cur_pose)
        cur_speed = torch.where(restart, speed[..., t], cur_speed)
        action = inverse_step(
            cur_pose,
            cur_speed,
            pose[..., t + 1, :],
            speed[..., t + 1],
            max_acc,
            max_yaw,
            dt,
            position_gain,
        )
        step_valid = valid[..., t] & valid[..., t + 1]
        action = action * step_valid[..., None]
        actions.append(action)
        cur_pose, cur_speed = unicycle_step(cur_pose, cur_speed, action, dt)
    return torch.stack(actions, dim=-2), valid[..., :-1] & valid[..., 1:]


def rollout_from_log(
    pose: torch.Tensor,
    speed: torch.Tensor,
    valid: torch.Tensor,
    action: torch.Tensor,
    dt: float = C.DT,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Integrate actions from the logged initial state, restarting from the log after gaps.

    Args:
        pose: [..., T, 3] logged poses (only used at the first valid step of each segment).
        speed: [..., T] logged signed speeds (same).
        valid: [..., T] bool.
        action: [..., T-1, 2] actions (acceleration, yaw rate).
        dt: step in seconds.

    Returns:
        (pose [..., T, 3], speed [..., T]) simulated; entries at invalid steps are zero.
    """
    n_t = pose.shape[-2]
    cur_pose, cur_speed = pose[..., 0, :], speed[..., 0]
    poses, speeds = [], []
    for t in range(n_t):
        restart = valid[..., t] & ~(valid[..., t - 1] if t > 0 else torch.zeros_like(valid[..., 0]))
        cur_pose = torch.where(restart[..., None], pose[..., t, :], cur_pose)
        cur_speed = torch.where(restart, speed[..., t], cur_speed)
        poses.append(cur_pose)
        speeds.append(cur_speed)
        if t < n_t - 1:
            cur_pose, cur_speed = unicycle_step(cur_pose, cur_speed, action[..., t, :], dt)
    out_pose = torch.stack(poses, dim=-2) * valid[..., None]
    out_speed = torch.stack(speeds, dim=-1) * valid
    return out_pose, out_speed
