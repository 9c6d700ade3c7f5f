"""WOSAC rollouts of policies, export/score/evaluate CLI, and the token cache."""

from __future__ import annotations

import dataclasses
import json
import os
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch

from policies import make_policy
from tbsim_env.cli import main
from tbsim_env.data import load_scenarios
from tbsim_env.data.cache import (
    CacheError,
    TokenCache,
    build_cache,
    open_training_data,
    read_shard,
)
from tbsim_env.data.generator import generate_scenario
from tbsim_env.evaluation import export_submission
from tbsim_env.metrics.wosac import read_submission, score_scenario, validate_scenario_rollouts
from tbsim_env.metrics.wosac.simulate import linear_extrapolation_rollouts, simulate_rollouts
from tbsim_env.metrics.wosac.submission import SubmissionError, rollouts_to_proto

pytestmark = pytest.mark.float_sensitive


@pytest.fixture(scope="module")
def real(womd_dir):
    return load_scenarios(womd_dir / "waymo-open-dataset" / "motion_data_one_scenario.tfrecord")[0]


def test_rollouts_cover_exactly_the_sim_agents(real):
    r = simulate_rollouts(real, make_policy("constant_velocity"), num_rollouts=4)
    sim_ids = set(real.tracks.id[real.tracks.valid[:, 10]].tolist())
    assert set(r.object_id.tolist()) == sim_ids and r.x.shape == (4, len(sim_ids), 80)
    proto = rollouts_to_proto(simulate_rollouts(real, make_policy("constant_velocity")))
    validate_scenario_rollouts(proto, real)  # the server's checks


def test_constant_velocity_keeps_speed_and_heading(real):
    r = simulate_rollouts(real, make_policy("constant_velocity"), num_rollouts=1)
    dx, dy = np.diff(r.x[0].numpy(), axis=-1), np.diff(r.y[0].numpy(), axis=-1)
    speed = np.hypot(dx, dy) / 0.1
    assert np.allclose(speed, speed[:, :1], atol=1e-2)
    assert torch.allclose(r.heading[0], r.heading[0, :, :1].expand_as(r.heading[0]), atol=1e-5)


def test_log_replay_matches_the_official_reference(real):
    scores = score_scenario(real, simulate_rollouts(real, make_policy("log_replay")))
    assert scores.realism_meta_metric == pytest.approx(0.8266, abs=1e-3)
    assert scores.average_displacement_error == 0.0


def test_linear_extrapolation_spread_and_seed(real):
    a = linear_extrapolation_rollouts(real, seed=1)
    b = linear_extrapolation_rollouts(real, seed=1)
    c = linear_extrapolation_rollouts(real, seed=2)
    assert torch.equal(a.x, b.x) and not torch.equal(a.x, c.x)
    # Waymo's test_submission has a mean per-step std across rollouts of 1.08 m in x.
    assert 0.8 < float(a.x.std(0).mean()) < 1.4


def test_policies_rank_as_expected(real):
    log = score_scenario(real, simulate_rollouts(real, make_policy("log_replay")))
    lin = score_scenario(real, linear_extrapolation_rollouts(real))
    assert log.realism_meta_metric > lin.realism_meta_metric


def test_cli_export_is_byte_identical_and_scores(tmp_path, one_scenario_path, capsys):
    data = str(one_scenario_path)
    for name in ("a", "b"):
        args = [
            "export-wosac",
            "--data",
            data,
            "--policy",
            "constant_velocity",
            "--rollouts",
            "32",
            "--seed",
            "3",
            "--out",
            str(tmp_path / f"{name}.binproto"),
        ]
        assert main(args) == 0
    assert (tmp_path / "a.binproto").read_bytes() == (tmp_path / "b.binproto").read_bytes()
    sub = read_submission(tmp_path / "a.binproto")
    assert len(sub.scenario_rollouts) == 1 and len(sub.scenario_rollouts[0].joint_scenes) == 32
    out_json = tmp_path / "s.json"
    assert (
        main(
            [
                "wosac-score",
                "--data",
                data,
                "--submission",
                str(tmp_path / "a.binproto"),
                "--version",
                "wosac2024",
                "--json",
                str(out_json),
            ]
        )
        == 0
    )
    assert "637f20cafde22ff8" in capsys.readouterr().out
    fields = json.loads(out_json.read_text())
    assert json.dumps(fields).count("realism_meta_metric") >= 1


