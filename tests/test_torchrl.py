"""TorchRL adapter (``tbsim_env.integrations.torchrl``): specs, partial resets, exact values.

Skips when TorchRL is not installed (the ``torchrl`` extra, part of the ``test`` extra).
"""

from __future__ import annotations

import pytest
import torch

pytest.importorskip("torchrl", reason="TorchRL is not installed (pip install -e '.[torchrl]')")

from torchrl.envs.utils import check_env_specs  # noqa: E402

from tbsim_env.core.config import EnvConfig  # noqa: E402
from tbsim_env.data.generator import default_scenarios  # noqa: E402
from tbsim_env.env import BatchedTrafficEnv  # noqa: E402
from tbsim_env.integrations.torchrl import TorchRLTrafficEnv  # noqa: E402

SHORT = EnvConfig(end_step=18)  # 8-step episodes: restarts within a short rollout
KW = dict(controlled="all", npc_policy="constant_velocity", config=SHORT)


@pytest.fixture(scope="module")
def scenes():
    return default_scenarios(2)


def _random_actions(env: TorchRLTrafficEnv, steps: int, seed: int) -> torch.Tensor:
    """[steps, B, Q, 2] actions within the action bounds, from a seeded generator."""
    g = torch.Generator().manual_seed(seed)
    high = torch.as_tensor(env.env.action_high)
    b, q = env.batch_size[0], env.num_agents
    return (torch.rand(steps, b, q, 2, generator=g) * 2 - 1) * high


@pytest.mark.parametrize("layout", ["dense", "indexed"])
def test_check_env_specs(scenes, layout, torch_one_thread):
    env = TorchRLTrafficEnv(scenarios=scenes, batch_size=2, seed=0, obs_layout=layout, **KW)
    check_env_specs(env, break_when_any_done="both", seed=1)
    spec, q = env.full_done_spec, env.num_agents
    assert spec["done"].shape == (2, 1)
    assert spec["agents", "done"].shape == (2, q, 1)
    assert env.full_action_spec["agents", "action"].shape == (2, q, 2)
    obs_spec = env.observation_spec
    if layout == "dense":
        assert obs_spec["agents", "observation", "map"].shape == (2, q, 64, 20, 4)
        assert "tokens" not in obs_spec.keys()
    else:
        assert obs_spec["agents", "observation", "index"].shape == (2, q, 25 + 64 + 25)
        n = env.env.bank.start.pose.shape[1]  # agent slots of the bank
        rows = min(n, q * (1 + 25))  # per slot, or per observer and neighbour when fewer
        assert obs_spec["tokens", "agent_tokens"].shape[:2] == (2, rows)


def _obs_entry(td, env: TorchRLTrafficEnv, key: str) -> torch.Tensor:
    """Where a BatchedTrafficEnv observation key lives in the TorchRL TensorDict."""
    if key == "scene":
        return td["scenario_index"]
    if key in ("agent_tokens", "light_tokens"):
        return td["tokens", key]
    return td["agents", "observation", key]


@pytest.mark.parametrize("layout", ["dense", "indexed"])
def test_values_equal_batched_env_across_restarts(scenes, layout, torch_one_thread):
    """Stepping through TorchRL (step_and_maybe_reset) gives BatchedTrafficEnv's values."""
    env = TorchRLTrafficEnv(scenarios=scenes, batch_size=2, seed=5, obs_layout=layout, **KW)
    ref = BatchedTrafficEnv(scenes, 2, seed=5, obs_layout=layout, **KW)
    actions = _random_actions(env, 20, seed=0)
    td = env.reset()
    ref_obs, ref_info = ref.reset()
    restarts = 0
    for t in range(len(actions)):
        for k, v in ref_obs.items():
            assert torch.equal(_obs_entry(td, env, k), v), k
        assert torch.equal(td["agents", "mask"], ref_info["agent_mask"])
        td["agents", "action"] = actions[t]
        data, td = env.step_and_maybe_reset(td)
        ref_obs, rew, term, trunc, ref_info = ref.step(actions[t])
        nxt = data["next"]
        assert torch.equal(nxt["agents", "reward"][..., 0], rew)
        assert torch.equal(nxt["agents", "truncated"][..., 0], trunc)
        assert torch.equal(nxt["done"][:, 0], ref_info["done"])
        for k, v in ref_info["final_obs"].items():  # the true last observation
            assert torch.equal(_obs_entry(nxt, env, k), v), k
        assert torch.equal(nxt["agents", "info", "progress"], ref_info["progress"])
        assert torch.equal(nxt["scenario_index"], ref_info["scenario_index"])
        restarts += int(ref_info["done"].sum())
    assert restarts >= 2  # both slots went through a restart


def test_random_rollout_across_autoreset(scenes, torch_one_thread):
    """A random-policy rollout longer than an episode: done flags, masks and restarts."""
    env = TorchRLTrafficEnv(scenarios=scenes, batch_size=2, seed=2, **KW)
    data = env.rollout(20, break_when_any_done=False)
    assert data.shape == (2, 20)
    nxt = data["next"]
    done = nxt["done"][..., 0]  # [B, T]
    # 8-step episodes unless every agent ends earlier
    assert bool(done[:, 7].all()) or bool(done[:, :7].any())
    assert int(done.sum()) >= 2
    # after a slot's episode ended, the root of the next step is a fresh start
    b, t = done[:, :-1].nonzero(as_tuple=True)
    assert len(b) > 0
    assert not data["done"][b, t + 1].any()
    assert data["agents", "mask"][b, t + 1].any(-1).all()
    assert not data["agents", "done"][b, t + 1].any()
    # per agent: done == ended in this step: it acted and is not active after the step
    acted, alive = data["agents", "mask"], nxt["agents", "mask"]
    assert torch.equal(nxt["agents", "done"][..., 0], acted & ~alive)
    assert torch.equal(nxt["agents", "done"][done], acted[done][..., None])
    # slot terminated / truncated split the slot's done
    assert torch.equal(nxt["terminated"] | nxt["truncated"], nxt["done"])
    assert not (nxt["terminated"] & nxt["truncated"]).any()


