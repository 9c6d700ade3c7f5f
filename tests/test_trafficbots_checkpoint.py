"""TrafficBots checkpoints: safetensors + JSON round trip and strict key/shape checks."""

from __future__ import annotations

import json

import pytest
import torch
from safetensors.torch import load_file, save_file

import tbsim_env  # noqa: F401  (first: avoids the policies <-> tbsim_env.env import cycle)

# isort: split

from policies.trafficbots import (
    TokenBatch,
    TrafficBots,
    TrafficBotsConfig,
    average_checkpoints,
    load_checkpoint,
    load_state_into,
    rollout,
    save_checkpoint,
)
from policies.trafficbots.synthetic import make_synthetic_tokens
from tbsim_env.core.errors import CheckpointError

pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def saved(tmp_path_factory):
    torch.manual_seed(0)
    model = TrafficBots(TrafficBotsConfig.small()).eval()
    base = tmp_path_factory.mktemp("ckpt") / "tb_small"
    w_path, c_path = save_checkpoint(model, base)
    return model, base, w_path, c_path


def _actions(model: TrafficBots) -> torch.Tensor:
    tok = make_synthetic_tokens(n_agents=8, n_map=48, n_tl=4, seed=5)
    batch = TokenBatch.from_tokens(tok)
    with torch.no_grad():
        ctx = model.prepare(batch, 2, torch.Generator().manual_seed(9))
        return rollout(model, ctx, batch, gt_steps=11, n_steps=14).action


def test_round_trip_gives_identical_outputs(saved) -> None:
    model, base, w_path, c_path = saved
    assert w_path.name == "tb_small.safetensors" and c_path.name == "tb_small.json"
    assert json.loads(c_path.read_text())["config"]["hidden_dim"] == 64
    loaded = load_checkpoint(base)
    assert loaded.cfg == model.cfg and not loaded.training
    assert torch.equal(_actions(model), _actions(loaded))
    # Either file path works as the base path.
    assert load_checkpoint(w_path).cfg == model.cfg


def test_other_config_fails_naming_keys(saved) -> None:
    _, base, _, _ = saved
    with pytest.raises(CheckpointError, match=r"map_encoder\.layers\.2\.") as err:
        load_checkpoint(base, config=TrafficBotsConfig.paper())
    assert "missing keys" in str(err.value) and "mismatched keys" in str(err.value)


def test_tampered_key_and_shape_fail(saved, tmp_path) -> None:
    model, base, w_path, c_path = saved
    state = load_file(str(w_path))
    renamed = dict(state)
    renamed["action_head.branches.9.net.0.weight"] = renamed.pop(
        "action_head.branches.0.net.0.weight"
    )
    save_file(renamed, str(tmp_path / "renamed.safetensors"))
    (tmp_path / "renamed.json").write_text(c_path.read_text())
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(tmp_path / "renamed")
    msg = str(err.value)
    assert "missing keys ['action_head.branches.0.net.0.weight']" in msg
    assert "unexpected keys ['action_head.branches.9.net.0.weight']" in msg

    reshaped = dict(state)
    reshaped["posterior.log_std"] = torch.zeros(17)
    save_file(reshaped, str(tmp_path / "reshaped.safetensors"))
    with pytest.raises(CheckpointError, match=r"posterior\.log_std: checkpoint \(17,\)"):
        load_state_into(TrafficBots(model.cfg), tmp_path / "reshaped")


def test_bad_or_missing_files_fail(saved, tmp_path) -> None:
    _, base, w_path, _ = saved
    with pytest.raises(CheckpointError, match="cannot read config"):
        load_checkpoint(tmp_path / "nothing")
    (tmp_path / "badcfg.json").write_text(
        json.dumps({"format": "tbsim.trafficbots", "version": 1, "config": {"hidden_dim": 64}})
    )
    with pytest.raises(CheckpointError, match="invalid config"):
        load_checkpoint(tmp_path / "badcfg")
    (tmp_path / "junk.safetensors").write_bytes(b"not a safetensors file")
    with pytest.raises(CheckpointError, match="cannot read weights"):
        load_state_into(TrafficBots(TrafficBotsConfig.small()), tmp_path / "junk")


def test_average_of_checkpoints_is_the_elementwise_mean(saved, tmp_path) -> None:
    model, base, _, _ = saved
    torch.manual_seed(1)
    other = TrafficBots(TrafficBotsConfig.small())
    save_checkpoint(other, tmp_path / "other")
    w_path, _ = average_checkpoints([base, tmp_path / "other"], tmp_path / "mean")
    mean = load_checkpoint(w_path)
    assert mean.cfg == model.cfg
    a, b, m = model.state_dict(), other.state_dict(), mean.state_dict()
    assert any(not torch.equal(a[k], b[k]) for k in a if a[k].is_floating_point())
    for key in a:
        torch.testing.assert_close(m[key], (a[key] + b[key]) / 2, rtol=0, atol=1e-7)
    # The CLI writes the same file.
    from tbsim_env.cli import main

    argv = ["average", str(base), str(tmp_path / "other"), "--out", str(tmp_path / "cli")]
    assert main(argv) == 0
    cli = load_checkpoint(tmp_path / "cli").state_dict()
    assert all(torch.equal(cli[k], m[k]) for k in m)


def test_average_rejects_one_checkpoint_and_mixed_configs(saved, tmp_path) -> None:
    _, base, _, _ = saved
    with pytest.raises(CheckpointError, match="two or more"):
        average_checkpoints([base], tmp_path / "mean")
    cfg = TrafficBotsConfig.small().to_dict() | {"dropout": 0.0}
    save_checkpoint(TrafficBots(TrafficBotsConfig.from_dict(cfg)), tmp_path / "other")
    with pytest.raises(CheckpointError, match="dropout"):
        average_checkpoints([base, tmp_path / "other"], tmp_path / "mean")
