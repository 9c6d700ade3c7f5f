"""Batched benchmark episodes (tbsim_env.benchmark.batch): several scenes stepped together give
the results of one scene at a time, and a failing row fails alone."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from tbsim_env.benchmark import (
    BatchInput,
    BenchmarkSettings,
    FunctionPlanner,
    load_planner,
    run_benchmark,
)
from tbsim_env.benchmark import runner as R
from tbsim_env.benchmark.batch import batchable, run_batch
from tbsim_env.benchmark.episode import EpisodeRecord, EpisodeSpec, run_episode
from tbsim_env.data.generator import generate_scenario
from tbsim_env.data.loader import load_scenarios
from tests.test_benchmark import road
from tests.test_preprocess_support import Agent, make_scenario

# Batched against one-scene floats: CI runs it on both kernel paths.
pytestmark = [pytest.mark.usefixtures("torch_one_thread"), pytest.mark.float_sensitive]


def _close(a, b, path: str = "") -> None:
    """``a`` == ``b`` for JSON-like values, floats within float32 rounding."""
    if isinstance(a, float) and isinstance(b, float):
        both_inf = math.isinf(a) and a == b
        assert both_inf or a == pytest.approx(b, rel=1e-5, abs=1e-5), path
    elif isinstance(a, dict):
        assert a.keys() == b.keys(), path
        for k in a:
            _close(a[k], b[k], f"{path}.{k}")
    elif isinstance(a, list | tuple):
        assert len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b)):
            _close(x, y, f"{path}[{i}]")
    else:
        assert a == b, path


@pytest.fixture(scope="module")
def scenes(one_scenario_path):
    """A real scene and three generated ones of different sizes (padded apart in a batch)."""
    generated = [generate_scenario(k, 3) for k in ("merge", "t_junction", "intersection")]
    return [load_scenarios(one_scenario_path)[0], *generated]


def _same_records(a: EpisodeRecord, b: EpisodeRecord) -> None:
    """Every field equal, arrays of floats within float32 rounding."""
    for f in dataclasses.fields(EpisodeRecord):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray) and x.dtype.kind == "f":
            np.testing.assert_allclose(x, y, rtol=1e-5, atol=1e-4, err_msg=f.name)
        elif isinstance(x, np.ndarray):
            np.testing.assert_array_equal(x, y, err_msg=f.name)
        else:
            assert x == pytest.approx(y, rel=1e-5, abs=1e-5), f.name


@pytest.mark.parametrize(
    ("planner", "traffic"),
    [
        ("expert", "log_replay"),
        ("constant_velocity", "log_replay"),
        ("idm", "log_replay"),
        ("constant_velocity", "idm"),  # IDM NPCs: each row's draws seeded as its scene's alone
        ("idm", "idm_lanes"),
    ],
)
def test_batched_episodes_equal_one_scene_at_a_time(scenes, planner, traffic):
    """Every recorded state of every agent, not only the scores."""
    specs = [EpisodeSpec(sc, traffic, seed=11 + k) for k, sc in enumerate(scenes)]
    assert batchable(specs[0], load_planner(planner))
    together = run_batch(specs, load_planner(planner))
    for spec, b in zip(specs, together):
        (a,) = run_episode(spec, lambda: load_planner(planner))
        assert a.error is None and b.error is None
        _same_records(a, b)


def test_the_benchmark_runs_batches_and_gives_the_same_json(scenes, monkeypatch):
    batches = []
    monkeypatch.setattr(R, "run_batch", lambda s, p: batches.append(len(s)) or run_batch(s, p))
    traffic = ("log_replay", "idm")
    alone = run_benchmark(scenes, BenchmarkSettings("idm", traffic, batch_size=1), progress=False)
    assert batches == []
    together = run_benchmark(
        scenes, BenchmarkSettings("idm", traffic, batch_size=3), progress=False
    )
    assert batches == [3, 3, 1, 1]  # three scenes under each mode, then the fourth
    assert [(r.scenario_id, r.traffic) for r in together] == [
        (r.scenario_id, r.traffic) for r in alone
    ]
    for a, b in zip(alone, together):
        _close(a.to_json(), b.to_json(), a.scenario_id)


def test_learned_traffic_and_per_agent_planners_run_one_scene_at_a_time(scenes):
    spec = EpisodeSpec(scenes[0], "log_replay")
    idm = load_planner("idm")
    assert not batchable(EpisodeSpec(scenes[0], "trafficbots"), idm)  # padding would round
    assert not batchable(EpisodeSpec(scenes[0], "log_replay", "tracks_to_predict"), idm)
    assert not batchable(spec, FunctionPlanner(lambda x: (0.0, 0.0)))


class _Flaky:
    """A batch planner: NaN for scene s1 from step 10, raises on the batch holding s2 at
    step 12, else holds speed."""

    def act_batch(self, x: BatchInput):
        if "s2" in x.scenario_ids and x.step == 12:
            raise RuntimeError("planner crashed")
        a = np.zeros((len(x.agents), 2), np.float32)
        a[[s == "s1" for s in x.scenario_ids]] = np.nan
        return a


def test_a_failing_row_fails_alone_and_a_raising_planner_its_batch():
    scenes = [
        make_scenario([Agent((0.0, 0.0), speed=5.0)], road_map=road(), scenario_id=f"s{k}")
        for k in range(4)
    ]
    settings = BenchmarkSettings(planner="flaky", traffic=("log_replay",), batch_size=2)
    results = run_benchmark(scenes, settings, _Flaky, progress=False)
    assert [r.scenario_id for r in results] == ["s0", "s1", "s2", "s3"]
    assert results[0].error is None and results[0].score == pytest.approx(100.0)
    assert "s1" in results[1].error and "not finite" in results[1].error
    assert "step 10" in results[1].error and results[1].score == 0.0
    for r in results[2:]:  # the batch [s2, s3]
        assert "RuntimeError: planner crashed" in r.error and "step 12" in r.error
        assert r.scenario_id in r.error and r.score == 0.0


def test_batch_size_must_be_positive():
    with pytest.raises(ValueError, match="batch_size"):
        BenchmarkSettings(planner="expert", batch_size=0)
