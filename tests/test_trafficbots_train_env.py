"""TrafficBots trainer (resume, checkpoints) and TrafficBots NPCs inside TrafficEnv."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from policies import make_policy
from policies.trafficbots import TrafficBots, TrafficBotsConfig, save_checkpoint
from policies.trafficbots.train import TrainConfig, build_parser, train
from tbsim_env.core.config import EnvConfig, TerminationConfig
from tbsim_env.core.config_cli import parse_config
from tbsim_env.core.errors import CheckpointError
from tbsim_env.data.cache import build_cache
from tbsim_env.env import TrafficEnv
from tests.conftest import check_parallel_api

pytestmark = pytest.mark.usefixtures("torch_one_thread")


@pytest.fixture(scope="module")
def random_checkpoint(tmp_path_factory):
    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("ckpt") / "small"
    save_checkpoint(TrafficBots(TrafficBotsConfig.small()), path)
    return str(path)


def test_train_help_documents_every_option(capsys):
    """``tbsim train --help`` takes each option's text from ``TrainConfig``'s docstring."""
    import dataclasses

    with pytest.raises(SystemExit):
        build_parser().parse_args(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    for f in dataclasses.fields(TrainConfig):
        flag = "--" + f.name.replace("_", "-")
        assert flag in text, flag
    helps = {a.dest: a.help for a in build_parser()._actions if a.dest != "help"}
    assert set(helps) == {f.name for f in dataclasses.fields(TrainConfig)}
    assert all(len(h.replace(" (default: %(default)s)", "")) > 10 for h in helps.values())
    assert "exponential moving average of the weights" in text and "(default: 2000)" in text
    args = build_parser().parse_args(["--data", "c", "--out", "o", "--ema-decay", "0.99"])
    assert parse_config(TrainConfig, args).ema_decay == 0.99


def test_train_writes_checkpoints_and_resumes(tmp_path):
    build_cache(["generated:intersection,merge:0-1"], tmp_path / "cache", workers=1, progress=False)
    cfg = TrainConfig(
        data=str(tmp_path / "cache"),
        out=str(tmp_path / "run"),
        steps=3,
        stop_at=2,  # a first segment of a 3-step run
        rollout_steps=13,
        log_every=1,
        ckpt_every=1,
        workers=0,
        threads=1,
    )
    train(cfg, progress=False)
    lines = (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()
    assert [json.loads(x)["step"] for x in lines] == [1, 2]
    # The teacher-forcing schedule spans all 3 steps, not the segment: 0.3 -> 0.15 -> 0.
    assert [json.loads(x)["teacher_forcing"] for x in lines] == pytest.approx([0.3, 0.15])
    assert all(np.isfinite(json.loads(x)["loss"]) for x in lines)
    meta = json.loads((tmp_path / "run" / "optimizer.json").read_text())
    assert meta["step"] == 2
    weights_before = (tmp_path / "run" / "last.safetensors").read_bytes()
    train(TrainConfig(**{**cfg.__dict__, "stop_at": None}), progress=False)
    lines = (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()
    assert [json.loads(x)["step"] for x in lines] == [1, 2, 3]  # resumed at 2, not restarted
    assert (tmp_path / "run" / "last.safetensors").read_bytes() != weights_before
    # The trained checkpoint loads as an NPC policy.
    make_policy("trafficbots", checkpoint=str(tmp_path / "run" / "last"))


def test_train_warms_up_and_keeps_an_ema_across_a_resume(tmp_path, random_checkpoint):
    from safetensors.torch import load_file

    build_cache(["generated:merge:0-0"], tmp_path / "cache", workers=1, progress=False)
    run = tmp_path / "run"
    cfg = TrainConfig(
        data=str(tmp_path / "cache"),
        out=str(run),
        steps=3,
        stop_at=1,
        lr=1e-3,
        warmup_steps=2,
        ema_decay=0.75,
        rollout_steps=13,
        log_every=1,
        ckpt_every=1,
        workers=0,
        threads=1,
        init=random_checkpoint,
    )
    train(cfg, progress=False)
    w1, e1 = load_file(str(run / "last.safetensors")), load_file(str(run / "ema.safetensors"))
    assert all(torch.equal(w1[k], e1[k]) for k in w1)  # the average starts at the weights
    train(TrainConfig(**{**cfg.__dict__, "stop_at": 2}), progress=False)  # resumes at step 1
    w2, e2 = load_file(str(run / "last.safetensors")), load_file(str(run / "ema.safetensors"))
    moved = [k for k in w2 if not torch.equal(w1[k], w2[k])]
    assert moved
    for k in moved:
        torch.testing.assert_close(e2[k], 0.75 * e1[k] + 0.25 * w2[k])
    train(TrainConfig(**{**cfg.__dict__, "stop_at": None}), progress=False)
    lrs = [json.loads(x)["lr"] for x in (run / "metrics.jsonl").read_text().splitlines()]
    assert lrs == pytest.approx([5e-4, 1e-3, 1e-3])  # linear warm-up over 2 steps
    with pytest.raises(ValueError, match="ema_decay"):
        train(TrainConfig(**{**cfg.__dict__, "out": str(tmp_path / "r2"), "ema_decay": 1.0}))


def test_train_init_fine_tunes_from_a_checkpoint(tmp_path, random_checkpoint):
    from safetensors.torch import load_file

    build_cache(["generated:merge:0-0"], tmp_path / "cache", workers=1, progress=False)
    cfg = TrainConfig(
        data=str(tmp_path / "cache"),
        out=str(tmp_path / "run"),
        steps=1,
        rollout_steps=13,
        lr=0.0,  # AdamW with lr 0 leaves the weights as they were loaded
        weight_decay=0.0,
        workers=0,
        threads=1,
        init=random_checkpoint,
    )
    train(cfg, progress=False)
    start = load_file(f"{random_checkpoint}.safetensors")
    after = load_file(str(tmp_path / "run" / "last.safetensors"))
    assert start.keys() == after.keys()
    assert all(torch.equal(start[k], after[k]) for k in start)
    assert json.loads((tmp_path / "run" / "optimizer.json").read_text())["step"] == 1
    # A checkpoint of another config is refused, naming the mismatch.
    paper = TrainConfig(**{**cfg.__dict__, "out": str(tmp_path / "run2"), "model": "paper"})
    with pytest.raises(CheckpointError, match="does not match the model"):
        train(paper, progress=False)


def test_trafficbots_npcs_pass_the_parallel_api(random_checkpoint):
    env = TrafficEnv(npc_policy="trafficbots", npc_checkpoint=random_checkpoint)
    check_parallel_api(env, num_cycles=15)


def test_trafficbots_npcs_react_to_the_controlled_agent(random_checkpoint):
    from tbsim_env.data.generator import generate_scenario

    sc = generate_scenario("merge", seed=2)

    def run(action):
        never = EnvConfig(termination=TerminationConfig(collision=False, goal=False))
        env = TrafficEnv(
            [sc], npc_policy="trafficbots", npc_checkpoint=random_checkpoint, config=never
        )
        env.reset(seed=0)
        a = env.agents[0]
        for _ in range(15):
            env.step({a: action})
        return env.sim_state.pose.clone(), env.episode.setup.npc.clone()

    pose_a, npc = run(np.array([0.0, 0.0], np.float32))
    pose_b, _ = run(np.array([-5.0, 0.5], np.float32))
    moved = (pose_a - pose_b)[..., :2].norm(dim=-1)[npc]
    # Closed loop: the NPCs' trajectories depend on what the controlled agent does.
    assert moved.max() > 1e-3


def test_mismatched_npc_checkpoint_is_rejected(tmp_path, random_checkpoint):
    bad = tmp_path / "bad"
    save_checkpoint(TrafficBots(TrafficBotsConfig.small()), bad)
    text = (tmp_path / "bad.json").read_text().replace('"hidden_dim": 64', '"hidden_dim": 32')
    (tmp_path / "bad.json").write_text(text)
    with pytest.raises(CheckpointError):
        TrafficEnv(npc_policy="trafficbots", npc_checkpoint=str(bad))


def test_torchrun_ddp_two_processes(tmp_path):
    """DistributedDataParallel over Gloo on CPU: 2 processes train, replicas stay identical."""
    import subprocess
    import sys

    build_cache(["generated:merge:0-1"], tmp_path / "cache", workers=1, progress=False)
    cmd = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc-per-node",
        "2",
        "-m",
        "policies.trafficbots.train",
        "--data",
        str(tmp_path / "cache"),
        "--out",
        str(tmp_path / "run"),
        "--steps",
        "2",
        "--rollout-steps",
        "12",
        "--device",
        "cpu",
        "--workers",
        "0",
        "--threads",
        "1",
        "--log-every",
        "1",
        "--batch-size",
        "1",
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    assert (tmp_path / "run" / "last.safetensors").exists()
    steps = [
        json.loads(x)["step"] for x in (tmp_path / "run" / "metrics.jsonl").read_text().splitlines()
    ]
    assert steps == [1, 2]
