"""Indexed observations: pairwise-relative, frame-free, and a fraction of the dense bytes."""

from __future__ import annotations

import pytest
import torch

from tbsim_env.data import load_scenarios
from tbsim_env.data.generator import default_scenarios
from tbsim_env.observation.tokens import (
    ObsConfig,
    build_map_context,
    densify,
    init_history,
    observation_shapes,
    observe_indexed,
)
from tbsim_env.sim.build import build_sim_state

pytestmark = pytest.mark.usefixtures("torch_one_thread")


def _observe(scenarios):
    state = build_sim_state(scenarios)
    cfg = ObsConfig()
    ctx = build_map_context(scenarios, state.origin, cfg)
    hist = init_history(state, cfg.history)
    observers = torch.arange(state.num_agents).expand(state.batch_size, -1).contiguous()
    return observe_indexed(state, hist, ctx, observers, cfg), state, cfg


@pytest.fixture(scope="module")
def real(womd_dir):
    return load_scenarios(womd_dir / "waymo-open-dataset" / "motion_data_one_scenario.tfrecord")


@pytest.mark.parametrize("which", ["real", "generated"])
def test_indexed_observation_is_invariant_to_rotation_and_translation(which, request):
    scenes = request.getfixturevalue("real") if which == "real" else default_scenarios(2)
    moved = [s.transformed(1.1, (3000.0, -1500.0)) for s in scenes]
    a, state, _ = _observe(scenes)
    b, _, _ = _observe(moved)
    valid = state.valid  # observers that exist (the others sit at the frame's origin)
    seen = a.mask.bool() & valid[:, :, None]
    assert seen.sum() > 100
    assert torch.equal(a.mask[valid], b.mask[valid])
    assert torch.equal(a.index[seen], b.index[seen])
    torch.testing.assert_close(a.pose[valid][..., :2], b.pose[valid][..., :2], atol=1e-3, rtol=0)
    # dyaw is wrapped to [-pi, pi): opposite lanes of a generated map sit on the seam.
    turn = torch.remainder(a.pose[valid][..., 2] - b.pose[valid][..., 2] + torch.pi, 2 * torch.pi)
    torch.testing.assert_close(turn, torch.full_like(turn, torch.pi), atol=1e-3, rtol=0)
    torch.testing.assert_close(a.agent_tokens[valid], b.agent_tokens[valid], atol=1e-3, rtol=0)
    torch.testing.assert_close(a.map_tokens, b.map_tokens, atol=1e-3, rtol=0)


def test_dense_layout_is_a_gather_of_the_indexed_one():
    obs, state, cfg = _observe(default_scenarios(2))
    dense = densify(obs, cfg.tokens.piece_segments)
    shapes = observation_shapes(cfg)
    b, q = obs.ego.shape
    assert {k: tuple(v.shape[2:]) for k, v in dense.items()} == shapes
    per_observer_dense = sum(v[0, 0].numel() for v in dense.values())
    per_observer_indexed = (obs.index[0, 0].numel() + obs.pose[0, 0].numel()) + (
        obs.mask[0, 0].numel() + 1
    )
    # The dense layout copies every seen token per observer; the indexed one refers to it.
    assert per_observer_dense > 9000 and per_observer_indexed < 700
    # A neighbour's dense history is its own token, as every observer that sees it sees it.
    ka = cfg.num_agents
    i, j, k = (obs.mask[..., :ka] > 0).nonzero()[0].tolist()
    slot = obs.index[i, j, k]
    h = cfg.history
    torch.testing.assert_close(
        dense["agents"][i, j, k].flatten(), obs.agent_tokens[i, slot, : h * 5], rtol=0, atol=0
    )
    torch.testing.assert_close(
        dense["ego_history"][i, j].flatten(), obs.agent_tokens[i, j, : h * 5], rtol=0, atol=0
    )


def test_the_observation_spec_builds_the_space_the_keys_and_the_docs_table():
    from pathlib import Path

    from tbsim_env.env import TrafficEnv
    from tbsim_env.observation.spec import OBS_KEYS, observation_table

    env = TrafficEnv(default_scenarios(1), controlled="all", npc_policy="log_replay")
    obs, _ = env.reset(seed=0)
    names = [k.name for k in OBS_KEYS]
    space = env.observation_space(env.agents[0])
    assert sorted(space.spaces) == sorted(names)  # gymnasium sorts a Dict's keys
    for agent_obs in obs.values():
        assert list(agent_obs) == names
        assert space.contains(agent_obs)
    page = (Path(__file__).resolve().parents[1] / "docs" / "environments.md").read_text()
    assert observation_table() in page, "the observation table of the docs differs from OBS_KEYS"


@pytest.mark.parametrize("which", ["real", "generated"])
def test_observer_mask_describes_listed_observers_as_without_it(which, request):
    """Masked-out observers see nothing; the listed ones (searched as a gathered list) see
    exactly what they see when every observer is described."""
    scenes = request.getfixturevalue("real") if which == "real" else default_scenarios(3)
    full, state, cfg = _observe(scenes)
    listed = state.valid & (
        torch.rand(state.valid.shape, generator=torch.Generator().manual_seed(0)) < 0.6
    )
    assert 0 < listed.sum() < listed.numel()
    ctx = build_map_context(scenes, state.origin, cfg)
    if which == "real":  # the grid's map search runs on the gathered list
        assert ctx.grid.cells.value.shape[-1] < ctx.pose.shape[1]
    hist = init_history(state, cfg.history)
    part = observe_indexed(state, hist, ctx, full.ego, cfg, observer_mask=listed)
    for key in ("index", "pose", "mask"):
        a, b = getattr(full, key), getattr(part, key)
        assert torch.equal(a[listed], b[listed]), key
        assert not b[~listed].any(), key
    assert full.mask[listed].sum() > 100
    assert torch.equal(full.agent_tokens, part.agent_tokens)