def test_agent_mask(scenes, torch_one_thread):
    """The mask marks active agents; inactive ones get zero observations and rewards and
    are never done (done marks the step an agent ends)."""
    env = TorchRLTrafficEnv(scenarios=scenes, batch_size=2, seed=4, **KW)
    td = env.reset()
    n_agents = [len(names) for names in env.env.agent_names]
    mask = td["agents", "mask"]
    for b, k in enumerate(td["scenario_index"].tolist()):
        assert int(mask[b].sum()) == n_agents[k]
        assert not mask[b, n_agents[k] :].any()  # padding slots
    assert torch.equal(env.env.agent_mask, mask)
    # an agent drives off at full speed into the others: collisions end some agents early
    actions = _random_actions(env, 7, seed=3)
    data = env.rollout(7, policy=_ReplayPolicy(actions), break_when_any_done=False)
    nxt = data["next"]
    m = nxt["agents", "mask"]
    ended_early = (~m[:, :-1] & data["agents", "mask"][:, :-1]).any()
    assert ended_early, "no agent ended before the episode end in this rollout"
    acted = data["agents", "mask"]
    # the next observation is the last one of agents that ended in this step, zero for
    # agents that did not act
    assert not nxt["agents", "observation", "ego_history"][~acted].any()
    assert nxt["agents", "observation", "ego_history_mask"][acted & ~m].any(-1).all()
    assert not nxt["agents", "reward"][~acted].any()
    done = nxt["agents", "done"][..., 0]
    assert not done[~acted].any()
    assert torch.equal(
        done, nxt["agents", "terminated"][..., 0] | nxt["agents", "truncated"][..., 0]
    )
    # an agent that ended stays inactive until its slot restarts
    slot_done = nxt["done"][..., 0]
    for t in range(done.shape[1] - 1):
        gone = ~slot_done[:, t, None] & done[:, t]
        assert not acted[:, t + 1][gone].any()


def test_partial_reset_rules(scenes, torch_one_thread):
    env = TorchRLTrafficEnv(scenarios=scenes, batch_size=2, seed=0, **KW)
    td = env.reset()
    td["agents", "action"] = torch.zeros(2, env.num_agents, 2)
    env.step(td)
    bad = td.empty()
    bad["_reset"] = torch.tensor([[True], [False]])
    with pytest.raises(RuntimeError, match="only the slots whose episode ended"):
        env.reset(bad)
    assert env.reset()["agents", "mask"].any()  # a full reset always works


class _ReplayPolicy:
    """Writes actions[t] [B, Q, 2] into ("agents", "action") at the t-th call."""

    def __init__(self, actions: torch.Tensor) -> None:
        self.actions, self.t = actions, 0

    def __call__(self, td):
        td["agents", "action"] = self.actions[self.t]
        self.t += 1
        return td


def test_mappo_example_tiny_run(tmp_path, monkeypatch, torch_one_thread):
    """examples/torchrl_mappo.py: two iterations on one scene write the curve and finite stats."""
    import importlib.util
    import math
    import sys

    from tests.conftest import REPO

    path = REPO / "examples" / "torchrl_mappo.py"
    spec = importlib.util.spec_from_file_location("torchrl_mappo", path)
    module = importlib.util.module_from_spec(spec)
    monkeypatch.setitem(sys.modules, "torchrl_mappo", module)  # its dataclass looks it up
    spec.loader.exec_module(module)
    png = tmp_path / "curve.png"
    argv = ["--iterations=2", "--num-envs=2", "--num-scenes=1", "--num-steps=12"]
    rows = module.main([*argv, "--update-epochs=1", f"--plot={png}"])
    assert [r["iteration"] for r in rows] == [1, 2]
    assert rows[1]["agent_steps"] > rows[0]["agent_steps"] > 0
    assert all(math.isfinite(r["approx_kl"]) and math.isfinite(r["v_loss"]) for r in rows)
    assert png.stat().st_size > 10_000


# torchrl's own collector module warns about its deprecated weight updaters at import
@pytest.mark.filterwarnings("ignore:Creating .*WeightUpdater:DeprecationWarning")
def test_collector_trajectories_follow_episodes(scenes, torch_one_thread):
    """A TorchRL collector resets finished slots itself; its trajectory ids change exactly
    where an agent or a slot ended (agent done flags are events)."""
    from torchrl.collectors import Collector

    env = TorchRLTrafficEnv(scenarios=scenes, batch_size=2, seed=0, **KW)
    collector = Collector(env, None, frames_per_batch=2 * 12, total_frames=2 * 12)
    try:
        (data,) = list(collector)
    finally:
        collector.shutdown()
    assert data.shape == (2, 12)
    assert data["next", "done"].any()
    ids = data["collector", "traj_ids"]
    ended = data["next", "done"][..., 0] | data["next", "agents", "done"][..., 0].any(-1)
    assert torch.equal(ids[:, 1:] != ids[:, :-1], ended[:, :-1])
