"""One policy registry: a policy registered by a user works in every part of tbsim."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from policies import make_policy, make_rollout_fn, policy_names, register_policy
from policies.registry import _REGISTRY
from tbsim_env.cli import app as cli
from tbsim_env.data.generator import default_scenarios
from tbsim_env.env import BatchedTrafficEnv, TrafficEnv
from tbsim_env.evaluation import evaluate_policy
from tbsim_env.metrics.wosac.submission import read_submission


class Braking:
    """Every agent brakes at ``decel`` m/s^2 (a toy policy of the test)."""

    name = "test_braking"
    exact_replay = False

    def __init__(self, decel: float = 2.0) -> None:
        self.decel = decel

    def initial_state(self, state, scenarios, generator):
        return None

    def act(self, state, policy_state, generator):
        action = torch.zeros(*state.pose.shape[:2], 2, device=state.device)
        action[..., 0] = -self.decel * (state.speed > 0.1)
        return action, policy_state


@pytest.fixture(scope="module")
def braking():
    register_policy("test_braking", Braking, summary="brakes (test)")
    yield "test_braking"
    _REGISTRY.pop("test_braking")


@pytest.fixture(scope="module")
def scenes():
    return default_scenarios(2)


def test_it_is_listed_and_built(braking):
    assert braking in policy_names() and braking in policy_names(agents=True)
    assert make_policy(braking, decel=3.0).decel == 3.0
    with pytest.raises(ValueError, match="already registered"):
        register_policy(braking, Braking)


def test_it_drives_the_npcs_of_both_envs(braking, scenes):
    env = TrafficEnv(scenes, npc_policy=braking)
    env.reset(seed=0)
    npc = env.episode.setup.npc[0]
    speed0 = env.sim_state.speed[0, npc].clone()
    for _ in range(10):
        env.step({a: np.zeros(2, np.float32) for a in env.agents})
    moving = speed0 > 1.0
    assert moving.any() and (env.sim_state.speed[0, npc][moving] < speed0[moving] - 0.5).all()
    venv = BatchedTrafficEnv(scenes, 2, npc_policy=braking, seed=0)
    venv.reset()
    venv.step(torch.zeros(2, venv.num_agents, 2))
    assert venv.npc_policy.name == braking


def test_it_is_evaluated_and_exported(braking, scenes, tmp_path):
    fn = make_rollout_fn(braking)
    rollouts = fn(scenes[0], 2, 0)
    assert rollouts.x.shape[0] == 2
    scores, _ = evaluate_policy(scenes[:1], braking, num_rollouts=2, seed=0)
    assert len(scores) == 1 and np.isfinite(scores[0].realism_meta_metric)
    with pytest.raises(ValueError, match="takes no checkpoint"):
        make_rollout_fn(braking, checkpoint="weights.safetensors")


def test_the_cli_offers_it(braking, tmp_path, capsys, one_scenario_path):
    out = tmp_path / "sub.binproto"
    args = ["export-wosac", "--data", str(one_scenario_path), "--out", str(out)]
    assert cli.main([*args, "--policy", braking, "--rollouts", "2"]) == 0
    assert len(read_submission(out).scenario_rollouts) == 1
    with pytest.raises(SystemExit):
        cli.main([*args, "--policy", "nope"])
    assert "invalid choice" in capsys.readouterr().err
    view = tmp_path / "view.html"
    assert cli.main(["view", str(one_scenario_path), "--policy", braking, "--rollouts", "1",
                     "--out", str(view)]) == 0  # fmt: skip
    assert view.stat().st_size > 10_000


def test_a_rollouts_only_name_cannot_drive_agents():
    with pytest.raises(ValueError, match="cannot drive agents"):
        make_policy("linear_extrapolation")
    assert "linear_extrapolation" not in policy_names(agents=True)
