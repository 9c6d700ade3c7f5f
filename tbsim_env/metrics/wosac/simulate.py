"""Closed-loop rollouts of a whole scenario for WOSAC: R joint futures of every sim agent.

Sim agents are the tracks valid at the current step (WOSAC's definition). They are all driven by
one policy through the batched core (R rollouts = a batch of R copies of the scenario), except
with an exact-replay policy, which copies the log. Tracks that appear only after the current
step are removed from the simulation: WOSAC ignores them, and using them would leak the logged
future into the rollouts. Box heights (z) are held at their current-step value.

Every rollout covers the 80 steps after the current one (``horizon.wosac_end_step``), also on a
scene that logs only its history (the WOSAC test split); only log replay needs the logged future.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from tbsim_env.data.scenario import Scenario
from tbsim_env.metrics.wosac.rollouts import Rollouts, log_replay_rollouts
from tbsim_env.observation.rows import take_rows
from tbsim_env.sim import core
from tbsim_env.sim.build import build_sim_state
from tbsim_env.sim.horizon import wosac_end_step, wosac_scenario
from tbsim_env.sim.policy import Policy
from tbsim_env.sim.state import SimState


def tile_state(state: SimState, n: int) -> SimState:
    """Repeat a batch-of-one state ``n`` times along the batch axis (``take_rows`` of row 0)."""
    return take_rows(state, torch.zeros(n, dtype=torch.int64, device=state.device))


def simulate_rollouts(
    scenario: Scenario,
    policy: Policy,
    *,
    num_rollouts: int = 32,
    seed: int = 0,
    device: str | torch.device = "cpu",
) -> Rollouts:
    """Roll out every sim agent of ``scenario`` with ``policy`` for the 80 WOSAC steps.

    Args:
        scenario: the logged scenario (history up to ``current_index`` is used as is; the
            logged future, if any, is not read).
        policy: drives every sim agent (``exact_replay`` policies copy the log instead).
        num_rollouts: R joint futures (32 for WOSAC).
        seed: seeds the rollout generator (same seed, same rollouts).
        device: torch device.

    Returns:
        ``Rollouts`` with [R, A_sim, S] poses in the scenario frame, S = 80.

    Raises:
        MissingFutureError: log replay of a scene without its logged future.
    """
    if getattr(policy, "exact_replay", False):
        # WOSAC's log replay: the logged future as stored, placeholders at invalid steps
        # included (what the official reference scores 0.8266 / 0.8070 on 637f20cafde22ff8).
        return log_replay_rollouts(scenario, num_rollouts=num_rollouts)
    start = scenario.current_index
    grid = wosac_scenario(scenario)
    base = build_sim_state([grid], start_step=start, device=device)
    sim = torch.from_numpy(scenario.sim_agent_mask()).to(base.device)[None]
    agents = base.agents.mask & torch.nn.functional.pad(sim, (0, base.num_agents - sim.shape[1]))
    base = base.replace(
        agents=dataclasses.replace(base.agents, mask=agents),
        valid=base.valid & agents,
    )
    base = base.replace(controlled=agents.clone())
    state = tile_state(base, num_rollouts)
    gen = torch.Generator(device="cpu").manual_seed(int(seed))
    pstate = policy.initial_state(state, [grid] * num_rollouts, gen)
    n_steps = wosac_end_step(scenario) - start
    poses = []
    last = state.pose
    with torch.inference_mode():
        for _ in range(n_steps):
            action, pstate = policy.act(state, pstate, gen)
            state = core.step(state, action)
            last = torch.where(state.valid[..., None], state.pose, last)
            poses.append(last)
    pose = torch.stack(poses, dim=2)  # [R, N, S, 3]
    idx = torch.nonzero(sim[0], as_tuple=True)[0]
    pose = pose[:, idx].double()
    origin = base.origin[0]
    z0 = torch.from_numpy(scenario.tracks.xyz[idx.cpu().numpy(), start, 2]).to(pose.device)
    return Rollouts(
        scenario_id=scenario.scenario_id,
        object_id=torch.from_numpy(scenario.tracks.id[idx.cpu().numpy()]).long(),
        x=(pose[..., 0] + origin[0]).float().cpu(),
        y=(pose[..., 1] + origin[1]).float().cpu(),
        z=z0[None, :, None].expand(num_rollouts, -1, n_steps).float().cpu().contiguous(),
        heading=pose[..., 2].float().cpu(),
    )


def linear_extrapolation_rollouts(
    scenario: Scenario, *, num_rollouts: int = 32, seed: int = 0, noise_std: float = 0.1
) -> Rollouts:
    """The official WOSAC tutorial baseline: constant displacement plus cumulative noise.

    Each object moves by its last history displacement ``p[t] - p[t-1]`` every step (zero if
    ``t-1`` is invalid), heading held. Every rollout adds, per step and per dimension, Gaussian
    noise of standard deviation ``noise_std`` times the largest absolute displacement over
    objects in that dimension; the noise accumulates (it is added to the position each step).
    With ``noise_std = 0.1`` (variance 0.01) the spread matches Waymo's ``test_submission``.

    Args:
        scenario: the scenario.
        num_rollouts: R.
        seed: noise seed.
        noise_std: see above.
    """
    t = scenario.current_index
    idx = scenario.sim_agent_indices()
    tr = scenario.tracks
    p10 = tr.xyz[idx, t].astype(np.float64)
    prev_ok = tr.valid[idx, t - 1]
    disp = np.where(prev_ok[:, None], p10 - tr.xyz[idx, t - 1], 0.0)  # [A, 3]
    n_steps = wosac_end_step(scenario) - t
    rng = np.random.default_rng(seed)
    scale = noise_std * np.abs(disp).max(axis=0)  # [3]
    noise = rng.standard_normal((num_rollouts, len(idx), n_steps, 3)) * scale
    k = np.arange(1, n_steps + 1, dtype=np.float64)
    pos = p10[None, :, None] + k[None, None, :, None] * disp[None, :, None] + noise.cumsum(axis=2)
    heading = np.broadcast_to(tr.heading[idx, t][None, :, None], (num_rollouts, len(idx), n_steps))
    return Rollouts(
        scenario_id=scenario.scenario_id,
        object_id=torch.from_numpy(tr.id[idx]).long(),
        x=torch.from_numpy(pos[..., 0]).float(),
        y=torch.from_numpy(pos[..., 1]).float(),
        z=torch.from_numpy(pos[..., 2]).float(),
        heading=torch.from_numpy(np.ascontiguousarray(heading)).float(),
    )


__all__ = [
    "linear_extrapolation_rollouts",
    "simulate_rollouts",
    "tile_state",
]
