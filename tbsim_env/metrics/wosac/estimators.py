"""Likelihood estimators of WOSAC: per-object histograms and Bernoulli (docs/metrics.md).

Pure torch functions, device-agnostic. Shapes: R rollouts, E evaluated objects, T future steps.
"""

from __future__ import annotations

import torch

from tbsim_env.metrics.wosac.config import HistogramSpec


def histogram_bin_index(values: torch.Tensor, spec: HistogramSpec) -> torch.Tensor:
    """Bin index of every value, exactly as ``tfp.stats.histogram`` after clipping.

    Values are clipped to [min, max]; bins are [e_k, e_{k+1}) with the last bin closed, and NaN
    falls into the last bin.

    Args:
        values: any shape, float (feature unit).
        spec: the feature's bins.

    Returns:
        int64 tensor of the same shape, in [0, num_bins).
    """
    interior = torch.tensor(spec.edges[1:-1], dtype=values.dtype, device=values.device)
    clipped = values.clamp(spec.min_val, spec.max_val)
    index = torch.searchsorted(interior, clipped.contiguous(), right=True)
    return torch.where(torch.isnan(values), spec.num_bins - 1, index)


def histogram_log_likelihood(
    log_values: torch.Tensor,
    sim_values: torch.Tensor,
    spec: HistogramSpec,
    pseudocount: float,
) -> torch.Tensor:
    """Log-likelihood of each logged value under its object's pooled simulated histogram.

    The sample of object i is every simulated value of i (all rollouts and steps, unmasked, NaNs
    included): p_k = (count_k + c) / (N + num_bins * c) with N = R * T
    (``independent_timesteps``, per-object histograms).

    Args:
        log_values: [E, T] logged feature values.
        sim_values: [R, E, T] simulated feature values.
        spec: the feature's bins.
        pseudocount: c, added to every bin.

    Returns:
        [E, T] float log-probabilities (natural log) of the logged values' bins.
    """
    r, e, t = sim_values.shape
    sim_bins = histogram_bin_index(sim_values, spec).permute(1, 0, 2).reshape(e, r * t)
    counts = torch.zeros(e, spec.num_bins, dtype=sim_values.dtype, device=sim_values.device)
    counts.scatter_add_(1, sim_bins, torch.ones_like(sim_bins, dtype=sim_values.dtype))
    prob = (counts + pseudocount) / (r * t + spec.num_bins * pseudocount)
    log_bins = histogram_bin_index(log_values, spec)
    return torch.log(prob).gather(1, log_bins)


def bernoulli_log_likelihood(
    log_flags: torch.Tensor, sim_flags: torch.Tensor, pseudocount: float
) -> torch.Tensor:
    """Log-likelihood of each object's logged indication under its simulated Bernoulli.

    p(log indication) = (rollouts agreeing with the log + c) / (R + 2c).

    Args:
        log_flags: [E] bool logged indication.
        sim_flags: [R, E] bool simulated indications.
        pseudocount: c (0.001 in the challenge configs).

    Returns:
        [E] float32 log-probabilities.
    """
    r = sim_flags.shape[0]
    agree = (sim_flags == log_flags.unsqueeze(0)).sum(0).to(torch.float32)
    return torch.log((agree + pseudocount) / (r + 2.0 * pseudocount))


def masked_likelihood(log_likelihood: torch.Tensor, mask: torch.Tensor) -> float:
    """exp(mean of the log-likelihood over the masked entries), pooled over every axis.

    An empty mask gives NaN (the official 0/0).

    Args:
        log_likelihood: any shape, float.
        mask: bool, same shape.
    """
    total = torch.where(mask, log_likelihood, 0.0).sum()
    return float(torch.exp(total / mask.sum()))
