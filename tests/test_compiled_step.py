"""``TrafficEnv(compile=True)``: the step as one ``torch.compile`` graph gives the eager results.

Compiling needs a C++ compiler (inductor on the CPU): without one these tests skip, except
under CI, where they fail. Each compile takes ~15 s, so the tests share scenarios of two shapes.
"""

from __future__ import annotations

import dataclasses
import os
import shutil

import numpy as np
import pytest
import torch

from tbsim_env.core import constants as C
from tbsim_env.core.config import EnvConfig
from tbsim_env.data import load_scenarios
from tbsim_env.data.generator import default_scenarios
from tbsim_env.env import TrafficEnv
from tbsim_env.env.compiled import StepFunction
from tbsim_env.env.episode import StepConfig, step
from tbsim_env.observation import ObsConfig
from tbsim_env.sim.edge_grid import build_edge_grid

if not (shutil.which("c++") or shutil.which("g++")):
    reason = "torch.compile on the CPU needs a C++ compiler (c++ / g++ not found)"
    if os.environ.get("CI", "").lower() == "true":
        pytest.fail(reason + "; under CI it is required", pytrace=False)
    pytest.skip(reason, allow_module_level=True)

pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def scenes(womd_dir):
    """A real scene and two generated ones: three shapes. The second makes the env compile a
    graph with dynamic shapes, which the third must reuse."""
    real = load_scenarios(womd_dir / "waymo-open-dataset" / "motion_data_one_scenario.tfrecord")
    return [real[0], *default_scenarios(2)]


def _play(env, episodes: int, seed: int) -> list:
    """Per step of ``episodes`` episodes: (agents, obs, rewards, terms, truncs, infos)."""
    rng = np.random.default_rng(seed)
    trace = []
    env.reset(seed=seed)
    for ep in range(episodes):
        if ep:
            env.reset()
        while env.agents:
            acts = {a: rng.uniform(-3, 3, 2).astype(np.float32) for a in env.agents}
            trace.append((list(env.agents), *env.step(acts)))
    return trace


def test_compiled_env_matches_eager_on_three_scenario_shapes(scenes):
    from torch._dynamo.utils import counters  # what PyTorch's own tests count graphs with

    kwargs = dict(controlled="tracks_to_predict", npc_policy="log_replay")
    eager = _play(TrafficEnv(scenes, **kwargs), episodes=3, seed=3)
    compiled_env = TrafficEnv(scenes, compile=True, **kwargs)
    graphs = counters["stats"]["unique_graphs"]
    compiled = _play(compiled_env, episodes=3, seed=3)
    # One graph for the first shape, then dynamic ones: the merge has a single traffic light,
    # and dynamo specialises dims of size 0 and 1, so it gets a graph of its own. No more: a
    # guard on a Python-side cache once made it recompile on every new key, and the padding
    # of ``k_nearest`` on whether a scene has fewer than k targets.
    assert 1 <= counters["stats"]["unique_graphs"] - graphs <= 3
    assert len(compiled) == len(eager) > 150
    collided = 0
    for (agents_e, obs_e, rew_e, term_e, trunc_e, info_e), (
        agents_c,
        obs_c,
        rew_c,
        term_c,
        trunc_c,
        info_c,
    ) in zip(eager, compiled):
        assert agents_c == agents_e
        assert term_c == term_e and trunc_c == trunc_e
        for a in agents_e:
            assert rew_c[a] == pytest.approx(rew_e[a], abs=1e-5)
            for key, want in obs_e[a].items():
                np.testing.assert_allclose(obs_c[a][key], want, atol=1e-5, err_msg=key)
            for key, want in info_e[a].items():
                if isinstance(want, float | dict):  # dict: the reward terms
                    assert info_c[a][key] == pytest.approx(want, abs=1e-4), key
                else:
                    assert info_c[a][key] == want, key
            collided += info_e[a]["collision"]
    # The random actions drive agents into others: the graph's removal path ran too.
    assert collided > 0


