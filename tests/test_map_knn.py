"""The clustered nearest-map-piece search (``tbsim_env.map_knn``) equals the full search."""

from __future__ import annotations

import math

import pytest
import torch

from tbsim_env import constants as C
from tbsim_env.data import load_scenarios
from tbsim_env.data.generator import default_scenarios
from tbsim_env.map_knn import candidate_pieces, nearest_pieces, scene_clusters, search_holds
from tbsim_env.observation import ObsConfig, build_map_context
from tbsim_env.sim.build import build_sim_state
from tbsim_env.sim.knn import k_nearest


@pytest.fixture(scope="module")
def contexts(womd_dir):
    wod = womd_dir / "waymo-open-dataset"
    real = [
        *load_scenarios(wod / "motion_data_one_scenario.tfrecord"),
        *load_scenarios(wod / "womd_scenario_input.tfrecord"),
    ]
    out = {}
    for name, scenes in (("real", real), ("generated", default_scenarios(3))):
        state = build_sim_state(scenes)
        out[name] = build_map_context(scenes, state.origin, ObsConfig())
    return out


def _pieces(ctx, me, k, within):
    """``nearest_pieces`` over a map context's pieces, as the observations search them."""
    return nearest_pieces(ctx.knn_xy[:, :, : ctx.pose.shape[1]], ctx.clusters, me, k, within)


def _observers(ctx, gen: torch.Generator, q: int = 300) -> torch.Tensor:
    """[B, q, 2]: points near random valid pieces (up to 60 m off), and a few 1-3 km away."""
    rows = []
    for b in range(ctx.valid.shape[0]):
        xy = ctx.pose[b, ctx.valid[b], :2]
        pick = torch.randint(len(xy), (q,), generator=gen)
        pts = xy[pick] + (torch.rand(q, 2, generator=gen) - 0.5) * 120.0
        pts[:5] = xy.mean(0) + torch.tensor([1000.0, -3000.0]) * torch.rand(5, 1, generator=gen)
        rows.append(pts)
    return torch.stack(rows)


def _piece_xy(ctx) -> torch.Tensor:
    """[B, M + 1, 2] piece anchor points, +inf for padding pieces and the sentinel index M."""
    xy = ctx.pose[..., :2].masked_fill(~ctx.valid[..., None], float("inf"))
    return torch.cat([xy, torch.full_like(xy[:, :1], float("inf"))], 1)


def _full(ctx, me_xy: torch.Tensor, k: int):
    """The plain search over every piece (distances as the observation computes them)."""
    m = ctx.pose.shape[1]
    dx = ctx.knn_xy[:, :, :m, 0] - me_xy[..., 0:1]
    dy = ctx.knn_xy[:, :, :m, 1] - me_xy[..., 1:2]
    return k_nearest(torch.sqrt(dx * dx + dy * dy), None, k, math.inf)  # the int64 key


@pytest.mark.parametrize("name", ["real", "generated"])
def test_clustered_search_equals_the_full_search(contexts, name):
    ctx = contexts[name]
    gen = torch.Generator().manual_seed(0)
    me = _observers(ctx, gen)
    k = ObsConfig().num_map
    idx, top = _pieces(ctx, me, k, ObsConfig().map_radius)
    ref_idx, ref_top = _full(ctx, me, k)
    assert torch.equal(top, ref_top)
    finite = torch.isfinite(ref_top)
    assert torch.equal(idx[finite], ref_idx[finite])


def test_the_clustered_search_holds_near_the_map_and_not_far_away(contexts):
    ctx = contexts["real"]
    assert ctx.clusters.num_clusters > C.MAP_KNN_CLUSTERS, "the real maps use the clustered path"
    gen = torch.Generator().manual_seed(1)
    me = _observers(ctx, gen)
    cand, bound, cand_xy = candidate_pieces(ctx.clusters, me, C.MAP_KNN_CLUSTERS)
    xy = torch.stack([_piece_xy(ctx)[b, cand[b]] for b in range(len(cand))])
    assert torch.equal(xy, cand_xy)  # the clusters' own copy of the anchor points
    dx, dy = xy[..., 0] - me[..., 0:1], xy[..., 1] - me[..., 1:2]
    d = torch.sqrt(dx * dx + dy * dy)
    m = ctx.pose.shape[1]
    _, top = k_nearest(d, None, ObsConfig().num_map, ObsConfig().map_radius, ids=(cand, m))
    holds = search_holds(top[..., -1], bound)
    assert holds[:, 5:].float().mean() > 0.95  # near the map: the clusters suffice
    # Where it holds, the candidates' k nearest are the true ones.
    ref_idx, ref_top = _full(ctx, me, ObsConfig().num_map)
    assert torch.equal(top[holds], ref_top[holds])


