"""One batched simulation step: controlled agents integrate actions, the others replay the log.

Controller assignment is a mask (``SimState.controlled``); the caller merges the actions of
external controllers and policies into one ``[B, N, 2]`` tensor beforehand (see
``merge_actions``), so a step is a handful of tensor operations whatever the mix.
"""

from __future__ import annotations

import torch

from tbsim_env.sim.dynamics import unicycle_step
from tbsim_env.sim.state import SimState
from tbsim_env.torch_utils import cached_arange, listed


def merge_actions(*pairs: tuple[torch.Tensor, torch.Tensor]) -> torch.Tensor:
    """Merge actions of several controllers by mask; later pairs win where masks overlap.

    Args:
        pairs: (mask [B, N] bool, action [B, N, 2]) per controller.

    Returns:
        [B, N, 2] merged action (zero where no mask is set).
    """
    out = torch.zeros_like(pairs[0][1])
    for mask, action in pairs:
        out = torch.where(mask[..., None], action, out)
    return out


def seen_before(state: SimState) -> torch.Tensor:
    """[B, N] bool: the agent was valid in the log at some step <= the current one."""
    return state.log.first_valid <= state.step[:, None]


def step(state: SimState, action: torch.Tensor) -> SimState:
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

    Returns:
        The state at ``step + 1``.
    """
    n_t = state.log.valid.shape[-1]
    nxt = (state.step + 1).clamp(max=n_t - 1)
    log_valid, log_pose, log_speed = _log_at(state, nxt)
    log_valid = log_valid & state.agents.mask
    fresh = state.log.first_valid > state.step.unsqueeze(1)  # not seen_before(state)

    moving = state.controlled & state.valid
    # Spawn (controlled, not present, not seen before) or replay (not controlled, present or
    # not seen before) where the log has the agent. For a moving agent ``from_log`` may be
    # anything: ``moving`` wins below. (``valid > controlled`` is ``valid & ~controlled``.)
    from_log = log_valid & (fresh | (state.valid > state.controlled))
    pose = torch.where(from_log.unsqueeze(-1), log_pose, state.pose)
    speed = torch.where(from_log, log_speed, state.speed)
    pairs = listed(moving)
    if pairs is None:
        moving_ = moving.unsqueeze(-1)
        limit = state.agents.action_limit
        act = torch.clamp(action, -limit, limit) * moving_  # clip_action
        sim_pose, sim_speed = unicycle_step(state.pose, state.speed, act)
        pose = torch.where(moving_, sim_pose, pose)
        speed = torch.where(moving, sim_speed, speed)
    else:  # the moving agents alone (a few of the slots: the rest replay the log)
        limit = state.agents.action_limit[pairs]
        act = torch.clamp(action[pairs], -limit, limit)
        sim_pose, sim_speed = unicycle_step(state.pose[pairs], state.speed[pairs], act)
        pose = pose.index_put(pairs, sim_pose)
        speed = speed.index_put(pairs, sim_speed)
    return state.replace(step=nxt, pose=pose, speed=speed, valid=moving | from_log)


def _log_at(state: SimState, t: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The log at step ``t`` [B] of each scenario: (valid [B, N], pose [B, N, 3], speed [B, N]).

    A batch of one on the CPU reads the step as a number (a view per field instead of an
    indexing operation; not under ``torch.compile``, where that would break the graph);
    otherwise one ``index_select`` of the time-major ``by_step`` blocks, b-th row at t[b].
    """
    log = state.log
    if state.batch_size == 1 and t.device.type == "cpu" and not torch.compiler.is_compiling():
        i = int(t.item())
        return log.valid[:, :, i], log.pose[:, :, i], log.speed[:, :, i]
    n_t = log.by_step.shape[1]
    rows = cached_arange(state.batch_size, state.device) * n_t + t
    at = log.by_step.flatten(0, 1).index_select(0, rows)  # [B, N, 5]
    return at[..., 4] > 0, at[..., :3], at[..., 3]
