"""TrafficBots does not depend on the world frame (issue 22): the same seed on a scene and on a
rotated + shifted copy of it gives the same futures, once the copy's are mapped back.

What is left between the two frames is float32 rounding (~1e-4 m for a move of 3.3 km), which
the closed loop amplifies in places (an agent whose actions oscillate step to step grows it
about threefold per step; a stop-or-go decision can tip), so a few agent-rollouts part by
decimetres; a frame dependence parts most of them. How much rounding is left depends on the
CPU's kernels, so the bounds below were measured, on the tests' scenes and settings, under
every kernel path that can be forced on one machine and against injected frame bugs
(``python bench/frame_invariance.py``; AMD EPYC with AVX-512, torch 2.13.0, numpy 2.4.6):

| per agent-rollout deviation | share <= 10 cm | p90 |
|---|---|---|
| move only: native, ATen AVX2 + numpy v3, ATen default + numpy baseline | >= 0.985 | <= 5 mm |
| bug: moved headings +1 mrad | <= 0.86 | >= 0.16 m |
| bug: moved tracks +2 cm against their map | <= 0.88 | >= 0.13 m |
| bug: moved headings +5 mrad, tracks +10 cm | <= 0.29 | >= 0.25 m |

The checks (share >= 0.95, p90 <= 2 cm) sit between the two: on the share 3.5 points from the
rounding and 7 from the smallest bug, on the p90 4x above the rounding and 6x below the bug.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch
from safetensors import safe_open
from safetensors.numpy import load_file, save_file

from policies.trafficbots.rollout import outside_boundary
from policies.trafficbots.wosac import load_default_model, trafficbots_rollouts
from tbsim_env.core.config import EnvConfig, TerminationConfig
from tbsim_env.data.cache import read_shard, write_shard
from tbsim_env.data.generator import generate_scenario
from tbsim_env.data.loader import load_scenarios
from tbsim_env.data.preprocess import preprocess_scenario
from tbsim_env.data.scenario import Scenario
from tbsim_env.env import TrafficEnv
from tests.test_preprocess_support import assert_tokens_equivariant

YAW, SHIFT = 1.1, (3000.0, -1500.0)
"""The move of the issue's reproduction: 1.1 rad about the origin, then (3000, -1500) m."""
TOLERANCE = 0.1
"""Metres an agent-rollout may part from its counterpart over the whole future."""
MIN_FRACTION = 0.95
"""Share of agent-rollouts that must stay within ``TOLERANCE`` (measured: >= 0.985 for the
move alone on every kernel path, <= 0.88 with the smallest injected bug)."""
MAX_P90 = 0.02
"""Metres the 90th percentile of the deviations may reach (measured: <= 5 mm for the move
alone, >= 0.13 m with the smallest injected bug)."""
SAMPLES, KEPT = 16, 4
"""Rollouts sampled and kept: the submission's 128 -> 32 selection at a quarter of 128 x 1/8."""
GENERATED = ("intersection", 10002)
"""A held-out generated scene (layout, seed): symmetric lanes, crosswalks and signals."""

pytestmark = [pytest.mark.usefixtures("torch_one_thread"), pytest.mark.float_sensitive]


def moved(scenario: Scenario) -> Scenario:
    """The scenario rotated by ``YAW`` about the origin and shifted by ``SHIFT``."""
    return scenario.transformed(YAW, SHIFT)