def test_a_search_of_too_few_clusters_falls_back_to_the_full_search(contexts, monkeypatch):
    ctx = contexts["real"]
    monkeypatch.setattr(C, "MAP_KNN_CLUSTERS", 2)  # 32 candidates cannot hold 64 nearest
    me = _observers(ctx, torch.Generator().manual_seed(2), q=50)
    idx, top = _pieces(ctx, me, ObsConfig().num_map, ObsConfig().map_radius)
    ref_idx, ref_top = _full(ctx, me, ObsConfig().num_map)
    assert torch.equal(top, ref_top) and torch.equal(idx, ref_idx)


def test_clusters_are_compact_and_cover_every_valid_piece(contexts):
    ctx = contexts["real"]
    for b in range(ctx.valid.shape[0]):
        valid = ctx.valid[b].numpy()
        leaves = scene_clusters(ctx.pose[b, :, :2].numpy(), valid, C.MAP_KNN_CLUSTER_SIZE)
        ids = sorted(i for leaf in leaves for i in leaf.tolist())
        assert ids == sorted(valid.nonzero()[0].tolist())
        assert all(len(leaf) <= C.MAP_KNN_CLUSTER_SIZE for leaf in leaves)
    members, center, radius = ctx.clusters.members, ctx.clusters.center, ctx.clusters.radius
    m = ctx.pose.shape[1]
    real = members < m
    xy = (
        _piece_xy(ctx)
        .gather(1, members.flatten(1)[..., None].expand(-1, -1, 2))
        .view(*members.shape, 2)
    )
    assert torch.equal(xy, ctx.clusters.member_xy)
    gap = torch.linalg.vector_norm(xy - center[:, :, None], dim=-1)
    assert (gap[real] <= radius[:, :, None].expand_as(gap)[real]).all()


@pytest.fixture(scope="module")
def token_batches(womd_dir):
    """The real samples as TrafficBots token batches: each scene alone and both together,
    trimmed to the same rows."""
    from policies.trafficbots import TokenBatch
    from tbsim_env.data.preprocess import preprocess_scenario

    wod = womd_dir / "waymo-open-dataset"
    scenes = [
        *load_scenarios(wod / "motion_data_one_scenario.tfrecord"),
        *load_scenarios(wod / "womd_scenario_input.tfrecord"),
    ]
    tokens = [preprocess_scenario(s) for s in scenes]
    rows = TokenBatch.from_tokens(tokens).rows_used()
    both = TokenBatch.from_tokens(tokens).trim(rows)
    return both, [TokenBatch.from_tokens([t]).trim(rows) for t in tokens]


def test_trafficbots_map_neighbours_from_clusters_equal_every_piece(token_batches):
    """TrafficBots' agents find the same map neighbours (rows, mask, relative poses) through
    the clusters of its scene encoding as over every piece; single scenes' clusters join into
    the batch's (fixed shapes)."""
    from policies.trafficbots import TrafficBots, TrafficBotsConfig
    from policies.trafficbots.knn import knn_relative
    from tbsim_env.rows import cat_rows

    both, singles = token_batches
    model = TrafficBots(TrafficBotsConfig.small()).eval()
    with torch.no_grad():
        enc = model.encode_scene(both)
        joined = cat_rows([model.encode_scene(b) for b in singles])
    clusters = enc.map_clusters
    assert clusters is not None and clusters.num_clusters > C.MAP_KNN_CLUSTERS
    for a, b in zip(
        (clusters.members, clusters.center, clusters.radius),
        (joined.map_clusters.members, joined.map_clusters.center, joined.map_clusters.radius),
        strict=True,
    ):
        assert torch.equal(a, b)
    # Queries: every agent's poses over its history, and points around the map.
    gen = torch.Generator().manual_seed(3)
    mp = enc.mp
    near = mp.pose[:, torch.randint(mp.pose.shape[1], (200,), generator=gen)].clone()
    near[..., :2] += (torch.rand(near.shape[:2] + (2,), generator=gen) - 0.5) * 80.0
    hist = both.ag_pose.flatten(1, 2)
    query = torch.cat([hist, near], 1)  # [B, Q, 3]
    cfg = model.cfg
    args = (query, mp.pose, mp.valid, cfg.ag_map_knn, cfg.ag_map_dist)
    got, want = knn_relative(*args, clusters), knn_relative(*args)
    for g, w in zip(got, want, strict=True):
        assert torch.equal(g, w)
    assert got[1].float().mean() > 0.9  # most neighbours lie within range
