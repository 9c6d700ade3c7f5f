"""TrafficBotsPolicy: the network driving NPCs of the simulator and the PettingZoo env."""

from __future__ import annotations

import pytest
import torch

import tbsim_env  # noqa: F401  (first: avoids the policies <-> tbsim_env.env import cycle)

# isort: split

from policies.base import Policy
from policies.trafficbots import TokenBatch, TrafficBots, TrafficBotsConfig
from policies.trafficbots.policy import TrafficBotsPolicy
from tbsim_env.data import load_scenarios
from tbsim_env.data.preprocess import preprocess_scenario
from tbsim_env.sim import core
from tbsim_env.sim.build import build_sim_state

pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def scenario(one_scenario_path):
    return load_scenarios(one_scenario_path)[0]


@pytest.fixture(scope="module")
def policy() -> TrafficBotsPolicy:
    torch.manual_seed(0)
    return TrafficBotsPolicy(TrafficBots(TrafficBotsConfig.small()))


def _drive(policy, scenario, seed: int, n_steps: int):
    state = build_sim_state([scenario])
    ps = policy.initial_state(state, [scenario], torch.Generator().manual_seed(seed))
    state = state.replace(controlled=state.agents.mask)
    actions = []
    for _ in range(n_steps):
        action, ps = policy.act(state, ps, torch.Generator())
        actions.append(action)
        state = core.step(state, action)
    return torch.stack(actions), ps, state


def test_policy_warm_history_is_the_log_in_the_token_frame(policy, scenario) -> None:
    assert isinstance(policy, Policy)
    state = build_sim_state([scenario])
    ps = policy.initial_state(state, [scenario], torch.Generator().manual_seed(0))
    gt = TokenBatch.from_tokens(preprocess_scenario(scenario))
    assert ps.rollout.step == 10 and ps.rollout.hist_tl_present[0, :, -10:].all()
    hist_valid = ps.rollout.hist_valid[0, :, -10:]
    assert torch.equal(hist_valid, gt.ag_valid[0, :, :10] & hist_valid)
    assert hist_valid[0].all()  # the SDC
    pose = ps.rollout.hist_pose[0, :, -10:, :2]
    assert torch.allclose(pose[hist_valid], gt.ag_pose[0, :, :10, :2][hist_valid], atol=1e-3)
    assert (ps.slot[0] >= 0).sum() == (gt.ag_type[0] > 0).sum()
    assert ps.slot[0, 0] == scenario.sdc_index


def test_policy_drives_selected_agents_deterministically(policy, scenario) -> None:
    a1, ps, state = _drive(policy, scenario, seed=0, n_steps=4)
    a2, _, _ = _drive(policy, scenario, seed=0, n_steps=4)
    a3, _, _ = _drive(policy, scenario, seed=1, n_steps=4)
    assert torch.equal(a1, a2) and not torch.equal(a1, a3)
    driven = torch.zeros(state.num_agents, dtype=torch.bool)
    driven[ps.slot[0][ps.slot[0] >= 0]] = True
    assert (a1[:, 0, ~driven] == 0).all()
    assert (a1[:, 0, driven].abs().amax(-1) > 0).any()
    assert torch.isfinite(a1).all() and int(state.step[0]) == 14


def test_policy_in_the_parallel_env(policy, scenario) -> None:
    from tbsim_env.env import TrafficEnv

    env = TrafficEnv([scenario], npc_policy=policy)
    obs, _ = env.reset(seed=0)
    for _ in range(3):
        obs, rew, term, trunc, _ = env.step({a: [0.0, 0.0] for a in env.agents})
    assert set(obs) <= set(rew) and len(rew) >= 1


def test_trimmed_policy_drives_like_the_padded_one(policy, scenario) -> None:
    """``trim=True`` (what ``TrafficEnv`` uses) runs on the used token rows only and gives the
    padded policy's actions (``BatchedTrafficEnv``'s fixed rows: ``test_vector_env``)."""
    from tbsim_env.env import TrafficEnv

    trimmed = TrafficBotsPolicy(policy.model, trim=True)
    a_pad, ps_pad, _ = _drive(policy, scenario, seed=3, n_steps=12)
    a_trim, ps_trim, _ = _drive(trimmed, scenario, seed=3, n_steps=12)
    n_used = int(TokenBatch.from_tokens(preprocess_scenario(scenario)).trim().ag_type.shape[1])
    assert ps_pad.rollout.hist_valid.shape[1] == 64 > n_used
    assert ps_trim.rollout.hist_valid.shape[1] == n_used
    assert torch.equal(ps_pad.slot[:, :n_used], ps_trim.slot)
    assert not (ps_pad.slot[:, n_used:] >= 0).any()
    assert (a_pad.abs() > 0).any() and torch.allclose(a_pad, a_trim, atol=1e-4)
    assert TrafficEnv([scenario]).npc_policy.trim


def test_trafficenv_reuses_each_scenes_encoding_exactly() -> None:
    """``TrafficEnv`` keeps each scene's tokens and encoding: returning to a scene starts from
    them, and every episode is the one a policy that computes them each time drives."""
    import numpy as np

    from tbsim_env.data.generator import default_scenarios
    from tbsim_env.env import TrafficEnv

    scenes = default_scenarios(2)

    def episodes(cache: bool) -> tuple[list[np.ndarray], TrafficEnv]:
        env = TrafficEnv(scenes, controlled="sdc", npc_policy="trafficbots")
        env.npc_policy.cache_scenes = cache
        poses = []
        for seed, k in enumerate((0, 1, 0)):  # scene 0 again from its cache
            env.reset(seed=seed, options={"scenario_index": k})
            for _ in range(12):
                if not env.agents:
                    break
                env.step({a: np.zeros(2, np.float32) for a in env.agents})
                poses.append(env.sim_state.pose.numpy().copy())
        return poses, env

    (cached, env), (fresh, _) = episodes(True), episodes(False)
    entries = list(env.npc_policy.scene_cache.values())
    assert len(entries) == 2 and all(e.encoding is not None for e in entries)
    assert all(np.array_equal(a, b) for a, b in zip(cached, fresh, strict=True))
