"""Inference knobs behind the kinematic diagnosis (docs/model_card/kinematics.md): the
personality temperature, sampled actions and the tracker's jitter on the WOSAC rollouts."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from policies.trafficbots import TrafficBotsConfig
from policies.trafficbots.batch import TokenBatch
from policies.trafficbots.config import InferenceConfig
from policies.trafficbots.model import TrafficBots
from policies.trafficbots.rollout import rollout
from policies.trafficbots.rules import smooth_yaw_rate
from policies.trafficbots.wosac import record_rollouts
from tbsim_env.core import constants as C
from tbsim_env.core.config import TokenConfig
from tbsim_env.data.generator import generate_scenario
from tbsim_env.data.generator.recording import TRACKER
from tbsim_env.data.preprocess import preprocess_scenario
from tbsim_env.metrics.wosac.rollouts import log_replay_rollouts
from tbsim_env.sim.geometry import wrap_angle

pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def scenario():
    return generate_scenario("intersection", 4)


@pytest.fixture(scope="module")
def batch(scenario):
    return TokenBatch.from_tokens(preprocess_scenario(scenario, TokenConfig()))


def _model(**changes) -> TrafficBots:
    torch.manual_seed(0)
    model = TrafficBots(TrafficBotsConfig.small(), InferenceConfig(**changes))
    return model.eval()


def _prepare(model: TrafficBots, batch: TokenBatch, n: int = 3):
    return model.prepare(batch, n, torch.Generator().manual_seed(5))


@pytest.mark.parametrize("name", ["latent_temperature", "action_sigma"])
@pytest.mark.parametrize("value", [-0.1, float("nan"), float("inf")])
def test_bad_temperature_or_sigma_is_rejected(name, value):
    with pytest.raises(ValueError, match=name):
        InferenceConfig(**{name: value})


def test_spec_and_shipped_take_the_mean_action_of_the_prior():
    for cfg in (InferenceConfig(), InferenceConfig.spec()):
        assert cfg.latent_temperature == 1.0 and cfg.action_sigma == 0.0
    assert InferenceConfig.spec().recording is None


def test_latent_temperature_scales_z_and_keeps_the_destinations(batch):
    base = _prepare(_model(), batch)
    for t in (0.0, 0.5):
        ctx = _prepare(_model(latent_temperature=t), batch)
        torch.testing.assert_close(ctx.z, t * base.z)
        assert torch.equal(ctx.dest, base.dest)
        assert torch.equal(ctx.z_valid, base.z_valid)


def test_action_noise_is_drawn_after_z_and_the_destinations(batch):
    base = _prepare(_model(), batch)
    assert base.action_eps is None
    ctx = _prepare(_model(action_sigma=0.1), batch)
    assert torch.equal(ctx.z, base.z) and torch.equal(ctx.dest, base.dest)
    n_ag = batch.ag_type.shape[1]
    assert ctx.action_eps.shape == (3 * batch.n_scenes, n_ag, C.NUM_STEPS, 2)
    assert abs(float(ctx.action_eps.std()) - 1.0) < 0.1


def test_sampled_actions_scatter_around_the_mean_ones(batch):
    """The same steps with sigma 0 and sigma > 0: the squashed actions differ by about the
    limit times sigma (tanh' <= 1), and never leave the type's limits."""
    outs = []
    for sigma in (0.0, 0.05):
        model = _model(action_sigma=sigma, gap_keeping=None, hold_parked=False)
        ctx = _prepare(model, batch)
        with torch.no_grad():
            traj = rollout(model, ctx, batch.repeat(1), gt_steps=11, n_steps=16)
        outs.append(traj)
    valid = outs[0].valid[..., 1:] & outs[1].valid[..., 1:]
    diff = (outs[1].action - outs[0].action)[valid]  # [k, 2], steps 1..15
    limit = torch.tensor([max(C.MAX_ACCEL), max(C.MAX_YAW_RATE)])
    assert float(diff.abs().max(0).values.div(limit).max()) <= 0.05 * 6
    assert bool((diff.abs() > 0).any())
    forced = outs[0].pose[:, :, :11]
    torch.testing.assert_close(outs[1].pose[:, :, :11], forced)


def test_recording_jitters_moving_tracks_only(scenario):
    exact = log_replay_rollouts(scenario, 4)
    rec = record_rollouts(scenario, exact, TRACKER, seed=3)
    again = record_rollouts(scenario, exact, TRACKER, seed=3)
    other = record_rollouts(scenario, exact, TRACKER, seed=4)
    assert torch.equal(rec.x, again.x) and torch.equal(rec.heading, again.heading)
    assert not torch.equal(rec.x, other.x)
    assert torch.equal(rec.z, exact.z) and torch.equal(rec.object_id, exact.object_id)
    tr, t0 = scenario.tracks, scenario.current_index
    sim = scenario.sim_agent_indices()
    types = tr.object_type[sim]
    dx = torch.hypot(rec.x - exact.x, rec.y - exact.y)  # [R, A, F]
    dyaw = wrap_angle(rec.heading - exact.heading).abs()
    step = np.hypot(*np.diff(tr.xyz[sim, t0:, :2], axis=1).transpose(2, 0, 1)) / C.DT
    ok = torch.as_tensor(tr.valid[sim, t0 + 1 :] & tr.valid[sim, t0:-1])[None].expand_as(dx)
    standing = ok & torch.as_tensor(step == 0.0)[None]
    vehicle = torch.as_tensor(types == int(C.ObjectType.VEHICLE))[None, :, None].expand_as(dx)
    moving = vehicle & ok & torch.as_tensor(step >= 1.0)[None]
    assert bool((vehicle & standing).any()) and bool(moving.any())
    # Standing vehicles stay put, up to the float32 rounding of their coordinates.
    assert float(dx[vehicle & standing].max()) < 2e-3
    assert float(dyaw[vehicle & standing].max()) < 1e-4
    # Moving vehicles scatter by about the fitted jitter (log-normal per track and rollout).
    typical = float(dx[moving].median())
    assert 0.3 * TRACKER.jitter_along < typical < 3 * TRACKER.jitter_along
    assert float(dyaw[moving].median()) < 5 * TRACKER.jitter_heading


def test_recording_needs_every_sim_agent_in_track_order(scenario):
    exact = log_replay_rollouts(scenario, 2)
    swapped = dataclasses.replace(exact, object_id=exact.object_id.flip(0))
    with pytest.raises(ValueError, match="track order"):
        record_rollouts(scenario, swapped, TRACKER, seed=0)


def test_smooth_yaw_rate_mixes_in_the_last_step_only_where_it_exists():
    action = torch.tensor([[[1.0, 0.4], [2.0, -0.4], [3.0, 0.2]]])
    last = torch.tensor([[-0.4, 0.4, 1.0]])
    ok = torch.tensor([[True, True, False]])
    out = smooth_yaw_rate(action, last, ok, 0.5)
    torch.testing.assert_close(out[..., 0], action[..., 0])  # accelerations untouched
    torch.testing.assert_close(out[..., 1], torch.tensor([[0.0, 0.0, 0.2]]))
    steady = smooth_yaw_rate(action, action[..., 1], torch.ones_like(ok), 0.7)
    torch.testing.assert_close(steady, action)  # a steady turn stays as it is


def test_yaw_rate_smoothing_is_checked_and_off_in_the_spec():
    for bad in (-0.1, 1.0):
        with pytest.raises(ValueError, match="yaw_rate_smoothing"):
            InferenceConfig(yaw_rate_smoothing=bad)
    assert InferenceConfig.spec().yaw_rate_smoothing == 0.0


def test_yaw_rate_smoothing_mixes_the_networks_yaw_rate_with_the_last_one(batch):
    """At a step of the model: applied yaw rate = 0.5 * the squashed network's + 0.5 * the
    history's last yaw rate (the heading's finite difference), where the agent was valid at
    both steps; the network's own output is unchanged (``StepOutput.raw_action``)."""
    model = _model(yaw_rate_smoothing=0.5, gap_keeping=None, hold_parked=False)
    plain = _model(gap_keeping=None, hold_parked=False)
    ctx = _prepare(model, batch, n=1)
    states = [model.initial_state(ctx), plain.initial_state(ctx)]
    for t in range(C.CURRENT_INDEX + 2):
        valid = batch.ag_valid[..., t]
        pose = batch.ag_pose[..., t, :] * valid[..., None]
        now = (pose, batch.ag_motion[..., t, 0] * valid, valid, batch.tl_state[..., t])
        (out, states[0]), (ref, states[1]) = (
            m.step(ctx, st, *now) for m, st in zip((model, plain), states, strict=True)
        )
    torch.testing.assert_close(out.raw_action, ref.raw_action)
    ok = states[0].hist_valid[..., -1] & states[0].hist_valid[..., -2]
    assert bool(ok.any())
    want = 0.5 * ref.action[..., 1] + 0.5 * states[0].hist_motion[..., -1, 2]
    torch.testing.assert_close(out.action[..., 1][ok], want[ok])
    torch.testing.assert_close(out.action[..., 1][~ok], ref.action[..., 1][~ok])
    torch.testing.assert_close(out.action[..., 0], ref.action[..., 0])
