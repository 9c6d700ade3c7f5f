"""Multi-layer perceptrons used by the encoders and heads."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import nn


class MLP(nn.Module):
    """``MLP[a, b, c, ...]``: Linear layers with ReLU between them (docs/model.md §3 convention).

    Args:
        dims: layer widths, input first.
        dropout: dropout after each hidden ReLU.
        layer_norm: LayerNorm after each hidden Linear, before the ReLU (``MLP_LN``).
        end_activation: also apply ReLU (and dropout) after the last Linear (AddNaviLatent).
    """

    def __init__(
        self,
        dims: Sequence[int],
        dropout: float = 0.0,
        layer_norm: bool = False,
        end_activation: bool = False,
    ) -> None:
        super().__init__()
        layers: list[nn.Module] = []
        n = len(dims) - 1
        for i in range(n):
            layers.append(nn.Linear(dims[i], dims[i + 1]))
            last = i == n - 1
            if last and not end_activation:
                break
            if layer_norm and not last:
                layers.append(nn.LayerNorm(dims[i + 1]))
            layers.append(nn.ReLU())
            if dropout > 0:
                layers.append(nn.Dropout(dropout))
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """[..., dims[0]] -> [..., dims[-1]]."""
        return self.net(x)
