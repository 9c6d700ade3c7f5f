"""The one neighbour-ranking rule (``tbsim_env.sim.knn.nearest_k``): 1 cm buckets, ties to the
lower id, the same selection from its int32 and int64 keys."""

from __future__ import annotations

import math

import pytest
import torch

from tbsim_env.sim.knn import nearest_k


def _reference(dist: torch.Tensor, k: int, ids: torch.Tensor | None = None) -> torch.Tensor:
    """Sort by (bucket, id) in Python: the rule written out."""
    out = []
    for row, d in enumerate(dist.reshape(-1, dist.shape[-1]).tolist()):
        col = list(range(len(d))) if ids is None else ids.reshape(-1, len(d))[row].tolist()
        bucket = [math.floor(min(x / 0.01 + 0.3819660112501051, 2.0**30)) for x in d]
        out.append(sorted(range(len(d)), key=lambda j: (bucket[j], col[j]))[:k])
    return torch.tensor(out).reshape(*dist.shape[:-1], k)


@pytest.mark.parametrize("m", [3, 32, 33, 64, 1024, 1025, 4097])
def test_int32_and_int64_keys_select_the_same_targets_within_reach(m: int) -> None:
    g = torch.Generator().manual_seed(m)
    dist = torch.rand(3, 5, m, generator=g) * 300.0
    dist[..., ::7] = dist[..., 1:2]  # exact ties
    dist[..., ::11] = float("inf")  # no target
    dist[0, 0, -1] = 3.0e6  # far beyond any radius
    k = min(m, 16)
    wide = nearest_k(dist, k)  # int64 key
    narrow = nearest_k(dist, k, exact_within=500.0)  # int32 key where it reaches
    # Everything the caller keeps (within its radius) is the same, in the same order; far
    # beyond it (3,000 km) targets may tie with "no target" in the int32 key.
    seen_w, seen_n = dist.gather(-1, wide) <= 500.0, dist.gather(-1, narrow) <= 500.0
    assert torch.equal(seen_w, seen_n) and torch.equal(wide[seen_w], narrow[seen_n])
    assert torch.equal(wide, nearest_k(dist, k, exact_within=math.inf))
    if m <= 64:
        assert torch.equal(wide, _reference(dist, k))


def test_ids_break_ties_and_rank_exactly_within_the_radius() -> None:
    g = torch.Generator().manual_seed(1)
    dist = torch.full((2, 4, 40), 50.0)  # all tie: the lower id wins
    ids = torch.stack([torch.randperm(1000, generator=g)[:40] for _ in range(8)]).reshape(2, 4, 40)
    pos = nearest_k(dist, 5, ids=ids, num_ids=1000, exact_within=200.0)
    assert torch.equal(ids.gather(-1, pos), ids.sort(-1).values[..., :5])
    assert torch.equal(pos, _reference(dist, 5, ids))
    with pytest.raises(ValueError, match="num_ids"):
        nearest_k(dist, 5, ids=ids)


def test_buckets_are_one_centimetre() -> None:
    # 1.004 m and 1.001 m share a bucket: the lower column (the farther one) goes first.
    dist = torch.tensor([[1.004, 1.001, 0.5, 1.02]])
    assert nearest_k(dist, 4, exact_within=10.0).tolist() == [[2, 0, 1, 3]]
