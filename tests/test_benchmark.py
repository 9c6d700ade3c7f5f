"""The planner benchmark (tbsim_env.benchmark): each metric on hand-made scenes, failing
planners, the expert against its own log, determinism and the command line."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest

from tbsim_env.benchmark import (
    BenchmarkSettings,
    ConstantVelocityPlanner,
    ExpertPlanner,
    FunctionPlanner,
    load_planner,
    run_benchmark,
)
from tbsim_env.benchmark.config import BenchmarkConfig
from tbsim_env.benchmark.episode import EpisodeSpec, log_record, run_episode
from tbsim_env.benchmark.metrics import CollisionKind, LaneIndex
from tbsim_env.benchmark.score import MULTIPLIERS, ScenarioResult, score_record
from tbsim_env.cli import main
from tbsim_env.core.constants import MapFeatureType
from tbsim_env.data.generator import generate_scenario
from tbsim_env.data.loader import load_scenarios
from tests.test_preprocess_support import Agent, Feature, line, make_road_map, make_scenario

pytestmark = pytest.mark.usefixtures("torch_one_thread")

MPH = 0.44704


def road(speed_limit_mps: float = 0.0):
    """A straight road along +x: edges at y = +-6 m (road on their left), one lane at y = 0
    heading +x (surface street) with the given limit."""
    m = make_road_map(
        [
            Feature(1, MapFeatureType.LANE, line((-300.0, 0.0), (400.0, 0.0), 2.0), subtype=2),
            Feature(2, MapFeatureType.ROAD_EDGE, line((400.0, 6.0), (-300.0, 6.0), 2.0)),
            Feature(3, MapFeatureType.ROAD_EDGE, line((-300.0, -6.0), (400.0, -6.0), 2.0)),
        ]
    )
    limits = np.array([speed_limit_mps / MPH, 0.0, 0.0], np.float32)
    return dataclasses.replace(m, speed_limit_mph=limits)


def episode(agents: list[Agent], planner, limit: float = 0.0, cfg=None) -> ScenarioResult:
    """The SDC (row 0) driven by ``planner`` among log-replayed agents, scored."""
    sc = make_scenario(agents, road_map=road(limit))
    (record,) = run_episode(EpisodeSpec(sc, "log_replay"), lambda: planner)
    return score_record(record, LaneIndex.of(sc), cfg)


def constant(accel: float = 0.0, yaw_rate: float = 0.0) -> FunctionPlanner:
    return FunctionPlanner(lambda x: (accel, yaw_rate), name="constant")


def test_rear_ended_while_stopped_is_not_at_fault_and_rear_ending_is():
    hit = episode([Agent((0.0, 0.0)), Agent((-30.0, 0.0), speed=10.0)], constant())
    (event,) = hit.collisions
    assert event["kind"] == CollisionKind.STOPPED_EGO.value and not event["at_fault"]
    assert hit.no_at_fault_collisions == 1.0
    hitting = episode([Agent((-30.0, 0.0), speed=10.0), Agent((0.0, 0.0))], constant())
    (event,) = hitting.collisions
    assert event["kind"] == CollisionKind.STOPPED_TRACK.value and event["at_fault"]
    assert hitting.no_at_fault_collisions == 0.0 and hitting.score == 0.0
    assert hitting.time_to_collision == 0.0 and hitting.min_ttc_s <= 0.5


def test_moving_collisions_by_where_the_ego_is_touched():
    front = episode([Agent((-30.0, 0.0), speed=12.0), Agent((0.0, 0.0), speed=5.0)], constant())
    assert [e["kind"] for e in front.collisions] == ["active_front"]
    assert front.no_at_fault_collisions == 0.0
    rear = episode([Agent((0.0, 0.0), speed=5.0), Agent((-30.0, 0.0), speed=12.0)], constant())
    assert [e["kind"] for e in rear.collisions] == ["active_rear"]
    assert rear.no_at_fault_collisions == 1.0
    assert rear.time_to_collision == 1.0  # the one closing in from behind is not watched


def test_leaving_the_drivable_area_fails_its_gate():
    off = episode([Agent((0.0, 0.0), speed=10.0)], constant(yaw_rate=0.3))
    assert off.drivable_area_compliance == 0.0 and off.score == 0.0
    assert off.max_offroad_m > 0.3 and any("drivable" in w for _, w in off.infractions)
    assert off.pdm_score == 0.0
    on = episode([Agent((0.0, 0.0), speed=10.0)], constant())
    assert on.drivable_area_compliance == 1.0 and on.score == pytest.approx(100.0)


def test_driving_against_the_lane_direction():
    wrong = episode([Agent((100.0, 0.0), yaw=math.pi, speed=10.0)], constant())
    assert wrong.wrong_way_m == pytest.approx(10.0, abs=0.5)
    assert wrong.driving_direction_compliance == 0.0 and wrong.score == 0.0
    slow = episode([Agent((100.0, 0.0), yaw=math.pi, speed=4.0)], constant())
    assert slow.driving_direction_compliance == 0.5
    right = episode([Agent((100.0, 0.0), speed=10.0)], constant())
    assert right.driving_direction_compliance == 1.0


def test_exceeding_the_speed_limit_by_half_the_tolerated_margin_scores_half():
    cfg = BenchmarkConfig()
    over = episode([Agent((0.0, 0.0), speed=10.0 + cfg.max_overspeed / 2)], constant(), 10.0)
    assert over.speed_limit_compliance == pytest.approx(0.5, abs=0.01)
    within = episode([Agent((0.0, 0.0), speed=9.0)], constant(), 10.0)
    assert within.speed_limit_compliance == 1.0
    unknown = episode([Agent((0.0, 0.0), speed=30.0)], constant())
    assert unknown.speed_limit_compliance is None  # the weights renormalise without it
    assert unknown.score == pytest.approx(100.0)


def test_a_jerky_planner_loses_comfort():
    flip = FunctionPlanner(lambda x: (4.0 if (x.step // 10) % 2 else -4.0, 0.0))  # 1 s each
    jerky = episode([Agent((0.0, 0.0), speed=10.0)], flip)
    bounds = BenchmarkConfig().comfort
    assert jerky.comfort == 0.0
    assert jerky.comfort_extremes["lon_jerk"] > bounds.max_abs_lon_jerk
    assert jerky.comfort_extremes["lon_accel"][1] > bounds.max_lon_accel
    chatter = FunctionPlanner(lambda x: (0.5 if x.step % 2 else -0.5, 0.0))  # filtered out
    assert episode([Agent((0.0, 0.0), speed=10.0)], chatter).comfort == 1.0
    want = 100 * (5 * jerky.ego_progress + 5) / 12  # no speed limits on this map
    assert jerky.score == pytest.approx(want)
    smooth = episode([Agent((0.0, 0.0), speed=10.0)], constant(0.5))
    assert smooth.comfort == 1.0


def test_failing_planners_fail_their_scene_and_the_run_goes_on():
    scenes = [
        make_scenario([Agent((0.0, 0.0), speed=5.0)], road_map=road(), scenario_id=f"s{k}")
        for k in range(3)
    ]

    def flaky(x):
        if x.scenario_id == "s0" and x.step == 12:
            raise RuntimeError("planner crashed")
        return (float("nan"), 0.0) if x.scenario_id == "s1" else (0.0, 0.0)

    settings = BenchmarkSettings(planner="flaky", traffic=("log_replay",))
    results = run_benchmark(scenes, settings, lambda: FunctionPlanner(flaky), progress=False)
    assert [r.scenario_id for r in results] == ["s0", "s1", "s2"]
    assert "s0" in results[0].error and "step 12" in results[0].error
    assert "RuntimeError: planner crashed" in results[0].error and results[0].score == 0.0
    assert "not finite" in results[1].error and "step 10" in results[1].error
    assert results[2].error is None and results[2].score == pytest.approx(100.0)


@pytest.fixture(scope="module")
def real(one_scenario_path):
    return load_scenarios(one_scenario_path)[0]


@pytest.mark.parametrize("scene", ["real", "merge", "intersection"])
def test_the_expert_scores_what_its_log_earns(request, scene):
    """Every gate and the scores of the expert (following its log in closed loop) equal those
    of the logged trajectory itself."""
    sc = request.getfixturevalue("real") if scene == "real" else generate_scenario(scene, 7)
    lanes = LaneIndex.of(sc)
    (record,) = run_episode(EpisodeSpec(sc, "log_replay"), ExpertPlanner)
    expert = score_record(record, lanes)
    log = score_record(log_record(sc, sc.sdc_index), lanes)
    for name in (*MULTIPLIERS, "time_to_collision", "comfort"):
        assert getattr(expert, name) == getattr(log, name), name
    assert expert.score == pytest.approx(log.score, abs=1.0)
    assert expert.ego_progress == pytest.approx(log.ego_progress, abs=0.01)


def test_same_seed_same_json_with_reactive_traffic():
    sc = generate_scenario("t_junction", 3)
    settings = BenchmarkSettings(planner="constant_velocity", traffic=("trafficbots",), seed=4)
    a = run_benchmark([sc], settings, progress=False)
    b = run_benchmark([sc], settings, progress=False)
    assert json.dumps([r.to_json() for r in a]) == json.dumps([r.to_json() for r in b])


def test_load_planner_takes_names_factories_and_functions(tmp_path, monkeypatch):
    (tmp_path / "my_planners.py").write_text(
        "import numpy as np\n"
        "def brake(x):\n    return np.array([-1.0, 0.0])\n"
        "class Cruise:\n    name = 'cruise'\n    def act(self, x):\n        return (0.0, 0.0)\n"
        "def make():\n    return Cruise()\n"
    )
    monkeypatch.syspath_prepend(str(tmp_path))
    assert isinstance(load_planner("expert"), ExpertPlanner)
    assert isinstance(load_planner("constant_velocity"), ConstantVelocityPlanner)
    assert load_planner("my_planners:brake").act(None).tolist() == [-1.0, 0.0]
    assert load_planner("my_planners:make").name == "cruise"
    assert load_planner("my_planners:Cruise").name == "cruise"
    with pytest.raises(ValueError, match="PACKAGE.MODULE:NAME"):
        load_planner("no_such_planner")


def test_cli_benchmark_writes_tables_json_plot_and_pages(tmp_path, capsys, one_scenario_path):
    out = tmp_path / "bench.json"
    argv = ["benchmark", "--planner", "expert", "--traffic", "log_replay,constant_velocity",
            "--data", str(one_scenario_path), "--json", str(out), "--plot",
            str(tmp_path / "scores.png"), "--html", str(tmp_path / "pages"),
            "--worst", "1"]  # fmt: skip
    assert main(argv) == 0
    text = capsys.readouterr().out
    assert "| log_replay | 1 |" in text and "| constant_velocity | 1 |" in text
    doc = json.loads(out.read_text())
    assert doc["meta"]["planner"] == "expert" and len(doc["episodes"]) == 2
    assert set(doc["summary"]) == {"log_replay", "constant_velocity"}
    assert (tmp_path / "scores.png").stat().st_size > 0
    assert len(list((tmp_path / "pages").glob("*.html"))) == 1
    assert main(["benchmark", "--planner", "nope", "--data", str(one_scenario_path)]) == 2
    assert "PACKAGE.MODULE:NAME" in capsys.readouterr().err
    bad = ["benchmark", "--planner", "expert", "--traffic", "warp", "--data", "x"]
    assert main(bad) == 2


def test_the_idm_planner_stops_behind_a_standing_vehicle_where_constant_velocity_hits_it():
    agents = [Agent((-40.0, 0.0), speed=10.0), Agent((0.0, 0.0))]
    hits = episode(agents, ConstantVelocityPlanner())
    assert hits.no_at_fault_collisions == 0.0
    stops = episode(agents, load_planner("idm"))
    assert stops.error is None and stops.collisions == [] and stops.no_at_fault_collisions == 1.0
    assert stops.score > 0.0


def test_sharded_run_resumes_and_gives_the_same_json(
    tmp_path, capsys, one_scenario_path, scenario_input_path
):
    common = ["benchmark", "--planner", "constant_velocity", "--traffic", "log_replay",
              "--data", str(one_scenario_path), str(scenario_input_path)]  # fmt: skip
    assert main([*common, "--json", str(tmp_path / "plain.json")]) == 0
    work = tmp_path / "work"
    assert main([*common, "--work-dir", str(work), "--json", str(tmp_path / "a.json")]) == 0
    assert "2 shards computed, 0 already" in capsys.readouterr().out
    assert len(list(work.glob("benchmark-*.json"))) == 2
    assert main([*common, "--work-dir", str(work), "--json", str(tmp_path / "b.json")]) == 0
    assert "0 shards computed, 2 already" in capsys.readouterr().out
    a, b, plain = (json.loads((tmp_path / f).read_text()) for f in ("a.json", "b.json",
                                                                  "plain.json"))  # fmt: skip
    assert a["episodes"] == b["episodes"] == plain["episodes"]