def map_back(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Moved-frame coordinates [...] (metres) -> the original frame, float64."""
    c, s = np.cos(-YAW), np.sin(-YAW)
    dx = np.asarray(x, np.float64) - SHIFT[0]
    dy = np.asarray(y, np.float64) - SHIFT[1]
    return c * dx - s * dy, s * dx + c * dy


def within(deviation: np.ndarray) -> float:
    """Share of the entries of ``deviation`` [...] (metres) within ``TOLERANCE``."""
    return float((deviation <= TOLERANCE).mean())


def assert_frame_free(deviation: np.ndarray) -> None:
    """The deviations [...] (metres) between a scene's and its moved copy's futures are
    rounding amplified by the closed loop, not a frame dependence (bounds measured above)."""
    worst = np.sort(deviation.ravel())[-10:]
    assert within(deviation) >= MIN_FRACTION, worst
    assert np.quantile(deviation, 0.9) <= MAX_P90, worst


@pytest.fixture(scope="module")
def model():
    return load_default_model()


@pytest.fixture(scope="module")
def real(one_scenario_path) -> Scenario:
    return load_scenarios(one_scenario_path)[0]


@pytest.fixture(scope="module")
def generated() -> Scenario:
    return generate_scenario(*GENERATED)


@pytest.fixture(params=["real", "generated"])
def scene(request) -> Scenario:
    return request.getfixturevalue(request.param)


def test_tokens_of_a_moved_scene_are_the_moved_tokens(scene):
    a, b = preprocess_scenario(scene), preprocess_scenario(moved(scene))
    assert_tokens_equivariant(a, b, YAW, atol=1e-4)


def test_wosac_rollouts_do_not_depend_on_the_world_frame(model, scene):
    a = trafficbots_rollouts(model, scene, num_rollouts=KEPT, num_samples=SAMPLES, seed=0)
    b = trafficbots_rollouts(model, moved(scene), num_rollouts=KEPT, num_samples=SAMPLES, seed=0)
    assert torch.equal(a.object_id, b.object_id)
    assert a.x.shape == (KEPT, len(a.object_id), 80)
    x, y = map_back(b.x.numpy(), b.y.numpy())
    deviation = np.hypot(x - a.x.numpy(), y - a.y.numpy()).max(-1)  # [R, A]
    assert_frame_free(deviation)
    x0, y0 = a.x.numpy(), a.y.numpy()
    moving = np.hypot(x0[..., -1] - x0[..., 0], y0[..., -1] - y0[..., 0])
    assert (moving > 5.0).mean() > 0.2  # not a scene of parked cars


def _env_positions(scenario: Scenario) -> tuple[np.ndarray, np.ndarray]:
    """Scenario-frame xy [S, N, 2] and validity [S, N] after each step of an episode with
    TrafficBots NPCs and log-following controlled agents (no termination)."""
    never = EnvConfig(termination=TerminationConfig(collision=False, goal=False))
    env = TrafficEnv(
        [scenario], npc_policy="trafficbots", controlled="tracks_to_predict", config=never
    )
    env.reset(seed=0)
    xy, valid = [], []
    while env.agents:
        env.step(env.expert_actions())
        s = env.sim_state
        xy.append((s.pose[0, :, :2].double() + s.origin[0]).numpy())
        valid.append(s.valid[0].numpy())
    return np.stack(xy), np.stack(valid)


def test_env_with_trafficbots_npcs_does_not_depend_on_the_world_frame(scene):
    xy_a, valid_a = _env_positions(scene)
    xy_b, valid_b = _env_positions(moved(scene))
    assert xy_a.shape[0] == 80
    np.testing.assert_array_equal(valid_a, valid_b)
    x, y = map_back(xy_b[..., 0], xy_b[..., 1])
    dist = np.where(valid_a, np.hypot(x - xy_a[..., 0], y - xy_a[..., 1]), 0.0)
    deviation = dist.max(0)[valid_a.any(0)]  # [agents]
    assert deviation.size > 20
    assert_frame_free(deviation)


def test_map_box_is_axis_aligned_in_the_sdc_frame(real):
    tok = preprocess_scenario(real)
    sdc_yaw = real.tracks.heading[real.sdc_index, real.current_index]
    assert float(tok.frame_yaw) == pytest.approx(float(sdc_yaw))
    # A point just inside the box's far x side, along the SDC's heading, is inside; a step
    # further out it is outside, whatever the token frame's orientation.
    box = torch.tensor([[*tok.map_boundary, float(tok.frame_yaw)]])
    c, s = np.cos(tok.frame_yaw), np.sin(tok.frame_yaw)
    inside = tok.map_boundary[1] - 0.5
    pts = torch.tensor([[[c * inside, s * inside], [c * (inside + 1), s * (inside + 1)]]])
    assert outside_boundary(pts.float(), box).tolist() == [[False, True]]


def test_shards_written_before_frame_yaw_read_with_a_zero_yaw(tmp_path, generated):
    tok = preprocess_scenario(generated)
    path = tmp_path / "shard.safetensors"
    write_shard([tok], path)
    with safe_open(str(path), framework="numpy") as f:
        meta = f.metadata()
    old = {k: v for k, v in load_file(str(path)).items() if k != "0.frame_yaw"}
    save_file(old, str(path), metadata=meta)
    (got,) = read_shard(path)
    assert got.frame_yaw.shape == () and float(got.frame_yaw) == 0.0
    np.testing.assert_array_equal(got.map_boundary, tok.map_boundary)
