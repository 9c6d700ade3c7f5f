"""TrafficBots network: invariance, explicit-state step API, seeded sampling, paper size."""

from __future__ import annotations

import dataclasses
import time

import numpy as np
import pytest
import torch

import tbsim_env  # noqa: F401  (first: avoids the policies <-> tbsim_env.env import cycle)

# isort: split

from policies.trafficbots import (
    TokenBatch,
    TrafficBots,
    TrafficBotsConfig,
    rollout,
    sample_rollouts,
)
from policies.trafficbots.model import PrepareMode
from policies.trafficbots.synthetic import make_synthetic_tokens
from tbsim_env.data.tokens import SceneTokens

SPEC_USED_PARAMS = 7.9e6


pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def small_model() -> TrafficBots:
    torch.manual_seed(0)
    return TrafficBots(TrafficBotsConfig.small()).eval()


@pytest.fixture(scope="module")
def tokens() -> SceneTokens:
    return make_synthetic_tokens(n_agents=12, n_map=80, n_tl=6, seed=1)


def transform_tokens(tok: SceneTokens, yaw: float, shift: tuple[float, float]) -> SceneTokens:
    """Rotate the whole scene by ``yaw`` about the origin, then translate by ``shift``."""
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, -s], [s, c]], dtype=np.float64)

    def move(p: np.ndarray, valid: np.ndarray) -> np.ndarray:
        out = p.astype(np.float64).copy()
        out[..., :2] = p[..., :2] @ rot.T + np.asarray(shift)
        return np.where(valid[..., None], out, 0.0).astype(np.float32)

    def turn(v: np.ndarray) -> np.ndarray:
        out = v.astype(np.float64).copy()
        out[..., :2] = v[..., :2] @ rot.T
        return out.astype(np.float32)

    map_pos = move(tok.map_pos, tok.map_valid)
    nodes = map_pos[tok.map_valid]
    boundary = np.array(
        [nodes[:, 0].min(), nodes[:, 0].max(), nodes[:, 1].min(), nodes[:, 1].max()],
        dtype=np.float32,
    )
    return dataclasses.replace(
        tok,
        map_pos=map_pos,
        map_dir=turn(tok.map_dir),
        map_boundary=boundary,
        agent_pos=move(tok.agent_pos, tok.agent_valid),
        agent_vel=turn(tok.agent_vel),
        agent_yaw=np.where(tok.agent_valid, tok.agent_yaw + yaw, 0.0).astype(np.float32),
    )


def _run(model: TrafficBots, tok: SceneTokens, seed: int, n_steps: int):
    batch = TokenBatch.from_tokens(tok)
    with torch.no_grad():
        ctx = model.prepare(batch, 1, torch.Generator().manual_seed(seed), PrepareMode(dest="gt"))
        return rollout(model, ctx, batch, gt_steps=11, n_steps=n_steps, disable_outside_map=False)


def test_actions_invariant_to_rotation_and_translation(small_model, tokens) -> None:
    yaw, shift = 1.1, (37.0, -52.0)
    ref = _run(small_model, tokens, seed=3, n_steps=18)
    moved = _run(small_model, transform_tokens(tokens, yaw, shift), seed=3, n_steps=18)
    assert torch.equal(ref.valid, moved.valid)
    assert ref.action.abs().max() > 0.05  # the test is not vacuous
    assert torch.allclose(ref.action, moved.action, atol=1e-4)
    # Trajectories map back onto each other (free closed loop from step 11).
    c, s = np.cos(-yaw), np.sin(-yaw)
    xy = moved.pose[..., :2] - torch.tensor(shift)
    back = torch.stack([c * xy[..., 0] - s * xy[..., 1], s * xy[..., 0] + c * xy[..., 1]], -1)
    v = ref.valid
    assert torch.allclose(back[v], ref.pose[..., :2][v], atol=1e-3)
    assert torch.equal(ref.tl_state, moved.tl_state)


def test_step_api_reproduces_rollout_and_sees_external_agents(small_model, tokens) -> None:
    batch = TokenBatch.from_tokens(tokens)
    n_steps = 15
    with torch.no_grad():
        ctx = small_model.prepare(batch, 2, torch.Generator().manual_seed(0))
        traj = rollout(small_model, ctx, batch, gt_steps=11, n_steps=n_steps)
        state = small_model.initial_state(ctx)
        for t in range(1, n_steps):
            args = (traj.pose[:, :, t - 1], traj.speed[:, :, t - 1], traj.valid[:, :, t - 1])
            out, new_state = small_model.step(ctx, state, *args, traj.tl_state[:, :, t - 1])
            assert torch.equal(out.action, traj.action[:, :, t - 1])
            assert out.action.shape == (2, batch.ag_type.shape[1], 2)
            if t == n_steps - 1:
                # An externally controlled agent 0 reported 3 m to its left: others react.
                pose = args[0].clone()
                pose[:, 0, 1] += 3.0
                moved, _ = small_model.step(ctx, state, pose, *args[1:], traj.tl_state[:, :, t - 1])
                others = traj.valid[:, 1:, t - 1]
                diff = (moved.action[:, 1:] - out.action[:, 1:]).abs().amax(-1)
                assert (diff[others] > 1e-6).any()
            state = new_state
    assert state.step == n_steps - 1
    assert state.hist_valid.shape[-1] == 11
    # The input state is never mutated (explicit, functional state).
    assert small_model.initial_state(ctx).step == 0


