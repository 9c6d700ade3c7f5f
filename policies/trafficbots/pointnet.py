"""PointNet (the VectorNet subgraph) over the nodes of map pieces or the steps of a window."""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn


def max_valid(x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """Max over the node dimension of the valid entries of a non-negative ``x`` (0 where a row
    has no valid entry): for ``x >= 0`` this is the max of the valid entries exactly.

    Args:
        x: [..., n, c] with ``x >= 0`` (ReLU outputs).
        valid: [..., n, 1] bool.

    Returns:
        [..., c].
    """
    return torch.where(valid, x, 0.0).amax(dim=-2)


class PointNet(nn.Module):
    """Three (configurable) layers of Linear(d, d/2) + ReLU + Dropout, then concat of the max
    over nodes; a final max-pool over the valid nodes (docs/model.md §3).

    Computed in a factored order (same function and parameters as the spec's steps, which
    ``pointnet_reference`` transcribes for the tests):

    * a layer's input ``[h_i, max_j h_j]`` is never built: its Linear splits into
      ``W_node h_i + (W_pool max_j h_j + b)``, the second term once per token, not per node
      (half the layer's multiply-adds, no concatenated copy);
    * invalid nodes are not zeroed between layers: every node is computed on its own, so they
      reach the output only through the max-pools, which skip them;
    * the final pool of ``[h_i, max_j h_j]`` is ``[max_j h_j, max_j h_j]``.

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
        keep = valid[..., None]
        h = self.dropout(torch.relu(self.layers[0](x)))  # [..., n, d/2], >= 0
        for layer in self.layers[1:]:
            w_node, w_pool = layer.weight.split(h.shape[-1], dim=1)
            pooled = F.linear(max_valid(h, keep), w_pool, layer.bias)  # [..., d/2]
            h = self.dropout(torch.relu(F.linear(h, w_node) + pooled[..., None, :]))
        pooled = max_valid(h, keep)
        return torch.cat([pooled, pooled], dim=-1)


def pointnet_reference(net: PointNet, x: torch.Tensor, valid: torch.Tensor) -> torch.Tensor:
    """``PointNet.forward`` in the reference's order (docs/model.md §3: -inf at invalid nodes,
    concat the max, zero invalid nodes, final max-pool); for tests."""

    def masked_max(y: torch.Tensor) -> torch.Tensor:
        pooled = y.masked_fill(~valid[..., None], float("-inf")).amax(dim=-2)
        return torch.where(valid.any(-1)[..., None], pooled, torch.zeros_like(pooled))

    for layer in net.layers:
        h = net.dropout(torch.relu(layer(x)))
        x = torch.cat([h, masked_max(h)[..., None, :].expand_as(h)], dim=-1)
        x = x.masked_fill(~valid[..., None], 0.0)
    return masked_max(x)
