"""Validation loss of a TrafficBots model on a token cache: the training objective without its
randomness, for choosing among checkpoints while (or right after) training.

Every scene of the cache is rolled out once in closed loop with the posterior personality, no
teacher forcing, no dropout and no input dropout, under ``torch.no_grad``; the loss terms of
``losses.training_step`` are averaged over the scenes. The model stays in train mode so that
the inference rules (gap keeping, road keeping, ...) stay off: the figure is the network's
imitation of the log, comparable between checkpoints, not a realism score (``tbsim
evaluate`` scores rollouts with the WOSAC metrics).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch
from torch import nn
from torch.utils.data import Dataset

from policies.trafficbots.batch import TokenBatch
from policies.trafficbots.losses import training_step
from policies.trafficbots.model import TrafficBots

TERMS = ("loss", "imitation", "kl", "destination", "tl_state")
"""The loss terms averaged (``training_step``'s logged scalars)."""


@contextlib.contextmanager
def dropout_off(model: nn.Module) -> Iterator[None]:
    """Set every ``nn.Dropout`` of ``model`` to p = 0 while the block runs (restored on exit)."""
    saved = [(m, m.p) for m in model.modules() if isinstance(m, nn.Dropout)]
    for m, _ in saved:
        m.p = 0.0
    try:
        yield
    finally:
        for m, p in saved:
            m.p = p


@torch.no_grad()
def validation_loss(
    model: TrafficBots,
    data: Dataset,
    *,
    batch_size: int = 8,
    seed: int = 0,
    device: torch.device | str = "cpu",
) -> dict[str, float]:
    """Mean loss terms of ``model`` over every scene of ``data`` (see the module docstring).

    Args:
        model: the network (its mode is restored on return).
        data: a token dataset (``tbsim_env.data.cache.open_training_data``).
        batch_size: scenes per rollout batch (each batch's losses are means over its agents,
            weighted here by its scenes: compare checkpoints at one batch size).
        seed: seed of the generator that draws the posterior personality.
        device: where to roll out.

    Returns:
        ``{term: mean over scenes}`` for ``TERMS``, and ``"scenes"``.

    Raises:
        ValueError: an empty dataset or a batch size below 1.
    """
    if batch_size < 1:
        raise ValueError(f"batch_size must be >= 1, got {batch_size}")
    if len(data) == 0:
        raise ValueError("validation data holds no scenes")
    was_training = model.training
    model.train()
    sums = dict.fromkeys(TERMS, 0.0)
    try:
        with dropout_off(model):
            for start in range(0, len(data), batch_size):
                items = [data[i] for i in range(start, min(start + batch_size, len(data)))]
                batch = TokenBatch.from_tokens(items, device=device).trim()
                gen = torch.Generator(device=batch.device).manual_seed(seed + start)
                _, logs = training_step(
                    model, batch, prior_prob=0.0, generator=gen, input_dropout_p=0.0
                )
                for term in TERMS:
                    sums[term] += logs[term] * len(items)
    finally:
        model.train(was_training)
    out = {term: total / len(data) for term, total in sums.items()}
    out["scenes"] = float(len(data))
    return out