def test_points_the_edge_grid_cannot_vouch_for_are_recomputed_or_redone(scenes, monkeypatch):
    env = TrafficEnv(scenes[:1], controlled="tracks_to_predict", npc_policy="log_replay")
    env.reset(seed=0)
    state = env.sim_state
    edges = state.road_edges
    # A grid that lists one segment per cell cannot vouch for most box corners.
    valid = edges.valid[0]
    segments = [(edges.start[0][valid].double().numpy(), edges.end[0][valid].double().numpy())]
    coarse = state.replace(
        road_edges=dataclasses.replace(edges, grid=build_edge_grid(segments, count=1))
    )
    episode = dataclasses.replace(env.episode, sim=coarse)
    config = StepConfig(env.config, env.obs_config, dense=True)
    actions = torch.zeros(1, episode.setup.query.shape[1], 2)
    with torch.inference_mode():
        want = step(env.episode, actions, None, config)[1].metrics
        # Within the recompute budget the graph recomputes the corners itself.
        fn = StepFunction(config, compile=True)
        got = fn(episode, actions, None)[1].metrics
        assert fn.eager_redos == 0 and not got.offroad_stale.any()
        torch.testing.assert_close(got.offroad_distance, want.offroad_distance, atol=1e-5, rtol=0)
        # Beyond it the step is redone eagerly.
        monkeypatch.setattr(C, "OFFROAD_RECOMPUTE_BUDGET", 1)
        fn = StepFunction(config, compile=True)
        got = fn(episode, actions, None)[1].metrics
    assert fn.eager_redos == 1
    assert got.offroad_stale is None, "the eager redo's result"
    torch.testing.assert_close(got.offroad_distance, want.offroad_distance, rtol=0, atol=0)


def test_the_recompute_budget_follows_the_corner_count():
    from tbsim_env.sim.offroad import recompute_budget

    assert recompute_budget(4) == 4  # every corner of a batch of one
    assert recompute_budget(256) == C.OFFROAD_RECOMPUTE_MIN  # the SDC of 64 scenes
    assert recompute_budget(1024) == 1024 // C.OFFROAD_RECOMPUTE_SHARE
    assert recompute_budget(64 * 257 * 4) == C.OFFROAD_RECOMPUTE_BUDGET  # every slot


def test_compiled_batched_env_equals_eager_through_restarts(scenes):
    from tbsim_env.env.vector_env import BatchedTrafficEnv

    kw = dict(controlled="all", npc_policy="constant_velocity", seed=3, obs_layout="indexed")
    eager = BatchedTrafficEnv(scenes, 3, **kw)
    compiled = BatchedTrafficEnv(scenes, 3, compile="always", **kw)
    obs_e, _ = eager.reset()
    obs_c, _ = compiled.reset()
    rng = np.random.default_rng(0)
    restarts = 0
    for _ in range(90):  # episodes end at step 90: every slot restarts once
        # Near the log: far from it, the projection on the logged route (progress) can jump
        # between two equally distant route segments on a rounding difference.
        noise = rng.normal(0.0, 0.3, (3, eager.num_agents, 2)).astype(np.float32)
        a = eager.expert_actions() + torch.from_numpy(noise)
        obs_e, rew_e, term_e, trunc_e, info_e = eager.step(a)
        obs_c, rew_c, term_c, trunc_c, info_c = compiled.step(a)
        assert torch.equal(term_e, term_c) and torch.equal(trunc_e, trunc_c)
        torch.testing.assert_close(rew_c, rew_e, atol=1e-4, rtol=0)
        for key, want in obs_e.items():
            if want.dtype == torch.int64:
                assert torch.equal(obs_c[key], want), key
            else:
                torch.testing.assert_close(obs_c[key], want, atol=1e-4, rtol=0, msg=key)
        restarts += int(info_e["done"].sum())
    assert restarts >= 3


def test_compile_takes_the_graph_only_where_it_pays_on_the_cpu():
    """``compile=True`` on the CPU: the graph for a batch of one, eager (with a warning that says
    so) beyond ``COMPILE_CPU_MAX_BATCH``; ``"always"`` forces the graph; other values refused.
    Building a StepFunction compiles nothing (that happens on the first call)."""
    config = StepConfig(EnvConfig(), ObsConfig(), dense=True)
    assert StepFunction(config, compile=True, batch_size=1).compiled
    with pytest.warns(UserWarning, match="steps eagerly"):
        big = StepFunction(config, compile=True, batch_size=C.COMPILE_CPU_MAX_BATCH + 1)
    assert not big.compiled
    with pytest.warns(UserWarning, match="steps eagerly"):
        crowded = StepFunction(config, True, 2, observers=C.COMPILE_CPU_MAX_OBSERVERS + 1)
    assert not crowded.compiled
    assert StepFunction(config, compile="always", batch_size=64).compiled
    assert not StepFunction(config, compile=False, batch_size=1).compiled
    with pytest.raises(ValueError, match="compile must be"):
        StepFunction(config, compile="fast")
