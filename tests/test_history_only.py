"""History-only scenes (the WOSAC test split: 11 logged steps, current step 10) end to end.

The two shared scenes of that kind are read like any other; whatever simulates runs its own
horizon on them, and whatever needs the logged future refuses them in one line.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from policies import make_policy
from policies.trafficbots.wosac import load_default_model, trafficbots_rollouts
from tbsim_env.cli import main
from tbsim_env.core.config import EnvConfig, TerminationConfig
from tbsim_env.core.constants import DT
from tbsim_env.core.errors import MissingFutureError, ScenarioFormatError
from tbsim_env.data import load_scenarios
from tbsim_env.data.cache import build_cache
from tbsim_env.data.protos import scenario_pb2
from tbsim_env.data.tfrecord import iter_records
from tbsim_env.data.womd import parse_scenario
from tbsim_env.env import TrafficEnv
from tbsim_env.env.vector_env import BatchedTrafficEnv
from tbsim_env.evaluation import export_submission
from tbsim_env.metrics.wosac import read_submission, validate_scenario_rollouts
from tbsim_env.metrics.wosac.simulate import simulate_rollouts
from tbsim_env.metrics.wosac.submission import rollouts_from_proto, rollouts_to_proto
from tests.conftest import check_parallel_api

HISTORY_ONLY = ("tfrecord-00149-of-00150_111.json", "tfrecord-00000-of-00150_78.json")
"""The shared WOSAC test-split scenes (``gpudrive_history/gpudrive/``)."""


@pytest.fixture(scope="module")
def history_dir(womd_dir: Path) -> Path:
    """Folder of the two history-only scenes and one full scene."""
    return womd_dir / "gpudrive_history" / "gpudrive"


@pytest.fixture(scope="module")
def history_scenes(history_dir: Path) -> list:
    return load_scenarios([history_dir / name for name in HISTORY_ONLY])


@pytest.fixture(scope="module")
def full(one_scenario_path: Path):
    return load_scenarios(one_scenario_path)[0]


def _cut_record(path: Path, steps: int) -> bytes:
    """The record of ``path`` with its log cut to the first ``steps`` steps."""
    ((_, _, payload),) = list(iter_records(path))
    msg = scenario_pb2.Scenario.FromString(payload)
    del msg.timestamps_seconds[steps:]
    del msg.dynamic_map_states[steps:]
    for track in msg.tracks:
        del track.states[steps:]
    return msg.SerializeToString()


# ----------------------------------------------------------------------------- reading


def test_readers_accept_history_only_scenes(history_scenes, full, one_scenario_path) -> None:
    for sc in history_scenes:
        assert sc.num_steps == sc.num_logged_steps == 11 and sc.current_index == 10
        assert not sc.has_future and sc.num_future_steps == 0
    assert full.has_future and full.num_logged_steps == 91 and full.num_future_steps == 80
    # The raw WOMD reader: the real record cut to its history.
    cut = parse_scenario(_cut_record(one_scenario_path, 11), path="cut.tfrecord", record=0)
    assert cut.num_logged_steps == 11 and not cut.has_future
    np.testing.assert_array_equal(cut.tracks.xyz, full.tracks.xyz[:, :11])
    assert cut.signals.state.shape == (full.signals.num_signals, 11)
    # Fewer steps than the current step: refused, naming the record and the field.
    with pytest.raises(ScenarioFormatError, match="record 0.*'current_time_index' 10 is not"):
        parse_scenario(_cut_record(one_scenario_path, 10), path="cut.tfrecord", record=0)


def test_on_time_grid_extends_with_invalid_steps(history_scenes, full) -> None:
    sc = history_scenes[0]
    grid = sc.on_time_grid(91)
    assert grid.num_steps == 91 and grid.num_logged_steps == 11 and not grid.has_future
    assert grid.validate() is grid and grid.scenario_id == sc.scenario_id
    np.testing.assert_array_equal(grid.tracks.xyz[:, :11], sc.tracks.xyz)
    np.testing.assert_array_equal(grid.tracks.valid[:, :11], sc.tracks.valid)
    assert not grid.tracks.valid[:, 11:].any() and not grid.signals.valid[:, 11:].any()
    assert grid.tracks.raw_heading is None or grid.tracks.raw_heading.shape == (26, 91)
    np.testing.assert_allclose(np.diff(grid.timestamps[10:]), DT)
    assert full.on_time_grid(91) is full  # a full WOMD scene is simulated as it is
    cut = full.on_time_grid(51)
    assert cut.num_steps == cut.num_logged_steps == 51 and cut.num_future_steps == 40
    with pytest.raises(ValueError, match="leaves out the current step"):
        sc.on_time_grid(10)
    with pytest.raises(ScenarioFormatError, match="valid after the log's end"):
        full.replace(logged_steps=50).validate()
    with pytest.raises(ScenarioFormatError, match="'logged_steps' 5 outside"):
        grid.replace(logged_steps=5).validate()


def test_missing_future_is_one_line_naming_the_scene(history_scenes, full) -> None:
    sc = history_scenes[0]
    with pytest.raises(MissingFutureError) as info:
        sc.require_log_until(90, "log replay")
    text = str(info.value)
    assert sc.scenario_id in text and HISTORY_ONLY[0] in text and "log replay" in text
    assert "steps 0-10" in text and "history only" in text and "\n" not in text
    assert isinstance(info.value, ValueError) and info.value.needed_step == 90
    full.require_log_until(90, "log replay")  # no error


def test_tbsim_info_shows_logged_steps_and_future(history_dir, capsys) -> None:
    assert main(["info", str(history_dir)]) == 0
    rows = {line.split()[0]: line.split() for line in capsys.readouterr().out.splitlines()}
    assert rows["scenario_id"][-2:] == ["steps", "future"]
    assert rows["1c8f1f7b63fc6118"][-2:] == ["11", "none"]
    assert rows["fcb5b4973f486e78"][-2:] == ["11", "none"]
    assert rows["792d65eb579314db"][-2:] == ["91", "80"]


def test_token_cache_skips_history_only_scenes(tmp_path, history_dir) -> None:
    m = build_cache([str(history_dir / HISTORY_ONLY[1])], tmp_path, workers=1, progress=False)
    assert m["scenario_ids"] == [] and len(m["skipped"]) == 1
    assert "fcb5b4973f486e78" in m["skipped"][0] and "token cache" in m["skipped"][0]


# ----------------------------------------------------------------------------- WOSAC rollouts


def _check_submission_entry(proto, scenario, num_rollouts: int) -> None:
    """The server's checks, then the shapes: every object valid at step 10, 80 steps each."""
    validate_scenario_rollouts(proto, scenario, num_rollouts=num_rollouts)
    r = rollouts_from_proto(proto)
    sim_ids = scenario.tracks.id[scenario.tracks.valid[:, 10]]
    assert sorted(r.object_id.tolist()) == sorted(sim_ids.tolist())
    assert r.x.shape == (num_rollouts, len(sim_ids), 80)
    assert all(torch.isfinite(v).all() for v in (r.x, r.y, r.z, r.heading))


