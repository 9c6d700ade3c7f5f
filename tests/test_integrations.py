"""RL-library integrations: Gymnasium checker, SuperSuit vector envs, SB3 PPO, RLlib PPO.

Each library is optional (the ``rl`` extra); a test whose library is missing skips with the
import error.
"""

from __future__ import annotations

import warnings

import gymnasium as gym
import numpy as np
import pytest
from pettingzoo import ParallelEnv

from tbsim_env.data.generator import default_scenarios
from tbsim_env.env.wrappers import SingleAgentTrafficEnv, SlotAgentsParallelEnv
from tests.conftest import check_parallel_api


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
    rewarded = 0
    for k in range(len(scenes)):  # one episode on each scene
        obs, _ = env.reset(seed=3, options={"scenario_index": k})
        ref_obs, _ = ref.reset(seed=3, options={"scenario_index": k})
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
        # Following the log reaches the goal (or the end) without collision; it earns a
        # reward when the logged SDC makes progress (not one waiting at a red light).
        t, k = ref.scenario.tracks, ref.scenario.sdc_index
        path = np.linalg.norm(np.diff(t.xyz[k, t.valid[k], :2], axis=0), axis=-1).sum()
        assert not info["collision"] and steps <= 80
        assert (total > 0) == (path > 1.0), (ref.scenario.scenario_id, total, path)
        rewarded += total > 0
        assert env.observation_space.contains(obs)
    assert rewarded >= 1


def test_slot_agents_env_is_a_valid_parallel_env(scenes):
    env = SlotAgentsParallelEnv(scenes, controlled="tracks_to_predict", npc_policy="log_replay")
    check_parallel_api(env, num_cycles=30)
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


def test_supersuit_stable_baselines3_vec_env(scenes):
    pytest.importorskip("supersuit")
    pytest.importorskip("stable_baselines3")
    from stable_baselines3.common.vec_env import VecEnv

    from tbsim_env.integrations.supersuit import make_vec_env

    vec = make_vec_env(2, "stable_baselines3", scenarios=scenes[:1], controlled="tracks_to_predict")
    assert isinstance(vec, VecEnv)
    sc = scenes[0]
    q = len({int(i) for i in sc.tracks_to_predict} | {sc.sdc_index})  # agent slots
    assert vec.num_envs == 2 * q
    obs = vec.reset()
    obs, rew, dones, infos = vec.step(np.zeros((vec.num_envs, 2), np.float32))
    assert obs.shape[0] == rew.shape[0] == 2 * q and not dones.any()
    vec.close()


class _MixedEndingEnv(ParallelEnv):
    """Two agents; at step 2 agent_0 terminates and agent_1 is truncated."""

    metadata = {"name": "mixed_v0"}
    possible_agents = ["agent_0", "agent_1"]

    def __init__(self) -> None:
        self.agents: list[str] = []
        self.t = 0
        self.render_mode = None

    def observation_space(self, agent):
        return gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def action_space(self, agent):
        return gym.spaces.Box(-1.0, 1.0, (1,), np.float32)

    def reset(self, seed=None, options=None):
        self.agents, self.t = list(self.possible_agents), 0
        return {a: np.zeros(1, np.float32) for a in self.agents}, {a: {} for a in self.agents}

    def step(self, actions):
        self.t += 1
        end = self.t == 2
        obs = {a: np.zeros(1, np.float32) for a in self.agents}
        term = {"agent_0": end, "agent_1": False}
        trunc = {"agent_0": False, "agent_1": end}
        if end:
            self.agents = []
        return obs, dict.fromkeys(obs, 0.0), term, trunc, {a: {} for a in obs}


def test_rllib_all_flag_when_agents_end_differently():
    pytest.importorskip("ray.rllib", reason="ray[rllib] is not installed (the 'rl' extra)")
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv

    from tbsim_env.integrations.rllib import TbsimRLlibEnv, make_rllib_env

    act = {a: np.zeros(1, np.float32) for a in _MixedEndingEnv.possible_agents}
    for wrapper, ends in ((ParallelPettingZooEnv, False), (TbsimRLlibEnv, True)):
        env = wrapper(_MixedEndingEnv())
        env.reset()
        env.step(act)
        _, _, term, trunc, _ = env.step(act)
        # RLlib's own wrapper never ends an episode with mixed endings; ours does.
        assert (term["__all__"] or trunc["__all__"]) == ends
    assert trunc["__all__"] and not term["__all__"]

    # The real env ends for RLlib within one log (80 steps), whatever the agents do.
    env = make_rllib_env({"num_default_scenes": 1, "npc_policy": "log_replay"})
    obs, _ = env.reset(seed=0)
    for _ in range(81):
        obs, rew, term, trunc, _ = env.step({a: np.zeros(2, np.float32) for a in obs})
        if term["__all__"] or trunc["__all__"]:
            break
    assert term["__all__"] or trunc["__all__"], "the episode never ended for RLlib"
    assert all(term[a] or trunc[a] for a in term if a != "__all__")


@pytest.mark.slow
def test_rllib_multi_agent_ppo_two_env_runners():
    pytest.importorskip("ray.rllib", reason="ray[rllib] is not installed (the 'rl' extra)")
    import ray
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.tune.registry import register_env

    from tbsim_env.integrations.rllib import ENV_NAME, make_rllib_env

    register_env(ENV_NAME, make_rllib_env)
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, ignore_reinit_error=True)
    try:
        config = (
            PPOConfig()
            .environment(ENV_NAME, env_config={"num_default_scenes": 1})
            .env_runners(num_env_runners=2, rollout_fragment_length=25, num_cpus_per_env_runner=1)
            .multi_agent(
                policies={"shared"}, policy_mapping_fn=lambda agent_id, *args, **kw: "shared"
            )
            .training(train_batch_size=100, minibatch_size=100, num_epochs=1)
            .learners(num_learners=0)
        )
        algo = config.build_algo()
        result = algo.train()
        assert result["env_runners"]["num_env_steps_sampled"] >= 100
        sampled = result["env_runners"]["num_module_steps_sampled"]["shared"]
        assert sampled >= 2 * 100  # every slot agent maps to the shared policy
        learner = result["learners"]["shared"]
        assert learner["num_module_steps_trained"] > 0 and np.isfinite(learner["total_loss"])
        algo.stop()
    finally:
        ray.shutdown()
