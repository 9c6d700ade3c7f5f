"""PointNet (the VectorNet subgraph) over the nodes of map pieces or the steps of a window."""

from __future__ import annotations

import torch
from torch import nn


def masked_max(x: torch.Tensor, valid: torch.Tensor, dim: int) -> torch.Tensor:
    """Max over ``dim`` of the valid entries; rows without a valid entry give 0.

    Args:
        x: [..., n, d].
        valid: [..., n] bool.
        dim: the node dimension of ``x`` (negative, counting ``d``).

    Returns:
        x reduced over ``dim``.
    """
    pooled = x.masked_fill(~valid[..., None], float("-inf")).amax(dim=dim)
    any_valid = valid.any(dim=dim + 1 if dim < 0 else dim)
    return torch.where(any_valid[..., None], pooled, torch.zeros_like(pooled))


class PointNet(nn.Module):
    """Three (configurable) layers of Linear(d, d/2) + ReLU + Dropout, then concat of the max
    over nodes; a final max-pool over the valid nodes (spec section 3).

    Args:
        dim: feature width d (input and output).
        n_layers: layers (3).
        dropout: dropout after each ReLU.
    """

    def __init__(self, dim: int, n_layers: int = 3, dropout: float = 0.1) -> None:
        super().__init__()
        self.layers = nn.ModuleList(nn.Linear(dim, dim // 2) for _ in range(n_layers))
        self.dropout = nn.Dropout(dropout)

    def forward(self, x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
        """Pool node features into one token.

        Args:
            x: [..., n, d] node features.
            valid: [..., n] bool.

        Returns:
            [..., d]; 0 for tokens without a valid node.
        """
        for layer in self.layers:
            h = self.dropout(torch.relu(layer(x)))  # [..., n, d/2]
            h_max = masked_max(h, valid, dim=-2)  # [..., d/2]
            x = torch.cat([h, h_max[..., None, :].expand_as(h)], dim=-1)
            x = x.masked_fill(~valid[..., None], 0.0)
        return masked_max(x, valid, dim=-2)