@pytest.mark.parametrize("policy", ["constant_velocity", "linear_extrapolation"])
def test_export_api_simulates_80_steps(tmp_path, history_scenes, policy) -> None:
    out = tmp_path / "sub.binproto"
    assert export_submission(history_scenes, policy, out, num_rollouts=32, seed=1) == 2
    sub = read_submission(out)
    for proto, sc in zip(sub.scenario_rollouts, history_scenes, strict=True):
        _check_submission_entry(proto, sc, 32)


def test_trafficbots_simulates_80_steps(history_scenes) -> None:
    model = load_default_model()
    for sc in history_scenes:
        # The WOSAC sampler (fewer samples than the submission's 128, same code path).
        r = trafficbots_rollouts(model, sc, num_rollouts=32, num_samples=32, seed=0)
        _check_submission_entry(rollouts_to_proto(r), sc, 32)
    # TrafficBots as a closed-loop policy of the simulator, and constant velocity.
    sc = history_scenes[1]
    for policy in ("trafficbots", "constant_velocity"):
        r = simulate_rollouts(sc, make_policy(policy), num_rollouts=2, seed=0)
        _check_submission_entry(rollouts_to_proto(r), sc, 2)
        assert (torch.hypot(r.x[:, :, -1] - r.x[:, :, 0], r.y[:, :, -1] - r.y[:, :, 0]) > 1).any()


