"""The pretrained TrafficBots weights shipped inside the package."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from policies.trafficbots import TrafficBotsConfig, load_checkpoint
from policies.trafficbots.wosac import DEFAULT_WEIGHTS, load_default_model, trafficbots_rollouts
from tbsim_env.core.config import EnvConfig, TerminationConfig
from tbsim_env.data.generator import generate_scenario
from tbsim_env.env import TrafficEnv

REFERENCE = Path(__file__).parent / "data" / "shipped_rollout_reference.json"
MAX_BYTES = 10 * 1024 * 1024


pytestmark = [pytest.mark.usefixtures("torch_one_thread"), pytest.mark.float_sensitive]


def test_weights_exist_within_the_size_limit():
    path = DEFAULT_WEIGHTS.with_suffix(".safetensors")
    assert path.exists(), f"missing {path}"
    assert path.stat().st_size <= MAX_BYTES
    assert DEFAULT_WEIGHTS.with_suffix(".json").exists()


def test_weights_load_with_the_small_config():
    model = load_default_model()
    assert model.cfg == TrafficBotsConfig.small()
    assert load_checkpoint(DEFAULT_WEIGHTS).cfg == model.cfg


def test_default_env_drives_a_full_episode_with_the_shipped_npcs():
    never = EnvConfig(termination=TerminationConfig(collision=False, goal=False))
    env = TrafficEnv(config=never)  # embedded scenes, shipped TrafficBots NPCs by default
    assert env.npc_policy.name == "trafficbots"
    env.reset(seed=0)
    a = env.agents[0]
    steps = 0
    while env.agents:
        env.step({a: env.expert_actions()[a]})
        steps += 1
        s = env.sim_state
        assert torch.isfinite(s.pose[s.valid]).all() and torch.isfinite(s.speed[s.valid]).all()
    assert steps == 80


def _reference_rollout() -> dict:
    sc = generate_scenario("merge", seed=10007)
    r = trafficbots_rollouts(load_default_model(), sc, num_rollouts=2, num_samples=2, seed=5)
    ids = r.object_id[:4].tolist()
    return {
        "scenario_id": sc.scenario_id,
        "object_id": ids,
        "x_step40": r.x[:, :4, 39].tolist(),
        "y_step40": r.y[:, :4, 39].tolist(),
        "heading_step40": r.heading[:, :4, 39].tolist(),
    }


def test_seeded_rollout_matches_stored_reference():
    """A regression guard: silent changes to the model code change these numbers. Across
    kernel paths (native AVX-512, ATen AVX2, ATen default with numpy's baseline) they moved by
    at most 1e-6 m and rad, a thousandth of the tolerance."""
    ref = json.loads(REFERENCE.read_text())
    got = _reference_rollout()
    assert got["object_id"] == ref["object_id"]
    for key in ("x_step40", "y_step40", "heading_step40"):
        np.testing.assert_allclose(got[key], ref[key], atol=1e-3, err_msg=key)


if __name__ == "__main__":  # regenerate the reference after a deliberate model change
    REFERENCE.parent.mkdir(exist_ok=True)
    REFERENCE.write_text(json.dumps(_reference_rollout(), indent=1))
    print(f"wrote {REFERENCE}")
