"""The Gymnasium VectorEnv view of the batched simulator (one learner per row: the SDC)."""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import pytest
import torch
from gymnasium.vector import AutoresetMode

from tbsim_env.data.generator import default_scenarios
from tbsim_env.env.gym_vector import TrafficVectorEnv
from tbsim_env.env.vector_env import BatchedTrafficEnv

pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def scenes():
    return default_scenarios(3)


def test_spaces_flattening_and_same_step_autoreset(scenes):
    venv = TrafficVectorEnv(scenes, 3, npc_policy="constant_velocity", seed=0)
    assert venv.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
    ref = BatchedTrafficEnv(scenes, 3, npc_policy="constant_velocity", seed=0)
    obs, info = venv.reset(seed=0)
    ref_obs, _ = ref.reset(seed=0)
    assert obs.dtype == np.float32 and obs.shape == venv.observation_space.shape
    assert venv.observation_space.contains(obs)
    dict_space = ref.single_observation_space()
    for row in range(3):
        want = gym.spaces.flatten(dict_space, {k: ref_obs[k][row, 0].numpy() for k in dict_space})
        np.testing.assert_array_equal(obs[row], want)
    ended, returns = 0, np.zeros(3)
    for _ in range(200):
        actions = venv.action_space.sample() * 0.0 + np.array([3.0, 0.6], np.float32)
        obs, rew, term, trunc, info = venv.step(actions)
        ref_obs, ref_rew, *_ = ref.step(torch.from_numpy(actions).reshape(3, 1, 2))
        np.testing.assert_array_equal(rew, ref_rew[:, 0].numpy())
        assert rew.dtype == np.float32 and term.dtype == trunc.dtype == np.bool_
        returns += rew
        done = term | trunc
        np.testing.assert_array_equal(info["_final_obs"], done)
        for row in np.flatnonzero(done):
            ended += 1
            assert info["episode"]["r"][row] == pytest.approx(returns[row], abs=1e-3)
            returns[row] = 0.0
            # Same-step autoreset: the returned observation starts the next episode.
            assert not np.array_equal(info["final_obs"][row], obs[row])
        assert venv.observation_space.contains(obs)
    assert ended >= 3


def test_dict_observations_torch_backend_and_refusals(scenes):
    venv = TrafficVectorEnv(scenes, 2, flatten=False, backend="torch", seed=1)
    obs, info = venv.reset()
    assert isinstance(obs, dict) and all(torch.is_tensor(v) for v in obs.values())
    assert obs["ego_history"].shape == (2, *venv.single_observation_space["ego_history"].shape)
    obs, rew, term, trunc, info = venv.step(torch.zeros(2, 2))
    assert torch.is_tensor(rew) and rew.shape == (2,)
    with pytest.raises(ValueError, match="SDC"):
        TrafficVectorEnv(scenes, 2, controlled="all")
    with pytest.raises(ValueError, match="backend"):
        TrafficVectorEnv(scenes, 2, backend="jax")