def test_tl_features_are_kept_only_while_the_window_is_unchanged(small_model, tokens) -> None:
    """A scene whose lights held their state through the TL window keeps last step's TL
    features and is not encoded again; they equal a fresh encoding at every step."""
    batch = TokenBatch.from_tokens([tokens, tokens, tokens])
    n_b, n_tl = batch.tl_piece.shape
    steps = 30
    tl = torch.zeros(n_b, n_tl, steps, dtype=torch.long)
    tl[1, 0, 15:] = 3  # scene 1: one light changes at step 15
    tl[2, :, ::7] = 4  # scene 2: blinks every 7 steps (the window never settles)
    pose = batch.ag_pose[..., 10, :] * batch.ag_valid[..., 10, None]
    speed, valid = batch.ag_motion[..., 10, 0], batch.ag_valid[..., 10]
    encoded = []
    enc = small_model.tl_encoder
    # The encoder's PointNet runs once per encoding, on the rows encoded.
    hook = enc.pointnet.register_forward_hook(lambda m, args, out: encoded.append(out.shape[0]))
    per_step = []
    with torch.no_grad():
        ctx = small_model.prepare(batch, 1, torch.Generator().manual_seed(0))
        state = small_model.initial_state(ctx)
        for t in range(steps):
            encoded.clear()
            _, state = small_model.step(ctx, state, pose, speed, valid, tl[..., t])
            per_step.append(sum(encoded))
            fresh = enc(state.hist_tl_state, state.hist_tl_present, ctx.tl, ctx.scene.tl_map_kv)
            torch.testing.assert_close(state.tl_feat, fresh, rtol=0, atol=1e-5)
    hook.remove()
    assert batch.tl_valid.any() and state.tl_feat.abs().sum() > 0
    # Rows encoded per step: all 3 until the windows fill (11 steps), then scene 2 (every
    # step), scene 1 again from its change until the change leaves the window.
    want = [3] * 11 + [1] * 4 + [2] * 11 + [1] * 4
    assert per_step == want


def test_seeded_sampling_is_reproducible_and_seed_dependent(small_model, tokens) -> None:
    def sample(seed: int):
        return sample_rollouts(
            small_model, tokens, n=4, k=2, generator=torch.Generator().manual_seed(seed)
        )

    a, b, c = sample(0), sample(0), sample(1)
    assert a.pose.shape == (1, 2, 12, 91, 3)
    assert torch.equal(a.pose, b.pose) and torch.equal(a.index, b.index)
    assert not torch.allclose(a.pose[..., 11:, :], c.pose[..., 11:, :])
    # Warm start: steps 0..10 are the logged history; agents absent from history never spawn.
    gt = TokenBatch.from_tokens(tokens)
    hist_valid = gt.ag_valid[0, :, :11]
    got = a.pose[0, :, :, :11, :2]
    assert torch.allclose(
        got[:, hist_valid], gt.ag_pose[0, :, :11, :2][hist_valid][None], atol=1e-5
    )
    never = ~hist_valid.any(-1)
    assert never.any() and not a.valid[0][:, never].any()
    assert (a.score[0] >= 0).all() and a.collided.shape == (1, 2, 12)
    assert small_model.training is False


def test_sample_rollouts_keeps_fewest_collisions(tokens) -> None:
    # Same seed with k = n gives every rollout's score: the kept ones never score worse.
    torch.manual_seed(4)
    model = TrafficBots(TrafficBotsConfig.small())
    out = sample_rollouts(model, tokens, n=6, k=3, generator=torch.Generator().manual_seed(2))
    full = sample_rollouts(model, tokens, n=6, k=6, generator=torch.Generator().manual_seed(2))
    kept = set(out.index[0].tolist())
    worst_kept = out.score[0].max()
    dropped = [s for i, s in zip(full.index[0].tolist(), full.score[0].tolist()) if i not in kept]
    assert all(s >= worst_kept for s in dropped)
    assert torch.equal(out.score[0], full.score[0, :3])


def test_small_config_size() -> None:
    model = TrafficBots(TrafficBotsConfig.small())
    n = model.num_parameters()
    print(f"small config: {n:,} parameters")
    assert 2e5 < n < 2e6