EXPORT_REFERENCE = Path(__file__).parent / "data" / "full_scene_export_reference.json"
"""``export_submission([637f20cafde22ff8], policy, num_rollouts=32, seed=3)`` of each policy,
summarised by ``export_summary`` (exact structure; floats compared with ``EXPORT_ATOL``):
the structure written from exports whose proto, floats cleared, had the recorded digest, the
floats from exports whose bytes matched those pinned before history-only scenes were supported
(commit 87e04d9), so full WOMD scenes are simulated as before. Regenerate (``python
tests/test_evaluation.py``) only for a deliberate change of the rollouts."""
EXPORT_POLICIES = ("constant_velocity", "linear_extrapolation", "log_replay")
SAMPLED_ROLLOUTS, SAMPLED_STEPS = (0, 31), (0, 39, 79)
EXPORT_ATOL = {"x": 0.01, "y": 0.01, "z": 0.01, "heading": 1e-3}
"""Metres and radians. The exported floats are float32 world coordinates (~4.6 km: one ulp is
0.5 mm) that other CPUs round differently; a change of the simulation moves them by far more."""


def export_structure(sub) -> dict:
    """The exact (non-float) content of a submission: its header fields, the scenario id, and
    per joint scene each trajectory's object id and the step counts of its four float
    fields."""
    from google.protobuf.json_format import MessageToDict

    header = MessageToDict(sub, preserving_proto_field_name=True)
    header.pop("scenario_rollouts", None)
    (scene,) = sub.scenario_rollouts
    trajectories = [
        [
            [t.object_id, len(t.center_x), len(t.center_y), len(t.center_z), len(t.heading)]
            for t in joint.simulated_trajectories
        ]
        for joint in scene.joint_scenes
    ]
    return {"header": header, "scenario_id": scene.scenario_id, "trajectories": trajectories}


def export_summary(path) -> dict:
    """The export at ``path`` as exact structure (``export_structure``) and the floats of
    ``SAMPLED_ROLLOUTS`` at ``SAMPLED_STEPS`` (x, y, z, heading [R, A, S] as lists)."""
    from tbsim_env.metrics.wosac.submission import rollouts_from_proto

    sub = read_submission(path)
    (scene,) = sub.scenario_rollouts
    r = rollouts_from_proto(scene)
    rows, steps = list(SAMPLED_ROLLOUTS), list(SAMPLED_STEPS)
    out = {"structure": export_structure(sub)}
    for name in EXPORT_ATOL:
        out[name] = getattr(r, name)[rows][:, :, steps].tolist()
    return out


@pytest.mark.parametrize("policy", EXPORT_POLICIES)
def test_seeded_full_scene_export_matches_the_recorded_one(tmp_path, real, policy):
    out = tmp_path / "sub.binproto"
    export_submission([real], policy, out, num_rollouts=32, seed=3)
    got, want = export_summary(out), json.loads(EXPORT_REFERENCE.read_text())[policy]
    assert got["structure"] == want["structure"]
    for name, atol in EXPORT_ATOL.items():
        diff = np.subtract(got[name], want[name])
        if name == "heading":
            diff = (diff + np.pi) % (2 * np.pi) - np.pi
        assert np.abs(diff).max() <= atol, (policy, name, np.abs(diff).max())


def test_export_never_writes_a_trajectory_of_the_wrong_length(tmp_path, real, monkeypatch):
    import tbsim_env.evaluation as evaluation

    def short(scenario, num_rollouts, seed):
        r = simulate_rollouts(scenario, make_policy("constant_velocity"), num_rollouts=2)
        return dataclasses.replace(r, x=r.x[..., :79], y=r.y[..., :79], z=r.z[..., :79],
                                   heading=r.heading[..., :79])  # fmt: skip

    monkeypatch.setattr(evaluation, "make_rollout_fn", lambda *a, **k: short)
    out = tmp_path / "sub.binproto"
    with pytest.raises(SubmissionError, match="center_x has 79 steps, expected 80"):
        export_submission([real], "constant_velocity", out, num_rollouts=2)
    assert not out.exists()


def test_cli_scores_official_test_submission(womd_dir, one_scenario_path, capsys):
    sub = womd_dir / "waymo-open-dataset" / "sim_agents" / "test_submission.binproto"
    assert (
        main(
            [
                "wosac-score",
                "--data",
                str(one_scenario_path),
                "--submission",
                str(sub),
                "--version",
                "wosac2024",
            ]
        )
        == 0
    )
    assert "0.2313" in capsys.readouterr().out


def test_cli_evaluate_writes_plot(tmp_path, one_scenario_path):
    png = tmp_path / "hist.png"
    assert (
        main(
            [
                "evaluate",
                "--data",
                str(one_scenario_path),
                "--policy",
                "linear_extrapolation",
                "--rollouts",
                "32",
                "--plot",
                str(png),
            ]
        )
        == 0
    )
    assert png.stat().st_size > 10_000


