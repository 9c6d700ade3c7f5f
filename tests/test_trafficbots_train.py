"""TrafficBots training: differentiable step, gradient routing (docs/model.md §6.4), overfitting one
scene."""

from __future__ import annotations

import time

import pytest
import torch

import tbsim_env  # noqa: F401  (first: avoids the policies <-> tbsim_env.env import cycle)

# isort: split

from policies.trafficbots import TokenBatch, TrafficBots, TrafficBotsConfig, rollout, training_step
from policies.trafficbots.losses import imitation_loss
from policies.trafficbots.model import PrepareMode
from policies.trafficbots.synthetic import make_synthetic_tokens


def _grad_norm(module: torch.nn.Module) -> float:
    return sum(float(p.grad.norm()) for p in module.parameters() if p.grad is not None)


pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def batch() -> TokenBatch:
    return TokenBatch.from_tokens(make_synthetic_tokens(n_agents=10, n_map=64, n_tl=6, seed=2))


def test_training_step_is_differentiable(batch) -> None:
    torch.manual_seed(0)
    model = TrafficBots(TrafficBotsConfig.small()).train()
    gen = torch.Generator().manual_seed(0)
    loss, logs = training_step(model, batch, generator=gen, teacher_forcing_p=0.3, n_steps=16)
    assert torch.isfinite(loss) and loss.requires_grad
    for key in ("imitation", "kl", "destination", "tl_state"):
        assert key in logs and logs[key] >= 0.0
    assert logs["kl"] >= 1.2 - 1e-6  # free nats: max(KL, 1) + 0.2 max(KL, 1)
    loss.backward()
    for name in ("map_encoder", "tl_encoder", "tl_head", "agent_encoder", "dest_predictor",
                 "dest_encoder", "posterior", "add_navi", "add_latent", "action_head"):  # fmt: skip
        assert _grad_norm(getattr(model, name)) > 0, name
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


def test_training_on_the_trimmed_batch_is_training_on_the_padded_one() -> None:
    """``tbsim train`` trims each batch's padding (``TokenBatch.trim``): same draws (latent
    choice, posterior samples, teacher forcing), same loss and gradients to float rounding.
    Eval mode, so that dropout (whose masks follow the tensor shapes) is off."""
    from tbsim_env.data.generator import generate_scenario
    from tbsim_env.data.preprocess import preprocess_scenario

    torch.manual_seed(0)
    model = TrafficBots(TrafficBotsConfig.small()).eval()
    scenes = [preprocess_scenario(generate_scenario(k, 3)) for k in ("merge", "t_junction")]
    padded = TokenBatch.from_tokens(scenes)
    trimmed = padded.trim()
    assert trimmed.ag_type.shape[1] < padded.ag_type.shape[1]
    results = []
    for batch in (padded, trimmed):
        model.zero_grad()
        gen = torch.Generator().manual_seed(3)
        loss, logs = training_step(model, batch, generator=gen, teacher_forcing_p=0.5, n_steps=21)
        loss.backward()
        results.append((logs, [p.grad.clone() for p in model.parameters() if p.grad is not None]))
    (logs_p, grads_p), (logs_t, grads_t) = results
    for key in ("imitation", "kl", "destination", "tl_state", "n_loss_valid"):
        assert logs_t[key] == pytest.approx(logs_p[key], rel=1e-4, abs=1e-6), key
    assert len(grads_p) == len(grads_t)
    for g_p, g_t in zip(grads_p, grads_t, strict=True):
        assert torch.allclose(g_p, g_t, rtol=1e-3, atol=1e-6)


def test_gradient_routing_and_bptt(batch) -> None:
    torch.manual_seed(1)
    model = TrafficBots(TrafficBotsConfig.small()).train()
    gen = torch.Generator().manual_seed(1)
    mode = PrepareMode(latent="posterior", dest="gt", tl_valid_from="full")
    ctx = model.prepare(batch, 1, gen, mode)
    forced = torch.zeros_like(batch.ag_valid[..., 0])
    forced[0, 1] = True
    actions = []  # record each step's action tensor (the graph leaves of the BPTT chain)
    step = model.step

    def spy(*args, **kwargs):
        out, state = step(*args, **kwargs)
        actions.append(out.action)
        return out, state

    model.step = spy
    traj = rollout(model, ctx, batch, gt_steps=batch.n_steps, teacher_force=forced, n_steps=18)
    loss, mask = imitation_loss(traj, batch)
    # Imitation never reaches the destination predictor or the TL head (detached inputs).
    loss.backward(retain_graph=True)
    assert _grad_norm(model.dest_predictor) == 0 and _grad_norm(model.tl_head) == 0
    assert _grad_norm(model.posterior) > 0 and _grad_norm(model.map_encoder) > 0
    # BPTT: the last step's error reaches the first free action through the dynamics only,
    # except for the teacher-forced agent whose chain is cut by the override.
    last = traj.pose[:, :, -1, :2].square().sum()
    (g,) = torch.autograd.grad(last, actions[10])  # action of step 10 -> 11 (first free)
    assert mask[0, 0, -1] and (g[0, 0].abs() > 0).all()
    assert g[0, 1].abs().sum() == 0
    # Teacher-forced agent replays the log exactly.
    v = batch.ag_valid[0, 1, :18]
    assert torch.allclose(traj.pose[0, 1, v], batch.ag_pose[0, 1, :18][v])


def test_overfit_one_real_scene(one_scenario_path) -> None:
    from tbsim_env.core.config import TokenConfig
    from tbsim_env.data import load_scenarios
    from tbsim_env.data.preprocess import preprocess_scenario

    scenario = load_scenarios(one_scenario_path)[0]
    cfg_tok = TokenConfig(max_agents=8, max_map_pieces=128, max_traffic_lights=16, training=True)
    real = TokenBatch.from_tokens(preprocess_scenario(scenario, cfg_tok))
    assert real.ag_valid[..., 11:21].any()
    torch.manual_seed(0)
    model = TrafficBots(TrafficBotsConfig.small())
    opt = torch.optim.AdamW(model.parameters(), lr=1e-3, weight_decay=0.0, betas=(0.9, 0.95))
    n_steps = 21  # 10 closed-loop steps after the warm start keep this test to seconds

    def evaluate() -> float:
        model.eval()
        with torch.no_grad():
            _, logs = training_step(
                model, real, prior_prob=0.0, generator=torch.Generator().manual_seed(7),
                n_steps=n_steps,
            )  # fmt: skip
        return logs["imitation"]

    before = evaluate()
    gen = torch.Generator().manual_seed(0)
    t0 = time.perf_counter()
    model.train()
    for _ in range(80):
        loss, _ = training_step(model, real, prior_prob=0.0, generator=gen, n_steps=n_steps)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 5.0)
        opt.step()
    after = evaluate()
    print(f"overfit: imitation {before:.4f} -> {after:.4f} in {time.perf_counter() - t0:.1f} s")
    assert after <= 0.5 * before


def test_training_step_runs_under_autocast(batch) -> None:
    """``tbsim train --amp`` runs the step under autocast (float16 on a GPU): every op must
    accept the mixed dtypes autocast produces. bfloat16 on the CPU takes the same paths
    (matrix products in half precision, softmax in float32), the sparse and dense attention
    both."""
    torch.manual_seed(0)
    model = TrafficBots(TrafficBotsConfig.small()).train()
    gen = torch.Generator().manual_seed(0)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        loss, _ = training_step(model, batch, generator=gen, teacher_forcing_p=0.3, n_steps=8)
    assert torch.isfinite(loss)
    loss.backward()
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)
