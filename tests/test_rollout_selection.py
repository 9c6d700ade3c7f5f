"""Choosing which sampled TrafficBots rollouts to keep for WOSAC: collisions, then off-road."""

from __future__ import annotations

import pytest
import torch

from policies.trafficbots.wosac import load_default_model, trafficbots_rollouts
from tbsim_env.data.generator import generate_scenario
from tbsim_env.evaluation import make_rollout_fn
from tbsim_env.metrics.wosac import (
    offroad_indication,
    score_scenario,
    simulated_offroad,
    simulated_road_departure,
)
from tbsim_env.sim.horizon import wosac_scenario

pytestmark = [pytest.mark.usefixtures("torch_one_thread"), pytest.mark.float_sensitive]


N = 6  # samples per call


@pytest.fixture(scope="module")
def model():
    return load_default_model()


@pytest.fixture(scope="module")
def scenario():
    # With the shipped weights, 0 to 2 of its evaluated agents leave the road per sample.
    return generate_scenario("intersection", 4)


def _run(model, scenario, keep: int, weight: float):
    return trafficbots_rollouts(
        model, scenario, num_rollouts=keep, num_samples=N, seed=11, road_edge_weight=weight
    )


@pytest.fixture(scope="module")
def plain(model, scenario):
    return _run(model, scenario, N, 0.0)  # all samples, ranked by collisions (the spec)


def test_offroad_indication_is_the_scored_offroad_rate(plain, scenario):
    flags = offroad_indication(scenario, plain)
    scores = score_scenario(scenario, plain)
    assert flags.shape == (N, scores.num_evaluated)
    assert float(flags.float().mean()) == pytest.approx(scores.simulated_offroad_rate)


def test_simulated_offroad_counts_every_step_and_needs_no_logged_future(plain, scenario):
    flags = simulated_offroad(scenario, plain)
    scored = offroad_indication(scenario, plain)  # only where the log is valid
    assert flags.shape == scored.shape
    assert not (scored & ~flags).any()  # every scored off-road agent is flagged
    # The same flags on the scene cut to its history (the future invalid, as in the WOSAC
    # test split), put back on WOSAC's time grid.
    history = wosac_scenario(scenario.on_time_grid(scenario.current_index + 1))
    assert torch.equal(simulated_offroad(history, plain), flags)


def test_road_departure_counts_only_agents_on_the_road_now(scenario, plain):
    """An evaluated agent driven into a lot corner of the junction departs from the road
    when it starts on it, and does not when it already stands in the lot at the current step;
    the other agents' flags stay as they are."""
    import dataclasses

    from tbsim_env.data.generator import frame_offset
    from tbsim_env.metrics.wosac.trajectories import select_objects

    t0 = scenario.current_index
    e = int(select_objects(scenario).track_index[0])
    dx, dy = frame_offset("intersection", 4)
    lot = (dx + 40.0, dy + 40.0)  # 40 m from both roads' axes
    j = int((plain.object_id == int(scenario.tracks.id[e])).nonzero()[0, 0])
    x, y = plain.x.clone(), plain.y.clone()
    x[:, j, -5:], y[:, j, -5:] = lot[0], lot[1]
    into_lot = dataclasses.replace(plain, x=x, y=y)
    assert simulated_offroad(scenario, into_lot)[:, 0].all()
    dep = simulated_road_departure(scenario, into_lot)
    assert dep[:, 0].all(), "it starts on the road"
    xyz = scenario.tracks.xyz.copy()
    xyz[e, t0, :2] = lot
    parked = dataclasses.replace(scenario, tracks=dataclasses.replace(scenario.tracks, xyz=xyz))
    dep_parked = simulated_road_departure(parked, into_lot)
    assert not dep_parked[:, 0].any()
    assert torch.equal(dep_parked[:, 1:], dep[:, 1:])
    assert not (dep & ~simulated_offroad(scenario, into_lot)).any()


def test_road_edge_weight_keeps_the_rollouts_that_stay_on_the_road(model, scenario, plain):
    everything = _run(model, scenario, N, 1000.0)  # all samples, departures dominate
    off = simulated_road_departure(scenario, everything).sum(-1)
    assert off.min() < off.max(), "premise: the samples differ in off-road agents"
    assert torch.equal(off, off.sort().values)  # ranked by off-road count
    # The same samples as without the weight, in another order.
    key = lambda r: sorted(r.x[:, :, -1].sum(-1).tolist())  # noqa: E731
    assert key(plain) == pytest.approx(key(everything))
    assert not torch.equal(plain.x, everything.x)
    # Keeping 3 keeps the first 3 of that ranking.
    kept = _run(model, scenario, 3, 1000.0)
    assert torch.equal(kept.x, everything.x[:3])
    assert torch.equal(kept.heading, everything.heading[:3])
    assert simulated_road_departure(scenario, kept).sum(-1).max() <= off[3:].min()


@pytest.mark.parametrize("weight", [-1.0, float("nan"), float("inf")])
def test_bad_road_edge_weight_is_rejected(model, scenario, weight):
    with pytest.raises(ValueError, match="road_edge_weight"):
        _run(model, scenario, 3, weight)


def test_road_edge_weight_is_trafficbots_only():
    with pytest.raises(ValueError, match="trafficbots only"):
        make_rollout_fn("constant_velocity", road_edge_weight=1.0)


def test_default_weight_is_the_inference_configs(model, scenario, plain):
    """None takes ``InferenceConfig.road_edge_weight``: 1 shipped, 0 under the spec's rules."""
    import dataclasses

    from policies.trafficbots.config import InferenceConfig

    assert model.inference.road_edge_weight == 1.0
    assert InferenceConfig.spec().road_edge_weight == 0.0
    default = trafficbots_rollouts(model, scenario, num_rollouts=3, num_samples=N, seed=11)
    assert torch.equal(default.x, _run(model, scenario, 3, 1.0).x)
    shipped = model.inference
    try:
        model.inference = dataclasses.replace(shipped, road_edge_weight=0.0)
        zero = trafficbots_rollouts(model, scenario, num_rollouts=N, num_samples=N, seed=11)
    finally:
        model.inference = shipped
    assert torch.equal(zero.x, plain.x)


@pytest.mark.parametrize("weight", [-1.0, float("nan"), float("inf")])
def test_inference_config_rejects_bad_road_edge_weight(weight):
    from policies.trafficbots.config import InferenceConfig

    with pytest.raises(ValueError, match="road_edge_weight"):
        InferenceConfig(road_edge_weight=weight)
