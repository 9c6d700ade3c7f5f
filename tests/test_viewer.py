"""The rollout viewer's embedded data (no browser): contents against the scenario and WOSAC.

The browser side (page loads, slider, clicks, screenshot) is in ``test_viewer_browser.py``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from tbsim_env.cli import main
from tbsim_env.core.constants import NUM_FUTURE, SIGNAL_TO_TL_STATE, MapFeatureType, ObjectType
from tbsim_env.data import load_scenarios
from tbsim_env.evaluation import make_rollout_fn
from tbsim_env.metrics.wosac.scoring import scenario_features
from tbsim_env.rendering import GROUP_COLORS, AgentGroup
from tbsim_env.rendering.viewer import (
    ViewerError,
    build_viewer_data,
    embedded_data,
    log_rollout,
    simulated_rollouts,
    viewer_html,
)

TOL = 0.006  # m: positions are embedded rounded to 1 cm


@pytest.fixture(scope="module")
def scenario(one_scenario_path: Path, torch_one_thread):
    return load_scenarios(one_scenario_path)[0]


@pytest.fixture(scope="module")
def rollouts(scenario):
    return make_rollout_fn("constant_velocity")(scenario, 3, 7)


@pytest.fixture(scope="module")
def data(scenario, rollouts) -> dict:
    shown = [*simulated_rollouts(scenario, rollouts), log_rollout(scenario)]
    return embedded_data(viewer_html(build_viewer_data(scenario, shown, "test")))


def _array(nested: list) -> np.ndarray:
    return np.array([[np.nan if v is None else v for v in row] for row in nested], np.float64)


def test_agents_and_palette(scenario, data: dict) -> None:
    t = scenario.tracks
    assert [a["id"] for a in data["agents"]] == t.id.tolist()
    assert [a["type"] for a in data["agents"]] == [
        ObjectType(int(k)).name.lower() for k in t.object_type
    ]
    cur = scenario.current_index
    sim = t.valid[:, cur]
    assert [a["sim_agent"] for a in data["agents"]] == sim.tolist()
    assert [a["sdc"] for a in data["agents"]].index(True) == scenario.sdc_index
    lengths = np.array([a["length"] for a in data["agents"]])
    np.testing.assert_allclose(lengths[sim], t.size[sim, cur, 0], atol=TOL)
    for g in AgentGroup:
        assert data["palette"]["groups"][str(int(g))]["color"] == list(GROUP_COLORS[g])
    assert data["num_steps"] == cur + 1 + NUM_FUTURE and data["current_step"] == cur


def test_log_rollout_is_the_log(scenario, data: dict) -> None:
    log = data["rollouts"][-1]
    assert log["name"] == "log"
    t = scenario.tracks
    x, y = _array(log["x"]), _array(log["y"])
    assert np.array_equal(np.isfinite(x), t.valid)
    np.testing.assert_allclose(x[t.valid], t.xyz[..., 0][t.valid], atol=TOL)
    np.testing.assert_allclose(y[t.valid], t.xyz[..., 1][t.valid], atol=TOL)
    expected = np.zeros(t.num_tracks, int)
    expected[scenario.sdc_index] = int(AgentGroup.SDC)
    assert log["group"] == expected.tolist()


def test_simulated_rollouts_are_history_then_rollout(scenario, rollouts, data: dict) -> None:
    cur, t = scenario.current_index, scenario.tracks
    sim = np.flatnonzero(t.valid[:, cur])
    pos = {int(i): k for k, i in enumerate(rollouts.object_id.tolist())}
    for r in range(rollouts.num_rollouts):
        entry = data["rollouts"][r]
        x, y = _array(entry["x"]), _array(entry["y"])
        assert entry["name"] == f"rollout {r}"
        for a in sim:
            k = pos[int(t.id[a])]
            np.testing.assert_allclose(x[a, cur + 1 :], rollouts.x[r, k].numpy(), atol=TOL)
            np.testing.assert_allclose(y[a, cur + 1 :], rollouts.y[r, k].numpy(), atol=TOL)
            hist = t.valid[a, : cur + 1]
            np.testing.assert_allclose(
                x[a, : cur + 1][hist], t.xyz[a, : cur + 1, 0][hist], atol=TOL
            )
        others = np.setdiff1d(np.arange(t.num_tracks), sim)
        assert np.isnan(x[others]).all()
        assert all(entry["group"][a] == -1 for a in others)
        sdc_group = entry["group"][scenario.sdc_index]
        assert sdc_group == int(AgentGroup.SDC)
        assert {entry["group"][a] for a in sim} - {sdc_group} == {int(AgentGroup.POLICY)}


def test_flags_are_the_wosac_indications(scenario, rollouts, data: dict) -> None:
    """Per step, the flags of the evaluated agents equal WOSAC's scoring features."""
    f = scenario_features(scenario, rollouts)
    first = scenario.current_index + 1
    index_of = {int(i): a for a, i in enumerate(scenario.tracks.id)}
    eval_tracks = [index_of[int(i)] for i in f.objects.eval_ids]
    seen = {"collision": 0, "offroad": 0}
    for name, field in (("collision", "collision_per_step"), ("offroad", "offroad_per_step")):
        wosac = getattr(f.sim_features, field)  # [R, E, F]
        for r in range(rollouts.num_rollouts):
            steps = data["rollouts"][r][name]
            for e, a in enumerate(eval_tracks):
                expected = (torch.nonzero(wosac[r, e]).flatten() + first).tolist()
                assert steps[a] == expected, (name, r, a)
        seen[name] = sum(len(s) > 0 for r in range(3) for s in data["rollouts"][r][name])
    # Constant velocity on this scene drives agents into others and off the road.
    assert seen["collision"] > 0 and seen["offroad"] > 0
    assert data["rollouts"][0]["flagged"] == scenario.tracks.valid[:, first - 1].tolist()


