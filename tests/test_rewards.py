"""Rewards: a weighted sum of named terms (``tbsim_env.env.rewards``), in both environments."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tbsim_env.core.config import EnvConfig, RewardConfig, TerminationConfig
from tbsim_env.data.generator import default_scenarios
from tbsim_env.env import BatchedTrafficEnv, TrafficEnv
from tbsim_env.env.agent_metrics import StepMetrics
from tbsim_env.env.rewards import (
    REWARD_TERM_NAMES,
    Baseline,
    register_reward_term,
    reward_and_termination,
)

SHAPE = (4, 50)


def _random_step(gen: torch.Generator) -> tuple[StepMetrics, torch.Tensor, Baseline]:
    flag = lambda: torch.rand(SHAPE, generator=gen) > 0.7  # noqa: E731
    pos = lambda: torch.rand(SHAPE, generator=gen) * 5  # noqa: E731
    metrics = StepMetrics(
        collision=flag(),
        offroad=flag(),
        offroad_distance=pos() - 2,
        progress=pos(),
        goal_distance=pos(),
        log_divergence=pos(),
        log_valid=flag(),
    )
    baseline = Baseline(
        progress_best=pos(),
        goal_reached=torch.rand(SHAPE, generator=gen) > 0.5,
        has_goal=torch.rand(SHAPE, generator=gen) > 0.2,
    )
    return metrics, pos() * 3, baseline


@pytest.fixture(scope="module")
def speeding():
    """A user term: m/s above 10, registered for this module."""
    register_reward_term("test_speeding", lambda x: (x.speed - 10.0).clamp_min(0.0))
    return "test_speeding"


def test_reward_is_the_weighted_sum_of_its_named_terms(speeding):
    gen = torch.Generator().manual_seed(3)
    configs = [
        RewardConfig(),
        RewardConfig(collision=0.0, offroad=0.0, progress=0.0, goal=0.0),
        RewardConfig(log_divergence=-0.1, alive=0.5),
        RewardConfig(collision=-2.0, progress=0.0, alive=-0.0, terms={speeding: -0.3}),
    ]
    ends = [
        TerminationConfig(),
        TerminationConfig(False, False, False),
        TerminationConfig(True, True, False),
    ]
    for rc in configs:
        for tc in ends:
            m, speed, base = _random_step(gen)
            out = reward_and_termination(m, speed, base, rc, tc)
            weights = {n: getattr(rc, n) for n in REWARD_TERM_NAMES} | dict(rc.terms)
            assert set(out.terms) == {n for n, w in weights.items() if w != 0.0}
            # The property: reward = sum of weight * term over the named terms.
            total = sum((weights[n] * out.terms[n].float() for n in out.terms), torch.zeros(SHAPE))
            torch.testing.assert_close(out.reward, total, rtol=0, atol=1e-5)
            # And each term is what its name says.
            gained = (m.progress - base.progress_best).clamp_min(0.0)
            goal_now = (m.goal_distance <= rc.goal_radius) & base.has_goal & ~base.goal_reached
            ref = (
                rc.collision * m.collision
                + rc.offroad * m.offroad
                + rc.progress * gained
                + rc.goal * goal_now
                + rc.log_divergence * m.log_divergence
                + rc.alive
                + dict(rc.terms).get(speeding, 0.0) * (speed - 10.0).clamp_min(0.0)
            ).float()
            torch.testing.assert_close(out.reward, ref, rtol=0, atol=1e-5)
            term = (m.collision & tc.collision) | (m.offroad & tc.offroad) | (goal_now & tc.goal)
            assert torch.equal(out.terminated, term) and torch.equal(out.goal_now, goal_now)


def test_unknown_or_builtin_terms_are_refused(speeding):
    with pytest.raises(ValueError, match="not a registered reward term"):
        BatchedTrafficEnv(
            default_scenarios(1), config=EnvConfig(reward=RewardConfig(terms={"nope": 1.0}))
        )
    with pytest.raises(ValueError, match="built-in"):
        register_reward_term("collision", lambda x: x.gained)
    with pytest.raises(ValueError, match="twice"):
        bad = RewardConfig(terms=((speeding, 1.0), (speeding, 2.0)))
        BatchedTrafficEnv(default_scenarios(1), config=EnvConfig(reward=bad))


def test_a_registered_term_drives_both_envs_alike(speeding):
    scenes = default_scenarios(2)
    cfg = EnvConfig(reward=RewardConfig(progress=0.0, goal=0.0, terms={speeding: -1.0}))
    env = TrafficEnv(scenes, npc_policy="log_replay", config=cfg)
    venv = BatchedTrafficEnv(scenes, 1, npc_policy="log_replay", config=cfg)
    env.reset(seed=0)
    venv.reset(scenario_indices=[0])
    penalised = 0
    for _ in range(40):
        a = env.agents[0]
        act = np.array([5.0, 0.0], np.float32)  # full throttle: soon above 10 m/s
        _, rew, _, _, info = env.step({a: act})
        _, vrew, _, _, vinfo = venv.step(torch.from_numpy(act).view(1, 1, 2))
        speed = info[a]["speed"]
        want = -max(speed - 10.0, 0.0) - float(info[a]["collision"]) - float(info[a]["offroad"])
        assert rew[a] == pytest.approx(want, abs=1e-5)
        assert float(vrew[0, 0]) == rew[a]
        assert float(vinfo["reward_terms"][speeding][0, 0]) == pytest.approx(max(speed - 10, 0))
        assert info[a]["reward_terms"][speeding] == pytest.approx(max(speed - 10, 0), abs=1e-5)
        assert set(info[a]["reward_terms"]) == {"collision", "offroad", speeding}
        penalised += speed > 10.0
        if not env.agents:
            break
    assert penalised > 5
