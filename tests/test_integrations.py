"""RL-library integrations: Gymnasium checker, SuperSuit vector envs, SB3 PPO, RLlib PPO.

Each library is optional (the ``rl`` extra); a test whose library is missing skips with the
import error.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from tbsim_env.data.generator import default_scenarios
from tbsim_env.env.wrappers import SingleAgentTrafficEnv, SlotAgentsParallelEnv


@pytest.fixture(scope="module")
def scenes():
    return default_scenarios(2)


def test_single_agent_env_passes_gymnasium_checker(scenes):
    from gymnasium.utils.env_checker import check_env

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # infinite Box bounds are intended
        for flatten in (True, False):
            env = SingleAgentTrafficEnv(scenes, npc_policy="constant_velocity", flatten=flatten)
            check_env(env, skip_render_check=True)
        env = SingleAgentTrafficEnv(scenes, normalize_actions=True)
        check_env(env, skip_render_check=True)


def test_single_agent_env_follows_trafficenv(scenes):
    """Flattened observations and rewards are those of the SDC in ``TrafficEnv``."""
    import gymnasium as gym

    from tbsim_env.env import TrafficEnv

    env = SingleAgentTrafficEnv(scenes, npc_policy="log_replay")
    ref = TrafficEnv(scenes, controlled="sdc", npc_policy="log_replay")
    obs, _ = env.reset(seed=3)
    ref_obs, _ = ref.reset(seed=3)
    (sdc,) = ref.agents
    space = ref.observation_space(sdc)
    assert env.observation_space.shape == obs.shape == (gym.spaces.flatdim(space),)
    np.testing.assert_array_equal(obs, gym.spaces.flatten(space, ref_obs[sdc]))
    total, steps = 0.0, 0
    while True:
        act = env.expert_action()
        np.testing.assert_array_equal(act, ref.expert_actions()[sdc])
        obs, r, term, trunc, info = env.step(act)
        ref_obs, ref_r, *_ = ref.step({sdc: act})
        np.testing.assert_array_equal(obs, gym.spaces.flatten(space, ref_obs[sdc]))
        assert r == ref_r[sdc]
        total += r
        steps += 1
        if term or trunc:
            break
    # Following the log reaches the goal (or the end) without collision.
    assert not info["collision"] and steps <= 80 and total > 0
    assert env.observation_space.contains(obs)


def test_slot_agents_env_is_a_valid_parallel_env(scenes):
    env = SlotAgentsParallelEnv(scenes, controlled="tracks_to_predict", npc_policy="log_replay")
    parallel_api_test(env, num_cycles=30)
    obs, infos = env.reset(seed=0)
    assert set(obs) == set(env.possible_agents)
    active = [s for s in env.agents if infos[s]["active"]]
    assert active and all(infos[s]["agent"].startswith("track_") for s in active)


def test_supersuit_vector_envs(scenes):
    ss = pytest.importorskip("supersuit")
    par = SlotAgentsParallelEnv(scenes, controlled="sdc", npc_policy="constant_velocity")
    vec = ss.pettingzoo_env_to_vec_env_v1(par)
    vec = ss.concat_vec_envs_v1(vec, 2, num_cpus=0, base_class="gymnasium")
    obs, _ = vec.reset(seed=0)
    assert obs.shape == (2, par.observation_space("agent_0").shape[0])
    ends = 0
    for _ in range(85):  # more than one episode: autoreset happens inside SuperSuit
        obs, rew, term, trunc, _ = vec.step(np.zeros((2, 2), np.float32))
        assert obs.shape[0] == 2 and rew.shape == (2,) and np.isfinite(obs).all()
        ends += int((term | trunc).sum())
    assert ends >= 2
    vec.close()


def test_stable_baselines3_ppo_learns_a_few_hundred_steps(scenes, tmp_path):
    sb3 = pytest.importorskip("stable_baselines3")
    env = SingleAgentTrafficEnv(scenes[:1], npc_policy="constant_velocity", normalize_actions=True)
    model = sb3.PPO(
        "MlpPolicy", env, n_steps=128, batch_size=64, n_epochs=2, seed=0, device="cpu", verbose=0
    )
    before = [p.detach().clone() for p in model.policy.parameters()]
    model.learn(total_timesteps=256)
    after = list(model.policy.parameters())
    assert model.num_timesteps >= 256
    assert any(not np.allclose(a.detach().numpy(), b.numpy()) for a, b in zip(after, before))
    model.save(tmp_path / "ppo")
    loaded = sb3.PPO.load(tmp_path / "ppo", device="cpu")
    obs, _ = env.reset(seed=1)
    action, _ = loaded.predict(obs, deterministic=True)
    assert env.action_space.contains(action.astype(np.float32))


@pytest.mark.slow
def test_rllib_multi_agent_ppo_two_env_runners():
    pytest.importorskip("ray.rllib", reason="ray[rllib] is not installed (the 'rl' extra)")
    import ray
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv
    from ray.tune.registry import register_env

    def make(_config):
        scenes = default_scenarios(1)
        return ParallelPettingZooEnv(
            SlotAgentsParallelEnv(
                scenes, controlled="tracks_to_predict", npc_policy="constant_velocity"
            )
        )

    register_env("tbsim_slots", make)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, ignore_reinit_error=True)
    try:
        config = (
            PPOConfig()
            .environment("tbsim_slots")
            .env_runners(num_env_runners=2, rollout_fragment_length=50, num_cpus_per_env_runner=1)
            .multi_agent(
                policies={"shared"}, policy_mapping_fn=lambda agent_id, *args, **kw: "shared"
            )
            .training(train_batch_size=200, minibatch_size=100, num_epochs=1)
            .learners(num_learners=0)
        )
        algo = config.build_algo()
        result = algo.train()
        runners = result["env_runners"]
        assert runners["num_env_steps_sampled"] >= 200
        algo.stop()
    finally:
        ray.shutdown()