def test_paper_config_size_and_full_scale_step() -> None:
    torch.manual_seed(0)
    model = TrafficBots(TrafficBotsConfig.paper()).eval()
    n = model.num_parameters()
    print(f"paper config: {n:,} parameters (spec: ~7.9 M used)")
    assert abs(n - SPEC_USED_PARAMS) / SPEC_USED_PARAMS < 0.10
    tok = make_synthetic_tokens(n_agents=64, n_map=1024, n_tl=128, seed=0)
    batch = TokenBatch.from_tokens(tok)
    with torch.no_grad():
        t0 = time.perf_counter()
        ctx = model.prepare(batch, 1, torch.Generator().manual_seed(0))
        t1 = time.perf_counter()
        state = model.initial_state(ctx)
        valid = batch.ag_valid[:, :, 0]
        args = (batch.ag_pose[:, :, 0], batch.ag_motion[:, :, 0, 0], valid, batch.tl_state[..., 0])
        out, state = model.step(ctx, state, *args)
        t2 = time.perf_counter()
    print(f"paper: prepare {1e3 * (t1 - t0):.0f} ms, one step {1e3 * (t2 - t1):.0f} ms")
    assert ctx.mp.feat.shape == (1, 1024, 128) and ctx.tl.map_idx.shape == (1, 128, 24)
    assert out.action.shape == (1, 64, 2) and out.tl_logits.shape == (1, 128, 5)
    assert torch.isfinite(out.action).all() and (out.action[valid] != 0).any()
    assert (out.action[~valid] == 0).all()


def test_sampling_on_the_real_scenario(one_scenario_path, small_model) -> None:
    from tbsim_env.data import load_scenarios
    from tbsim_env.data.preprocess import preprocess_scenario

    tok = preprocess_scenario(load_scenarios(one_scenario_path)[0])
    out = sample_rollouts(small_model, tok, n=2, k=1, generator=torch.Generator().manual_seed(0))
    gt = TokenBatch.from_tokens(tok)
    n_ag = gt.ag_type.shape[1]
    assert out.pose.shape == (1, 1, n_ag, 91, 3) and torch.isfinite(out.pose).all()
    hist = gt.ag_valid[0, :, :11]
    assert torch.allclose(out.pose[0, 0, :, :11][hist], gt.ag_pose[0, :, :11][hist], atol=1e-5)
    # Every agent present at the current step is simulated to the end unless it left the map.
    alive = out.valid[0, 0, :, -1]
    assert alive.sum() > 0 and not alive[~hist.any(-1)].any()
    moved = (out.pose[0, 0, :, -1, :2] - out.pose[0, 0, :, 10, :2]).norm(dim=-1)
    assert torch.isfinite(moved[alive]).all()


def test_trimmed_padding_changes_no_sample_and_no_step(small_model) -> None:
    """``TokenBatch.trim`` (what inference runs on) computes the function of the padded batch.

    A generated scene padded to the token limits (64 agents, 1024 pieces, 128 TL tokens):
    the same latents and destinations are drawn, and the closed-loop rollout agrees to float
    rounding (which grows in closed loop, so 30 steps are compared).
    """
    from tbsim_env.data.generator import generate_scenario
    from tbsim_env.data.preprocess import preprocess_scenario
    from tbsim_env.sim.geometry import wrap_angle

    full = TokenBatch.from_tokens(preprocess_scenario(generate_scenario("intersection", 10000)))
    trim = full.trim()
    n, m, n_tl = trim.ag_type.shape[1], trim.mp_cls.shape[1], trim.tl_piece.shape[1]
    assert (n, m, n_tl) < (64, 1024, 128) and trim.padded_sizes == (64, 1024)
    assert not full.ag_valid[:, n:].any() and not full.mp_valid[:, m:].any()
    runs = []
    for batch in (full, trim):
        with torch.no_grad():
            ctx = small_model.prepare(batch, 3, torch.Generator().manual_seed(7))
            runs.append((ctx, rollout(small_model, ctx, batch, gt_steps=11, n_steps=41)))
    (c_full, t_full), (c_trim, t_trim) = runs
    assert torch.equal(c_full.z[:, :n], c_trim.z)
    assert torch.equal(c_full.dest[:, :n][c_trim.dest_valid], c_trim.dest[c_trim.dest_valid])
    assert torch.allclose(c_full.mp.feat[:, :m], c_trim.mp.feat, atol=1e-5)
    assert torch.equal(t_full.valid[:, :n], t_trim.valid) and not t_full.valid[:, n:].any()
    pose_full, pose_trim = t_full.pose[:, :n], t_trim.pose
    assert torch.allclose(pose_full[..., :2], pose_trim[..., :2], atol=1e-3)
    assert wrap_angle(pose_full[..., 2] - pose_trim[..., 2]).abs().max() < 1e-3
    assert torch.equal(t_full.tl_state[:, :n_tl], t_trim.tl_state)