def test_cli_exports_a_folder_of_full_and_history_only_scenes(tmp_path, history_dir) -> None:
    scenes = {sc.scenario_id: sc for sc in load_scenarios(history_dir)}
    assert sorted(sc.has_future for sc in scenes.values()) == [False, False, True]
    args = ["export-wosac", "--data", str(history_dir), "--policy", "constant_velocity"]
    assert main([*args, "--out", str(tmp_path / "one.binproto")]) == 0
    sub = read_submission(tmp_path / "one.binproto")
    assert len(sub.scenario_rollouts) == 3
    for proto in sub.scenario_rollouts:
        _check_submission_entry(proto, scenes[proto.scenario_id], 32)
    assert main([*args, "--out", f"{tmp_path / 'shards'}/"]) == 0
    assert len(list((tmp_path / "shards").iterdir())) == 3


def _one_line_error(capsys, rc: int, *needles: str) -> str:
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert rc == 2 and "\n" not in err and "Traceback" not in captured.err, captured.err
    for needle in needles:
        assert needle in err, err
    return err


def test_what_needs_the_future_refuses_in_one_line(tmp_path, history_dir, capsys) -> None:
    one = str(history_dir / HISTORY_ONLY[0])
    rc = main(["evaluate", "--data", one, "--policy", "trafficbots"])
    _one_line_error(capsys, rc, "1c8f1f7b63fc6118", HISTORY_ONLY[0], "WOSAC scoring")
    for out in (tmp_path / "lr.binproto", f"{tmp_path / 'lr'}/"):
        rc = main(
            ["export-wosac", "--data", str(history_dir), "--policy", "log_replay"]
            + ["--out", str(out)]
        )
        _one_line_error(capsys, rc, "log replay", "history only")
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # no file, not even an empty one
    sub = tmp_path / "cv.binproto"
    assert (
        main(["export-wosac", "--data", one, "--policy", "constant_velocity", "--out", str(sub)])
        == 0
    )
    capsys.readouterr()
    rc = main(
        ["wosac-score", "--data", one, "--submission", str(sub), "--json", str(tmp_path / "s.json")]
    )
    _one_line_error(capsys, rc, "1c8f1f7b63fc6118", "WOSAC scoring")
    assert not (tmp_path / "s.json").exists()
    rc = main(["render", one, "--out", str(tmp_path / "x.mp4")])  # NPCs replay the log
    _one_line_error(capsys, rc, "1c8f1f7b63fc6118", "npc_policy='log_replay'")
    assert not (tmp_path / "x.mp4").exists()
    sc = load_scenarios(one)[0]
    with pytest.raises(MissingFutureError, match="log replay"):
        simulate_rollouts(sc, make_policy("log_replay"))
    # Ranking samples by agents leaving the road reads only the simulation: allowed.
    ranked = trafficbots_rollouts(
        load_default_model(), sc, num_rollouts=2, num_samples=4, road_edge_weight=1.0
    )
    assert ranked.num_rollouts == 2 and ranked.num_steps == 80


# ----------------------------------------------------------------------------- environments


