"""TrafficEnv: PettingZoo conformance, determinism, invariance, bad actions, rendering."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tbsim_env.core import constants as C
from tbsim_env.core.config import EnvConfig, TerminationConfig
from tbsim_env.core.errors import ActionError
from tbsim_env.data import load_scenarios
from tbsim_env.env import TrafficEnv
from tests.conftest import check_parallel_api


@pytest.fixture(scope="module")
def real(womd_dir):
    return load_scenarios(womd_dir / "waymo-open-dataset" / "motion_data_one_scenario.tfrecord")[0]


def test_parallel_api_on_real_scenario(one_scenario_path):
    check_parallel_api(TrafficEnv(str(one_scenario_path), npc_policy="log_replay"), num_cycles=100)
    env = TrafficEnv(
        str(one_scenario_path), npc_policy="log_replay", controlled="tracks_to_predict"
    )
    check_parallel_api(env, num_cycles=100)


def test_parallel_api_on_embedded_default():
    env = TrafficEnv(controlled="all", npc_policy="constant_velocity")
    env.reset(seed=0)
    assert set(env.agents) < set(env.possible_agents), "the union over scenes, not one scene's"
    check_parallel_api(env, num_cycles=100)


def test_agent_names_carry_track_ids(real):
    env = TrafficEnv([real], npc_policy="log_replay", controlled="tracks_to_predict")
    env.reset(seed=0)
    ids = {int(real.tracks.id[i]) for i in real.tracks_to_predict} | {real.sdc_id}
    assert set(env.agents) == {f"track_{i}" for i in ids}
    env = TrafficEnv([real], npc_policy="log_replay", controlled=[int(real.tracks.id[43])])
    env.reset()
    assert env.agents == [f"track_{int(real.tracks.id[43])}"]


def _rollout(env, seed, steps):
    obs, _ = env.reset(seed=seed)
    rng = np.random.default_rng(seed)
    trace = []
    for _ in range(steps):
        if not env.agents:
            break
        acts = {a: rng.uniform(-1, 1, 2).astype(np.float32) for a in env.agents}
        obs, rew, term, trunc, info = env.step(acts)
        trace.append((obs, rew, term, trunc))
    return trace, env.sim_state


def test_determinism_over_80_steps():
    env_a = TrafficEnv(controlled="all", npc_policy="constant_velocity", scenario_order="random")
    env_b = TrafficEnv(controlled="all", npc_policy="constant_velocity", scenario_order="random")
    trace_a, state_a = _rollout(env_a, 7, 80)
    trace_b, state_b = _rollout(env_b, 7, 80)
    assert len(trace_a) == len(trace_b) >= 80
    for (oa, ra, ta, ua), (ob, rb, tb, ub) in zip(trace_a, trace_b):
        assert ra == rb and ta == tb and ua == ub
        for agent in oa:
            for key in oa[agent]:
                np.testing.assert_array_equal(oa[agent][key], ob[agent][key])
    assert torch.equal(state_a.pose, state_b.pose)


def test_observations_invariant_to_rotation_and_translation(real):
    moved = real.transformed(1.1, (-3200.0, 4700.0))
    obs_a, _ = TrafficEnv([real], npc_policy="log_replay", controlled="tracks_to_predict").reset(
        seed=0
    )
    env_b = TrafficEnv([moved], npc_policy="log_replay", controlled="tracks_to_predict")
    obs_b, _ = env_b.reset(seed=0)
    for agent in obs_a:
        for key in obs_a[agent]:
            np.testing.assert_allclose(obs_a[agent][key], obs_b[agent][key], atol=1e-4, err_msg=key)
    # And after some closed-loop steps with the same actions.
    env_a = TrafficEnv([real], npc_policy="log_replay", controlled="tracks_to_predict")
    env_a.reset(seed=0)
    env_b.reset(seed=0)
    for _ in range(20):
        acts = {a: np.array([0.5, 0.05], np.float32) for a in env_a.agents}
        oa, *_ = env_a.step(acts)
        ob, *_ = env_b.step({a: acts[a] for a in env_b.agents})
    # float32 integration in two frames rounds differently: ~2e-4 m after 20 closed-loop steps.
    for agent in oa:
        for key in oa[agent]:
            np.testing.assert_allclose(oa[agent][key], ob[agent][key], atol=1e-3, err_msg=key)


def test_observation_content(real):
    env = TrafficEnv([real], npc_policy="log_replay")
    obs, _ = env.reset(seed=0)
    o = obs[env.agents[0]]
    assert env.observation_space(env.agents[0]).contains(o)
    # The ego's current pose is the origin of its own frame.
    np.testing.assert_allclose(o["ego_history"][-1, :4], [0, 0, 1, 0], atol=1e-5)
    # Neighbours are sorted by distance and masked consistently.
    d = np.linalg.norm(o["agents_pose"][:, :2], axis=-1)
    m = o["agents_mask"].astype(bool)
    assert m.sum() > 5 and np.all(np.diff(d[m]) >= -1e-4)
    assert np.all(o["agents"][~m] == 0)
    assert o["map_mask"].sum() == 64 and o["traffic_lights_mask"].sum() > 0


def test_bad_actions_raise_clear_errors(real):
    env = TrafficEnv([real], npc_policy="log_replay")
    env.reset(seed=0)
    a = env.agents[0]
    with pytest.raises(ActionError, match="not finite"):
        env.step({a: np.array([np.nan, 0.0])})
    with pytest.raises(ActionError, match="not finite"):
        env.step({a: np.array([0.0, np.inf])})
    with pytest.raises(ActionError, match="not active"):
        env.step({a: np.zeros(2), "track_999999": np.zeros(2)})
    with pytest.raises(ActionError, match="no action"):
        env.step({})
    with pytest.raises(ActionError, match="shape"):
        env.step({a: np.zeros(3)})
    with pytest.raises(ValueError, match="no track with id"):
        TrafficEnv([real], npc_policy="log_replay", controlled=[123456789])


def test_out_of_range_actions_are_clipped(real):
    env = TrafficEnv([real], npc_policy="log_replay")
    env.reset(seed=0)
    a = env.agents[0]
    slot = env.sim_state.agents.track_id[0].tolist().index(int(a.split("_")[1]))
    v0 = float(env.sim_state.speed[0, slot])
    env.step({a: np.array([100.0, 0.0])})
    assert float(env.sim_state.speed[0, slot]) == pytest.approx(v0 + 0.1 * C.MAX_ACCEL[1], abs=1e-4)


def test_expert_actions_follow_the_log(real):
    no_goal = EnvConfig(termination=TerminationConfig(goal=False))
    env = TrafficEnv(
        [real], npc_policy="log_replay", controlled=[int(real.tracks.id[43])], config=no_goal
    )
    env.reset(seed=0)
    a = env.agents[0]
    gaps = []
    while env.agents:
        _, _, _, _, info = env.step(env.expert_actions())
        gaps.append(info[a]["log_divergence"])
    assert len(gaps) == 80
    assert max(gaps) < 1.0 and float(np.mean(gaps)) < 0.2


def test_collision_terminates_and_removes_agent():
    env = TrafficEnv(controlled="all", npc_policy="log_replay")
    env.reset(seed=0)
    hit = False
    for _ in range(80):
        if not env.agents:
            break
        # Drive everyone hard to the left: collisions happen quickly.
        _, rew, term, _, info = env.step({a: np.array([5.0, 1.5]) for a in env.agents})
        for agent, done in term.items():
            if done and info[agent]["collision"]:
                hit = True
                assert rew[agent] <= -1.0 + 1.0
                assert agent not in env.agents
    assert hit


def test_lazy_observations_equal_the_eager_ones():
    """``lazy_observations=True`` returns, when read, what the eager reset and step return:
    every agent, every step, the agents that terminate on the step included."""
    envs = [
        TrafficEnv(controlled="all", npc_policy="log_replay", lazy_observations=lazy)
        for lazy in (False, True)
    ]
    for k in (1, 0):  # two scenes: each builds its own map context when first observed
        (eager, _), (lazy, _) = (env.reset(options={"scenario_index": k}) for env in envs)
        assert list(lazy) == list(eager)
        for agent in eager:
            for key, value in eager[agent].items():
                np.testing.assert_allclose(lazy[agent][key], value, rtol=0, atol=1e-5)
    ended = 0
    for step in range(40):
        if not envs[0].agents:
            break
        actions = {a: np.array([5.0, 1.5 * (-1) ** step]) for a in envs[0].agents}
        eager, _, term, _, _ = envs[0].step(actions)
        lazy, _, term_lazy, _, _ = envs[1].step(actions)
        assert term == term_lazy and list(lazy) == list(eager)
        ended += sum(term.values())
        if step % 3 == 0:
            continue  # some steps nobody reads: the next ones still observe their own state
        for agent in eager:
            for key, value in eager[agent].items():
                np.testing.assert_allclose(lazy[agent][key], value, rtol=0, atol=1e-5)
    assert ended > 0
    with pytest.raises(KeyError):
        lazy["track_does_not_exist"]


def test_episode_length_and_truncation(real):
    env = TrafficEnv([real], npc_policy="log_replay")
    env.reset(seed=0)
    a = env.agents[0]
    n = 0
    while env.agents:
        _, _, term, trunc, _ = env.step({a: np.zeros(2)})
        n += 1
    assert n == 80 and trunc[a] and not term[a]
    assert int(env.sim_state.step[0]) == 90


def test_render_rgb_array(real):
    env = TrafficEnv([real], npc_policy="log_replay", render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.dtype == np.uint8 and frame.ndim == 3 and frame.shape[2] == 3
    assert len(np.unique(frame.reshape(-1, 3), axis=0)) > 5
