"""The recipes of the docs' "Extending tbsim" page (docs/extending.md) run as written.

Each recipe is a fenced block preceded by a ``<!-- recipe: NAME -->`` line; the tests take the
blocks from the page itself, so the page cannot drift from the code. Whatever a recipe
registers (a policy name, a reward term) is removed again after its test.
"""

from __future__ import annotations

import inspect
import re
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from policies import registry
from tbsim_env.env import rewards

DOCS = Path(__file__).resolve().parents[1] / "docs"
PAGE = DOCS / "extending.md"
OBSERVATION_TABLE_PAGE = DOCS / "environments.md"
RECIPES = {
    "policy-module",
    "policy",
    "policy-entry-point",
    "reward-term",
    "reader",
    "observation-key",
}

pytestmark = pytest.mark.usefixtures("torch_one_thread")


def recipes() -> dict[str, str]:
    """{name: code} of every marked block of the page."""
    text = PAGE.read_text()
    found = re.findall(r"<!-- recipe: (\S+) -->\n```\w+\n(.*?)\n```", text, flags=re.S)
    names = [name for name, _ in found]
    assert len(names) == len(set(names)), f"a recipe name is used twice: {names}"
    return dict(found)


def run(code: str) -> dict:
    """Execute a recipe as a script and return its globals."""
    namespace: dict = {"__name__": "__recipe__"}
    exec(compile(code, "<docs recipe>", "exec"), namespace)
    return namespace


@pytest.fixture()
def workdir(tmp_path, monkeypatch):
    """An empty current folder on ``sys.path``, left clean of the recipes' modules and names."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.syspath_prepend(str(tmp_path))
    yield tmp_path
    sys.modules.pop("my_policies", None)
    registry._REGISTRY.pop("cruise", None)
    rewards._TERMS.pop("speeding", None)


def test_the_page_holds_every_recipe():
    assert set(recipes()) == RECIPES


def test_a_registered_policy_drives_npcs_and_is_evaluated(workdir):
    code = recipes()
    (workdir / "my_policies.py").write_text(code["policy-module"])
    ns = run(code["policy"])
    env = ns["env"]
    assert env.npc_policy.name == "cruise"
    assert "cruise" in registry.policy_names(agents=True)
    # The NPCs follow the policy: those not yet at 10 m/s sped up by about 0.1 m/s per step.
    npc = env.episode.setup.npc[0]
    before = env.sim_state.speed[0, npc].clone()
    slow = env.sim_state.valid[0, npc] & (before < 9.0)
    env.step({a: np.zeros(2, np.float32) for a in env.agents})
    # Every NPC below the target speeds up by 1 m/s^2 for one 0.1 s step.
    assert slow.sum() > 3
    after = env.sim_state.speed[0, npc]
    torch.testing.assert_close(after[slow], before[slow] + 0.1, atol=1e-4, rtol=0)
    meta = ns["scores"][0].realism_meta_metric
    assert 0.0 < meta < 1.0


def _entry_point(code: str) -> tuple[str, str, str]:
    """(group, name, "module:function") of the recipe's pyproject table."""
    group = re.search(r'^\[project\.entry-points\."([^"]+)"\]$', code, flags=re.M)
    value = re.search(r'^(\w+) = "([\w.]+:\w+)"$', code, flags=re.M)
    assert group and value, code
    return group.group(1), value.group(1), value.group(2)


def test_the_entry_point_makes_the_command_line_offer_the_policy(
    workdir, monkeypatch, one_scenario_path
):
    from tbsim_env.cli import app as cli

    code = recipes()
    group, name, target = _entry_point(code["policy-entry-point"])
    assert group == registry.ENTRY_POINT_GROUP
    # An installed distribution declaring that entry point, as pip would leave it.
    (workdir / "my_policies.py").write_text(code["policy-module"])
    info = workdir / "my_policies-0.1.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: my-policies\nVersion: 0.1\n")
    (info / "entry_points.txt").write_text(f"[{group}]\n{name} = {target}\n")
    monkeypatch.setattr(registry, "_entry_points_loaded", False)
    assert "cruise" not in registry._REGISTRY
    argv = ["evaluate", "--data", str(one_scenario_path), "--policy", "cruise"]
    assert cli.main([*argv, "--rollouts", "2"]) == 0
    assert registry.policy_entry("cruise").summary


