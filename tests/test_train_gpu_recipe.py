"""scripts/train_gpu.sh with a tiny budget on the CPU: prepare packs token caches that travel,
train unpacks them, fine-tunes from the shipped weights within its time budget, validates and
keeps the best weights, and resumes."""

from __future__ import annotations

import gzip
import json
import os
import shutil
import subprocess
from pathlib import Path

import pytest

from policies.trafficbots import TrafficBotsConfig, load_checkpoint
from policies.trafficbots.validate import validation_loss
from policies.trafficbots.wosac import load_default_model
from tbsim_env.data.cache import open_training_data

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "scripts" / "train_gpu.sh"


def _run(args: list[str], env: dict[str, str]) -> subprocess.CompletedProcess:
    res = subprocess.run(
        ["bash", str(SCRIPT), *args], env={**os.environ, **env}, capture_output=True, text=True
    )
    assert res.returncode == 0, res.stderr[-3000:]
    return res


@pytest.fixture(scope="module")
def recipe_env(tmp_path_factory) -> dict[str, str]:
    tmp = tmp_path_factory.mktemp("gpu_recipe")
    return {
        "GPU_DATA": str(tmp / "gpu_data"),
        "TRAIN_SOURCES": "generated:merge:0-1",
        "VAL_SOURCES": "generated:merge:2-2",
        "DEVICE": "cpu",
        "BATCH": "1",
        "WORKERS": "0",
        "VAL_EVERY": "1",
        "OMP_NUM_THREADS": "1",
    }


def test_prepare_packs_gzip_shards(recipe_env):
    _run(["prepare"], recipe_env)
    data = Path(recipe_env["GPU_DATA"])
    for split, n in (("train", 2), ("validation", 1)):
        assert (data / split / "manifest.json").exists()
        shards = list((data / split).glob("*.safetensors.gz"))
        assert shards and not list((data / split).glob("*.safetensors"))
        manifest = json.loads((data / split / "manifest.json").read_text())
        assert sum(s["count"] for s in manifest["shards"]) == n


def test_train_within_its_budget_keeps_the_best_and_resumes(recipe_env, tmp_path):
    out = tmp_path / "run"
    _run(["train", str(out), "0.01"], recipe_env)  # 0.6 s: stops after its first step
    lines = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    assert lines[0]["step"] == 0 and "val_loss" in lines[0]  # the shipped weights, first
    assert lines[-1]["step"] == 1 and "val_loss" in lines[-1]
    best = json.loads((out / "best_step.json").read_text())
    assert best["loss"] == min(x["val_loss"] for x in lines if "val_loss" in x)
    model = load_checkpoint(out / "best")
    assert model.cfg == TrafficBotsConfig.small()
    if best["step"] == 0:  # nothing beat the starting weights: they are the best
        shipped = load_default_model().state_dict()
        assert all((model.state_dict()[k] == v).all() for k, v in shipped.items())
    _run(["train", str(out), "0.01"], recipe_env)
    again = [json.loads(x) for x in (out / "metrics.jsonl").read_text().splitlines()]
    assert again[-1]["step"] == 2  # resumed from step 1


def test_validation_loss_is_deterministic_and_refuses_empty_data(recipe_env, tmp_path):
    packed = Path(recipe_env["GPU_DATA"]) / "validation"
    cache = tmp_path / "val"
    cache.mkdir()
    shutil.copy(packed / "manifest.json", cache)
    for f in packed.glob("*.gz"):
        (cache / f.stem).write_bytes(gzip.decompress(f.read_bytes()))
    data = open_training_data(str(cache))
    model = load_default_model()
    a, b = validation_loss(model, data), validation_loss(model, data)
    assert a == b and a["scenes"] == 1.0 and a["loss"] > 0
    assert not model.training  # the mode is restored
    with pytest.raises(ValueError, match="no scenes"):
        validation_loss(model, [])


@pytest.mark.parametrize(("smi", "want"), [(None, "64"), ("81559", "64"), ("143771", "128")])
def test_batch_follows_the_gpu_memory(tmp_path, smi, want):
    """128 on an H200-sized GPU (143,771 MiB), 64 on an H100 (81,559 MiB) or where
    nvidia-smi fails (no driver); $BATCH wins over both."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    fake = bin_dir / "nvidia-smi"  # a stand-in answering the memory query
    fake.write_text("#!/bin/sh\nexit 9\n" if smi is None else f"#!/bin/sh\necho {smi}\n")
    fake.chmod(0o755)
    env = {k: v for k, v in os.environ.items() if k != "BATCH"}
    env["PATH"] = f"{bin_dir}:/usr/bin:/bin"
    got = subprocess.run(["bash", str(SCRIPT), "batch"], env=env, capture_output=True, text=True)
    assert got.returncode == 0, got.stderr
    assert got.stdout.strip() == want
    forced = subprocess.run(
        ["bash", str(SCRIPT), "batch"], env={**env, "BATCH": "7"}, capture_output=True, text=True
    )
    assert forced.stdout.strip() == "7"
