"""WOSAC configs (weights, bins, versions) and likelihood estimators on hand-computed cases."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from tbsim_env.metrics.wosac.config import (
    BUCKETS,
    HISTOGRAMS,
    WOSAC_2024,
    WOSAC_2025,
    MetricVersion,
    WosacConfigError,
    get_config,
    parse_version,
)
from tbsim_env.metrics.wosac.estimators import (
    bernoulli_log_likelihood,
    histogram_bin_index,
    histogram_log_likelihood,
    masked_likelihood,
)


@pytest.mark.parametrize("config", [WOSAC_2024, WOSAC_2025])
def test_weights_sum_to_one(config):
    assert config.weights.total() == pytest.approx(1.0, abs=1e-12)
    assert sum(config.bucket_weight(b) for b in BUCKETS) == pytest.approx(1.0, abs=1e-12)


def test_version_specific_weights():
    assert WOSAC_2024.weights.traffic_light_violation == 0.0
    assert WOSAC_2024.weights.distance_to_road_edge == 0.10
    assert WOSAC_2025.weights.traffic_light_violation == 0.05
    assert WOSAC_2025.weights.distance_to_road_edge == 0.05
    assert WOSAC_2025.ttc_vehicles_only and not WOSAC_2024.ttc_vehicles_only
    assert WOSAC_2024.bucket_weight("interactive") == pytest.approx(0.45)
    assert WOSAC_2025.bucket_weight("map_based") == pytest.approx(0.35)


def test_version_parsing():
    assert parse_version("wosac2024") is MetricVersion.WOSAC2024
    assert parse_version("WOSAC2025") is MetricVersion.WOSAC2025
    assert get_config() is WOSAC_2025
    with pytest.raises(WosacConfigError, match="unknown WOSAC metric version 'wosac2023'"):
        parse_version("wosac2023")


def test_bin_edges_are_the_float32_tf_values():
    # The 11-bin edges are TF's float32 linspace values, not a float64 linspace rounded to
    # float32 (docs/metrics.md, "Histograms"); note the asymmetry around 0.
    edges = HISTOGRAMS.linear_acceleration.edges
    assert edges[6] == float(np.float32("1.09091")) != -edges[5]
    assert edges[6] != float(np.float32(np.linspace(-12.0, 12.0, 12)[6]))
    assert HISTOGRAMS.angular_speed.max_val == float(np.float32(0.628))
    assert HISTOGRAMS.distance_to_road_edge.edges[:4] == (-20.0, -14.0, -8.0, -2.0)
    for spec in (HISTOGRAMS.linear_speed, HISTOGRAMS.time_to_collision):
        assert spec.num_bins == 10 and len(spec.edges) == 11
        assert all(float(np.float32(e)) == e for e in spec.edges)


def test_histogram_bins_nan_to_last_bin_and_closed_last_bin():
    spec = HISTOGRAMS.linear_speed  # 0, 2.5, ..., 25
    values = torch.tensor([-1.0, 0.0, 2.4999, 2.5, 24.9, 25.0, 99.0, float("nan")])
    got = histogram_bin_index(values, spec).tolist()
    assert got == [0, 0, 0, 1, 9, 9, 9, 9]


def test_histogram_log_likelihood_hand_computed():
    spec = HISTOGRAMS.time_to_collision  # 10 bins of 0.5 s on [0, 5]
    # One object, 2 rollouts x 2 steps: values in bins 0, 0, 9 (5.0) and 9 (NaN).
    sim = torch.tensor([[[0.1, 0.2]], [[5.0, float("nan")]]])
    log = torch.tensor([[0.3, 2.0]])  # bins 0 and 4
    ll = histogram_log_likelihood(log, sim, spec, pseudocount=0.1)
    denom = 4 + 10 * 0.1
    expected = [math.log((2 + 0.1) / denom), math.log(0.1 / denom)]
    assert ll.shape == (1, 2)
    assert ll[0].tolist() == pytest.approx(expected, rel=1e-6)


def test_bernoulli_log_likelihood_hand_computed():
    sim = torch.tensor([[True, False], [True, False], [False, False], [True, False]])
    log = torch.tensor([True, True])
    ll = bernoulli_log_likelihood(log, sim, pseudocount=0.001)
    expected = [math.log(3.001 / 4.002), math.log(0.001 / 4.002)]
    assert ll.tolist() == pytest.approx(expected, rel=1e-6)


def test_masked_likelihood_pools_pairs_and_empty_is_nan():
    ll = torch.log(torch.tensor([[0.5, 0.25], [1.0, 0.1]]))
    mask = torch.tensor([[True, True], [True, False]])
    assert masked_likelihood(ll, mask) == pytest.approx((0.5 * 0.25 * 1.0) ** (1 / 3), rel=1e-6)
    assert math.isnan(masked_likelihood(ll, torch.zeros_like(mask)))