def test_a_registered_reward_term_is_weighted_into_the_reward(workdir):
    ns = run(recipes()["reward-term"])
    env, reward, info = ns["env"], ns["reward"], ns["info"]
    terms = info["reward_terms"]
    speeding = terms["speeding"]
    assert speeding.shape == reward.shape and (speeding > 0).any()
    weights = rewards.reward_weights(ns["config"].reward)
    assert weights["speeding"] == -0.1
    total = sum(w * terms[n].float() for n, w in weights.items())
    torch.testing.assert_close(reward, total)
    assert tuple(reward.shape) == (2, env.num_agents)


def test_a_reader_feeds_its_scenes_to_the_environment(workdir):
    from tbsim_env.core.errors import ScenarioFormatError
    from tbsim_env.data.generator import generate_scenario

    ns = run(recipes()["reader"])
    read, original = ns["read_npz"], generate_scenario("merge", seed=0)
    scene = read(workdir / "merge_0.npz")
    assert scene.scenario_id == original.scenario_id
    np.testing.assert_array_equal(scene.tracks.xyz, original.tracks.xyz)
    np.testing.assert_array_equal(scene.road_map.polylines[3], original.road_map.polylines[3])
    assert ns["env"].agents == ns["env"].possible_agents and ns["env"].agents
    # The reader's validate() refuses what no real scene holds, naming the field.
    with np.load(workdir / "merge_0.npz") as f:
        arrays = dict(f)
    arrays["size"] = -arrays["size"]
    np.savez(workdir / "bad.npz", **arrays)
    with pytest.raises(ScenarioFormatError, match="length"):
        read(workdir / "bad.npz")


def _observation_key_parts(code: str) -> tuple[str, str]:
    """The recipe's OBS_KEYS entry and dense_views dict entry, each without its comment line."""
    parts = re.split(r"^# .*$\n", code, flags=re.M)
    spec, value = (p.strip().rstrip(",") for p in parts if p.strip())
    return spec, value


def test_the_observation_key_recipe_fits_the_spec_and_densify():
    from tbsim_env import TrafficEnv, observation
    from tbsim_env.observation.spec import OBS_KEYS, ObsKey, observation_table

    spec_code, value_code = _observation_key_parts(recipes()["observation-key"])
    key = eval(spec_code, {"ObsKey": ObsKey, "_INF": float("inf")})
    assert isinstance(key, ObsKey) and key.name not in [k.name for k in OBS_KEYS]
    # The names the recipe uses are densify's.
    source = inspect.getsource(observation.dense_views)
    for name in re.findall(r"\b(pose|mask|ka|km|kt|ego|nb|mp)\b", value_code):
        assert re.search(rf"\b{name}\b", source), name
    env = TrafficEnv(None, controlled="all", npc_policy="log_replay")
    obs, _ = env.reset(seed=0)
    for agent_obs in obs.values():
        pose, ka = agent_obs["agents_pose"], env.obs_config.num_agents  # dense_views' names
        values = eval("{" + value_code + "}", {"pose": pose, "ka": ka})[key.name]
        values = torch.as_tensor(values)
        shape = tuple(env.obs_config.num_agents if d == "Ka" else d for d in key.dims)
        assert tuple(values.shape) == shape
        assert ((values >= key.low) & (values <= key.high)).all()
        masked = torch.as_tensor(agent_obs["agents_mask"]) == 0
        assert (values[masked] == 0).all() and (values[~masked] > 0).all()
    # The docs' table is the one the recipe tells to paste over.
    assert observation_table() in OBSERVATION_TABLE_PAGE.read_text()
