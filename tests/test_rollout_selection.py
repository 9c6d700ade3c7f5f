"""Choosing which sampled TrafficBots rollouts to keep for WOSAC: collisions, then off-road."""

from __future__ import annotations

import pytest
import torch

from policies.trafficbots.wosac import load_default_model, trafficbots_rollouts
from tbsim_env.data.generator import generate_scenario
from tbsim_env.evaluation import make_rollout_fn
from tbsim_env.metrics.wosac import offroad_indication, score_scenario, simulated_offroad
from tbsim_env.sim.horizon import wosac_scenario

pytestmark = pytest.mark.usefixtures("torch_one_thread")


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


def test_road_edge_weight_keeps_the_rollouts_that_stay_on_the_road(model, scenario, plain):
    everything = _run(model, scenario, N, 1000.0)  # all samples, off-road agents dominate
    off = simulated_offroad(scenario, everything).sum(-1)
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
    assert simulated_offroad(scenario, kept).sum(-1).max() <= off[3:].min()


@pytest.mark.parametrize("weight", [-1.0, float("nan"), float("inf")])
def test_bad_road_edge_weight_is_rejected(model, scenario, weight):
    with pytest.raises(ValueError, match="road_edge_weight"):
        _run(model, scenario, 3, weight)


def test_road_edge_weight_is_trafficbots_only():
    with pytest.raises(ValueError, match="trafficbots only"):
        make_rollout_fn("constant_velocity", road_edge_weight=1.0)
