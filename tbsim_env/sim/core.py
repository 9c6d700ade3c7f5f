"""One batched simulation step: controlled agents integrate actions, the others replay the log.

Controller assignment is a mask (``SimState.controlled``); the caller merges the actions of
external controllers and policies into one ``[B, N, 2]`` tensor beforehand (see
``merge_actions``), so a step is a handful of tensor operations whatever the mix.
"""

from __future__ import annotations

import torch

from tbsim_env.core import constants as C
from tbsim_env.core.torch_utils import (
    const,
    gather_rows,
    scalar,
    select_rows,
    where_into,
)
from tbsim_env.sim.dynamics import unicycle_planes, unicycle_step
from tbsim_env.sim.state import SimState


def merge_actions(*pairs: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """Merge actions of several controllers by mask; later pairs win where masks overlap.

    Args:
        pairs: (mask [B, N] bool, action [B, N, 2]) per controller.

    Returns:
        [B, N, 2] merged action (zero where no mask is set).

    From ``COMPONENT_MERGE_MIN_SLOTS`` slots on, merged a component at a time
    (``where_into``); below, by [B, N, 1] masks (fewer operations).
    """
    first = pairs[0][1]
    if first.numel() // first.shape[-1] < C.COMPONENT_MERGE_MIN_SLOTS:
        out = const(0.0, first)
        for mask, action in pairs:
            out = torch.where(mask.unsqueeze(-1), action, out)
        return out
    out = torch.empty(first.shape, dtype=first.dtype, device=first.device)
    for k in range(first.shape[-1]):
        plane = scalar(0.0, first.dtype, first.device)
        for mask, action in pairs[:-1]:
            plane = torch.where(mask, action[..., k], plane)
        mask, action = pairs[-1]
        where_into(out[..., k], mask, action[..., k], plane)
    return out


def seen_before(state: SimState) -> torch.Tensor:
    """[B, N] bool: the agent was valid in the log at some step <= the current one."""
    return state.log.first_valid <= state.step[:, None]


def step(state: SimState, action: torch.Tensor, movers: torch.Tensor | None = None) -> SimState:
    """Advance every scenario of the batch by one step.

    * Controlled agents that are present move by the unicycle with the action clipped to their
      type limits. A controlled agent that has not appeared yet spawns from the log when the log
      first shows it; once present it stays present (as in TrafficBots) until the caller removes
      it by clearing ``valid``.
    * Other agents take the logged state of the next step. An agent that disappears from the log
      leaves for good, even if the log shows it again later.

    Args:
        state: current state (``step`` < T - 1 for every scenario).
        action: [B, N, 2] (acceleration m/s^2, yaw rate rad/s), finite; only read where
            ``state.controlled``.
        movers: optional [B, K] int64 slots that include every controlled slot (repeats
            allowed): on a large batch only these integrate (e.g. the external agents when
            the NPCs replay the log), not every slot.

    Returns:
        The state at ``step + 1``.
    """
    b, n = state.valid.shape
    n_t = state.log.num_steps
    nxt = torch.add(state.step, scalar(1, state.step.dtype, state.device))
    nxt = nxt.clamp_max_(scalar(n_t - 1, nxt.dtype, nxt.device))
    at = _log_at(state, nxt)  # [B, N, 5]
    log_valid = torch.bitwise_and(at[..., 4] > const(0.0, at), state.agents.mask)
    fresh = state.log.first_valid > state.step.view(b, 1)  # not seen_before(state)

    moving = torch.bitwise_and(state.controlled, state.valid)
    # Spawn (controlled, not present, not seen before) or replay (not controlled, present or
    # not seen before) where the log has the agent. For a moving agent ``from_log`` may be
    # anything: ``moving`` wins below. (``valid > controlled`` is ``valid & ~controlled``.)
    from_log = torch.bitwise_and(log_valid, torch.bitwise_or(fresh, state.valid > state.controlled))
    masks = (moving, from_log)
    if b * n < C.COMPONENT_MERGE_MIN_SLOTS:
        pose, speed = _merge_few(state, action, at, masks)
    elif movers is None or b * n <= C.DENSE_DYNAMICS_MAX_SLOTS:
        pose, speed = _merge_dense(state, action, at, masks)
    else:
        pose, speed = _merge_movers(state, action, at, masks, movers)
    return state.replace(step=nxt, pose=pose, speed=speed, valid=torch.bitwise_or(moving, from_log))


def _merge_few(
    state: SimState, action: torch.Tensor, at: torch.Tensor, masks: tuple[torch.Tensor, ...]
) -> tuple[torch.Tensor, torch.Tensor]:
    """``step``'s (pose [B, N, 3], speed [B, N]) of a small batch: every slot integrates (a few
    operations on [B, N]), merged with the log by [B, N, 1] masks (the fewest operations).
    ``at``: ``_log_at`` the next step; ``masks``: (moving, from_log) [B, N] bool."""
    moving, from_log = masks
    b, n = moving.shape
    pose = torch.where(from_log.view(b, n, 1), at[..., :3], state.pose)
    speed = torch.where(from_log, at[..., 3], state.speed)
    limit = state.agents.action_limit
    act = torch.clamp(action, -limit, limit)  # clip_action
    sim_pose, sim_speed = unicycle_step(state.pose, state.speed, act)
    return torch.where(moving.view(b, n, 1), sim_pose, pose), torch.where(moving, sim_speed, speed)


def _merge_dense(
    state: SimState, action: torch.Tensor, at: torch.Tensor, masks: tuple[torch.Tensor, ...]
) -> tuple[torch.Tensor, torch.Tensor]:
    """``_merge_few``'s values on a larger batch (``_merge_planes``)."""
    moving, from_log = masks
    limit = state.agents.action_limit
    act = torch.clamp(action, -limit, limit)  # clip_action
    *sim_pose, sim_speed = unicycle_planes(state.pose.unbind(-1), state.speed, act.unbind(-1))
    return _merge_planes(state, at, from_log, (moving, sim_pose, sim_speed))


def _merge_movers(
    state: SimState,
    action: torch.Tensor,
    at: torch.Tensor,
    masks: tuple[torch.Tensor, ...],
    movers: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``_merge_dense``'s values with only the ``movers`` [B, K] integrating."""
    moving, from_log = masks
    merged = _merge_planes(state, at, from_log)
    return _integrate_movers(state, action, movers, moving, merged)


def _merge_planes(
    state: SimState,
    at: torch.Tensor,
    from_log: torch.Tensor,
    sim: tuple[torch.Tensor, list[torch.Tensor], torch.Tensor] | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(pose [B, N, 3], speed [B, N]): the log ``at`` where ``from_log``, else the state's, and
    with ``sim`` = (moving [B, N] bool, simulated (x, y, yaw) planes, speed) the simulated
    values where moving; a component at a time into the components of the new pose
    (``where_into``: no [B, N, 1] mask broadcast over [B, N, 3] poses)."""
    now, logged = state.pose.unbind(-1), at.unbind(-1)
    pose = torch.empty_like(state.pose)
    for k in range(3):
        if sim is None:
            where_into(pose[..., k], from_log, logged[k], now[k])
        else:
            kept = torch.where(from_log, logged[k], now[k])
            where_into(pose[..., k], sim[0], sim[1][k], kept)
    speed = torch.where(from_log, logged[3], state.speed)
    return pose, speed if sim is None else torch.where(sim[0], sim[2], speed)


def _integrate_movers(
    state: SimState,
    action: torch.Tensor,
    movers: torch.Tensor,
    moving: torch.Tensor,
    merged: tuple[torch.Tensor, torch.Tensor],
) -> tuple[torch.Tensor, torch.Tensor]:
    """(pose [B, N, 3], speed [B, N]): ``merged`` with the ``moving`` slots among ``movers``
    [B, K] integrated (``step``'s rule on K slots per row instead of N)."""
    b, k = movers.shape
    pose, speed = merged
    limit = gather_rows(state.agents.action_limit, movers)
    act = torch.clamp(gather_rows(action, movers), -limit, limit)
    sim_pose, sim_speed = unicycle_step(
        gather_rows(state.pose, movers), gather_rows(state.speed, movers), act
    )
    on = gather_rows(moving, movers)  # [B, K]
    # Repeated slots write the same values (all read by slot).
    new_pose = torch.where(on.view(b, k, 1), sim_pose, gather_rows(pose, movers))
    new_speed = torch.where(on, sim_speed, gather_rows(speed, movers))
    pose = pose.scatter(1, movers.view(b, k, 1).expand(b, k, 3), new_pose)
    return pose, speed.scatter(1, movers, new_speed)


def _log_at(state: SimState, t: torch.Tensor) -> torch.Tensor:
    """[B, N, 5] the log at step ``t`` [B] of each scenario (x, y, yaw, speed, valid as 0 / 1):
    one ``index_select`` of the time-major ``by_step`` blocks, b-th row at t[b]."""
    table = state.log.by_step.value  # [K, T, N, 5]
    return select_rows(table, t + state.log.row_steps).view(-1, *table.shape[2:])