def test_cli_reports_bad_input_cleanly(tmp_path, tf_example_path, capsys):
    cut = tmp_path / "example_cut.tfrecord"  # tf.Example files are read; a cut one is not
    cut.write_bytes(tf_example_path.read_bytes()[:-1000])
    rc = main(["info", str(cut)])
    assert rc == 2 and "example_cut.tfrecord" in capsys.readouterr().err
    rc = main(["info", str(tmp_path / "missing.tfrecord")])
    assert rc == 2


def test_token_cache_round_trip(tmp_path):
    m = build_cache(
        ["generated:intersection,merge:0-4"],
        tmp_path,
        workers=1,
        shard_size=2,
        progress=False,
        exclude_ids=["gen-merge-0003"],
    )
    cache = TokenCache(tmp_path)
    assert len(cache) == 4 and len(m["shards"]) == 2
    assert "gen-merge-0003" not in cache.scenario_ids
    from tbsim_env.core.config import TokenConfig
    from tbsim_env.data.preprocess import preprocess_scenario

    ref = preprocess_scenario(generate_scenario("intersection", 2), TokenConfig(training=True))
    got = cache[cache.scenario_ids.index("gen-intersection-0002")]
    for name in ("map_pos", "agent_pos", "agent_valid", "tl_state", "agent_dest"):
        np.testing.assert_array_equal(getattr(got, name), getattr(ref, name))
    with pytest.raises(IndexError):
        cache[4]
    (tmp_path / "shard-00000.safetensors").write_bytes(b"garbage")
    with pytest.raises(CacheError, match="cannot read shard"):
        read_shard(tmp_path / "shard-00000.safetensors")


def test_token_cache_keeps_an_lru_of_shards_and_joins_folders(tmp_path, monkeypatch):
    a, b = tmp_path / "a", tmp_path / "b"
    build_cache(["generated:merge:0-3"], a, workers=1, shard_size=1, progress=False)
    build_cache(["generated:t_junction:0-1"], b, workers=1, shard_size=1, progress=False)
    import tbsim_env.data.cache as cache_mod

    reads = []
    real_read = cache_mod.read_shard
    monkeypatch.setattr(cache_mod, "read_shard", lambda p: reads.append(p) or real_read(p))
    cache = TokenCache(a, max_shards=2)
    for i in (0, 1, 0, 1, 2, 0):  # 0 and 1 stay cached; 2 evicts 0, which is read again
        assert cache[i].scenario_id == f"gen-merge-{i:04d}"
    assert len(reads) == 4
    with pytest.raises(ValueError, match="max_shards"):
        TokenCache(a, max_shards=0)

    data = open_training_data(f"{a}, {b}*3")
    assert len(data) == 4 + 3 * 2
    ids = [data[i].scenario_id for i in range(len(data))]
    assert ids.count("gen-t_junction-0001") == 3 and ids.count("gen-merge-0002") == 1
    assert isinstance(open_training_data(str(a)), TokenCache)
    for bad in (f"{a}*0", f"{a}*x", " , "):
        with pytest.raises(ValueError):
            open_training_data(bad)
    with pytest.raises(CacheError):
        open_training_data(str(tmp_path / "missing"))


def test_feature_samples_of_a_scene_logged_beyond_the_wosac_horizon(womd_dir):
    """A 20 s ScenarioNet scene (198 steps) gives histogram samples over the 80 scored steps,
    as scoring cuts it."""
    from tbsim_env.data import load_scenarios
    from tbsim_env.evaluation import feature_samples

    path = womd_dir / "scenarionet_more" / "metadrive" / "0_at_f3b1e7b105.pkl"
    sc = load_scenarios(path)[0]
    assert sc.num_steps > 91
    r = linear_extrapolation_rollouts(sc, num_rollouts=2)
    samples = feature_samples(sc, r)
    speed_log, speed_sim = samples["linear_speed"]
    assert len(speed_log) > 0 and len(speed_sim) == pytest.approx(2 * len(speed_log), rel=0.2)


if __name__ == "__main__":  # regenerate the export reference after a deliberate change
    shared = Path(__file__).resolve().parents[2] / "shared" / "data" / "womd"
    womd = os.environ.get("TBSIM_WOMD_DIR", shared)
    scene = load_scenarios(Path(womd) / "waymo-open-dataset/motion_data_one_scenario.tfrecord")[0]
    ref = {}
    with tempfile.TemporaryDirectory() as tmp:
        for name in EXPORT_POLICIES:
            path = Path(tmp) / f"{name}.binproto"
            export_submission([scene], name, path, num_rollouts=32, seed=3)
            ref[name] = export_summary(path)
    EXPORT_REFERENCE.write_text(json.dumps(ref) + "\n")
    print(f"wrote {EXPORT_REFERENCE}")