def test_signals_and_map(scenario, data: dict) -> None:
    sig = scenario.signals
    state = np.array(data["signals"]["state"])
    steps = min(sig.state.shape[1], state.shape[1])
    tl = np.asarray(SIGNAL_TO_TL_STATE)[sig.state[:, :steps].astype(int)]
    np.testing.assert_array_equal(state[:, :steps], np.where(sig.valid[:, :steps], tl, -1))
    rm = scenario.road_map

    def count(kind: MapFeatureType, min_points: int) -> int:
        return sum(1 for k in rm.indices_of(kind) if rm.polylines[k].shape[0] >= min_points)

    m = data["map"]
    assert len(m["lanes"]) == count(MapFeatureType.LANE, 2) > 0
    assert len(m["road_edges"]) == count(MapFeatureType.ROAD_EDGE, 2) > 0
    assert len(m["crosswalks"]) == count(MapFeatureType.CROSSWALK, 2) > 0
    assert len(m["stop_signs"]) == count(MapFeatureType.STOP_SIGN, 1)
    assert len(m["road_lines"]) >= count(MapFeatureType.ROAD_LINE, 2)


def test_embedding_escapes_script_end(scenario) -> None:
    html = viewer_html(build_viewer_data(scenario, [log_rollout(scenario)], "</script><b>x"))
    assert html.count("</script>") == 1 and html.count("<script>") == 1
    # Self-contained: nothing fetched (no src/href/url/import, no address).
    page = html[: html.index("const TBSIM_DATA")] + html[html.index("(function () {") :]
    for fetch in ("src=", "href=", "url(", "@import", "http:", "https:", "fetch(", "import("):
        assert fetch not in page, fetch
    assert embedded_data(html)["title"] == "</script><b>x"


def test_refusals(scenario, rollouts) -> None:
    from dataclasses import replace

    with pytest.raises(ViewerError, match="rollouts are for scenario"):
        simulated_rollouts(scenario, replace(rollouts, scenario_id="other"))
    short = replace(
        rollouts,
        x=rollouts.x[..., :5],
        y=rollouts.y[..., :5],
        z=rollouts.z[..., :5],
        heading=rollouts.heading[..., :5],
    )
    with pytest.raises(ViewerError, match="5 steps"):
        simulated_rollouts(scenario, short)
    with pytest.raises(ViewerError, match="nothing to show"):
        build_viewer_data(scenario, [])


def test_cli_view(one_scenario_path: Path, womd_dir: Path, tmp_path: Path, capsys) -> None:
    out = tmp_path / "v.html"
    path = str(one_scenario_path)
    policy = ["--policy", "constant_velocity", "--rollouts", "2"]
    assert main(["view", path, *policy, "--out", str(out)]) == 0
    names = [r["name"] for r in embedded_data(out.read_text())["rollouts"]]
    assert names == ["constant_velocity 0", "constant_velocity 1", "log"]
    sub = womd_dir / "wosac_reference" / "rollouts_const_vel.binproto"
    assert main(["view", path, "--submission", str(sub), "--out", str(out)]) == 0
    assert len(embedded_data(out.read_text())["rollouts"]) == 33
    # A folder: the first scenario, or with a submission the first one it holds.
    folder = tmp_path / "mixed"
    folder.mkdir()
    for p in sorted((womd_dir / "gpudrive").glob("*.json")):
        (folder / p.name).symlink_to(p)
    (folder / "z.tfrecord").symlink_to(one_scenario_path)  # sorted last
    assert main(["view", str(folder), "--out", str(out)]) == 0
    assert embedded_data(out.read_text())["scenario_id"] != "637f20cafde22ff8"
    assert main(["view", str(folder), "--submission", str(sub), "--out", str(out)]) == 0
    assert embedded_data(out.read_text())["scenario_id"] == "637f20cafde22ff8"
    assert main(["view", path, "--scenario-id", "nope", "--out", str(out)]) == 2
    assert "no scenario 'nope'" in capsys.readouterr().err


def test_history_only_scene(womd_dir: Path) -> None:
    """A WOSAC test-split scene (11 logged steps): the log ends at the current step, the
    policy's rollouts cover the 80 steps after it."""
    from tbsim_env.rendering.viewer import policy_rollouts

    folder = womd_dir / "gpudrive_history" / "gpudrive"
    sc = next(s for s in load_scenarios(folder) if not s.has_future)
    shown = [*policy_rollouts(sc, "constant_velocity", num_rollouts=1), log_rollout(sc)]
    d = build_viewer_data(sc, shown)
    cur = sc.current_index
    assert d["num_steps"] == cur + 1 + NUM_FUTURE
    sim = sc.tracks.valid[:, cur]
    rollout, log = _array(d["rollouts"][0]["x"]), _array(d["rollouts"][1]["x"])
    assert np.isfinite(rollout[sim]).all() and np.isnan(rollout[~sim]).all()
    assert np.isnan(log[:, cur + 1 :]).all()
    assert np.array_equal(np.isfinite(log[:, : cur + 1]), sc.tracks.valid[:, : cur + 1])
    signals = np.array(d["signals"]["state"], int).reshape(-1, d["num_steps"])
    assert (signals[:, cur + 1 :] == -1).all()