@pytest.mark.parametrize("policy", ["constant_velocity", "trafficbots"])
def test_trafficenv_runs_the_whole_episode(history_scenes, policy) -> None:
    """The SDC is controlled, every other agent is an NPC of the policy from step 10 on (the
    log has nothing after it): all 80 steps run, nobody is frozen or dropped, and rewards and
    infos that compare with the log come out masked and finite."""
    never = EnvConfig(termination=TerminationConfig(collision=False, offroad=False, goal=False))
    env = TrafficEnv(history_scenes, controlled="sdc", npc_policy=policy, config=never)
    for k, sc in enumerate(history_scenes):
        env.reset(seed=0, options={"scenario_index": k})
        first = env.sim_state
        steps, rewards = 0, []
        while env.agents:
            # Expert actions are zero where the log has no next state: the SDC keeps its speed.
            _, rew, term, trunc, infos = env.step(env.expert_actions())
            rewards += list(rew.values())
            steps += 1
        assert steps == 80 and int(env.sim_state.step) == 90 and env.scenario is env.scenarios[k]
        assert list(trunc.values()) == [True] and not any(term.values())
        (info,) = infos.values()
        assert info["log_divergence"] == 0.0 and not info["goal_reached"]
        assert (
            np.isfinite(rewards).all()
            and np.isfinite([v for v in info.values() if isinstance(v, float)]).all()
        )
        last = env.sim_state
        present = torch.from_numpy(sc.tracks.valid[:, 10])
        assert torch.equal(last.valid[0, : sc.tracks.num_tracks], present)  # none dropped
        moved = torch.linalg.vector_norm(last.pose[0, :, :2] - first.pose[0, :, :2], dim=-1)
        fast = present & (first.speed[0, : sc.tracks.num_tracks].abs() > 1.0)
        assert fast.any() and (moved[: sc.tracks.num_tracks][fast] > 4.0).all()  # none frozen
        if policy == "constant_velocity":
            expect = first.speed[0, : sc.tracks.num_tracks].abs() * 8.0
            torch.testing.assert_close(
                moved[: sc.tracks.num_tracks][fast], expect[fast], rtol=1e-4, atol=1e-3
            )


def test_parallel_api_on_history_only_scenes(history_scenes) -> None:
    env = TrafficEnv(history_scenes[:1], controlled="sdc", npc_policy="constant_velocity")
    check_parallel_api(env, num_cycles=100)
    env = TrafficEnv(history_scenes, controlled="tracks_to_predict", npc_policy="trafficbots")
    check_parallel_api(env, num_cycles=100)


def test_envs_refuse_log_replay_past_the_log(history_scenes, history_dir) -> None:
    with pytest.raises(MissingFutureError, match=r"1c8f1f7b63fc6118 .*npc_policy='log_replay'"):
        TrafficEnv(history_scenes, npc_policy="log_replay")
    with pytest.raises(MissingFutureError, match="npc_policy='log_replay'"):
        BatchedTrafficEnv(history_dir, 2)  # log replay by default
    late = EnvConfig(start_step=20)
    with pytest.raises(MissingFutureError, match="an episode that starts at step 20"):
        TrafficEnv(history_scenes, npc_policy="constant_velocity", config=late)
    # A full scene replays its log to its end; an episode longer than the log needs a policy.
    full_env = TrafficEnv(history_dir / "tfrecord-00005-of-00150_792d65eb579314db.json",
                          npc_policy="log_replay")  # fmt: skip
    assert full_env.scenarios[0].has_future
    with pytest.raises(MissingFutureError, match="up to step 100"):
        TrafficEnv(full_env.scenarios, npc_policy="log_replay", config=EnvConfig(end_step=100))


def test_full_scene_npcs_go_on_under_the_policy_after_their_log(one_scenario_path) -> None:
    """``end_step`` past the log: every NPC is driven by the NPC policy after step 90 too."""
    never = TerminationConfig(collision=False, offroad=False, goal=False)
    config = EnvConfig(end_step=100, termination=never)
    env = TrafficEnv(one_scenario_path, npc_policy="constant_velocity", config=config)
    env.reset(seed=0)
    steps, at_90 = 0, None
    while env.agents:
        env.step({a: np.zeros(2, np.float32) for a in env.agents})
        steps += 1
        at_90 = env.sim_state if steps == 80 else at_90
    end = env.sim_state
    assert steps == 90 and int(at_90.step) == 90 and int(end.step) == 100
    assert env.scenarios[0].num_logged_steps == 91 and env.scenarios[0].num_steps == 101
    assert torch.equal(end.valid, at_90.valid)  # nobody left when the log ended
    moved = torch.linalg.vector_norm(end.pose[..., :2] - at_90.pose[..., :2], dim=-1)
    torch.testing.assert_close(moved, at_90.speed.abs() * at_90.valid, rtol=1e-4, atol=1e-3)
