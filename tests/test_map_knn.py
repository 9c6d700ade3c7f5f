"""The narrowed nearest-map-piece searches (``tbsim_env.observation.map_knn``: the
observations' grid, TrafficBots' clusters) equal the full search."""

from __future__ import annotations

import math

import pytest
import torch

from tbsim_env.core import constants as C
from tbsim_env.data import load_scenarios
from tbsim_env.data.generator import default_scenarios
from tbsim_env.observation.map_knn import (
    build_piece_clusters,
    build_piece_grid,
    candidate_pieces,
    grid_candidates,
    nearest_pieces,
    scene_clusters,
    search_holds,
)
from tbsim_env.observation.tokens import ObsConfig, build_map_context
from tbsim_env.sim.build import build_sim_state
from tbsim_env.sim.knn import k_nearest


@pytest.fixture(scope="module")
def real_scenes(womd_dir):
    wod = womd_dir / "waymo-open-dataset"
    return [
        *load_scenarios(wod / "motion_data_one_scenario.tfrecord"),
        *load_scenarios(wod / "womd_scenario_input.tfrecord"),
    ]


@pytest.fixture(scope="module")
def contexts(real_scenes):
    out = {}
    for name, scenes in (("real", real_scenes), ("generated", default_scenarios(3))):
        state = build_sim_state(scenes)
        out[name] = build_map_context(scenes, state.origin, ObsConfig())
    return out


def _index(ctx, kind: str):
    """The map context's own grid, or clusters of its pieces (TrafficBots' index)."""
    return ctx.grid if kind == "grid" else build_piece_clusters(ctx.pose[..., :2], ctx.valid)


def _pieces(ctx, index, me, k, within):
    """``nearest_pieces`` over a map context's pieces, as the observations search them."""
    return nearest_pieces(ctx.knn_xy[:, :, : ctx.pose.shape[1]], index, me, k, within)


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


def _full(ctx, me_xy: torch.Tensor, k: int, rows: torch.Tensor | None = None):
    """The plain search over every piece (distances as the observation computes them) of the
    map rows ``rows`` (all by default)."""
    m = ctx.pose.shape[1]
    xy = ctx.knn_xy if rows is None else ctx.knn_xy[rows]
    dx = xy[:, :, :m, 0] - me_xy[..., 0:1]
    dy = xy[:, :, :m, 1] - me_xy[..., 1:2]
    return k_nearest(torch.sqrt(dx * dx + dy * dy), None, k, math.inf)  # the int64 key


def _assert_equal_to_full(ctx, me, got):
    idx, top = got
    ref_idx, ref_top = _full(ctx, me, ObsConfig().num_map)
    assert torch.equal(top, ref_top)
    finite = torch.isfinite(ref_top)
    assert torch.equal(idx[finite], ref_idx[finite])


@pytest.mark.parametrize("kind", ["grid", "clusters"])
@pytest.mark.parametrize("name", ["real", "generated"])
def test_narrowed_search_equals_the_full_search(contexts, name, kind):
    ctx = contexts[name]
    me = _observers(ctx, torch.Generator().manual_seed(0))
    cfg = ObsConfig()
    _assert_equal_to_full(ctx, me, _pieces(ctx, _index(ctx, kind), me, cfg.num_map, cfg.map_radius))


def test_the_grid_search_holds_where_agents_drive_and_not_far_away(contexts, real_scenes):
    """Every logged position of every agent of the real samples is vouched for by its cell's
    list (where those lists hold what the full search finds); points kilometres away are not."""
    ctx, state = contexts["real"], build_sim_state(real_scenes)
    assert ctx.grid.cells.value.shape[-1] < ctx.pose.shape[1], "the real maps use the grid"
    m, cfg = ctx.pose.shape[1], ObsConfig()
    for b in range(ctx.valid.shape[0]):
        me = state.log.take("pose")[b][state.log.take("valid")[b]][None, :, :2]  # [1, P, 2]
        far = me[:, :5] + torch.tensor([1000.0, -3000.0])
        me = torch.cat([far, me], 1)
        rows = torch.tensor([b])
        cand, d, bound = grid_candidates(ctx.grid, me, rows)
        xy = _piece_xy(ctx)[b, cand[0]]
        dx, dy = xy[..., 0] - me[0, :, 0:1], xy[..., 1] - me[0, :, 1:2]
        assert torch.equal(d[0], torch.sqrt(dx * dx + dy * dy))  # the grid's copy of the points
        _, top = k_nearest(d, None, cfg.num_map, cfg.map_radius, ids=(cand, m))
        holds = search_holds(top[..., -1], bound)
        assert holds[:, 5:].all() and not holds[:, :5].any()
        ref_idx, ref_top = _full(ctx, me, cfg.num_map, rows)
        assert torch.equal(top[holds], ref_top[holds])


def test_the_clustered_search_holds_near_the_map_and_not_far_away(contexts):
    ctx = contexts["real"]
    clusters = _index(ctx, "clusters")
    assert clusters.num_clusters > C.MAP_KNN_CLUSTERS, "the real maps use the clustered path"
    gen = torch.Generator().manual_seed(1)
    me = _observers(ctx, gen)
    cand, bound, cand_xy = candidate_pieces(clusters, me, C.MAP_KNN_CLUSTERS)
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


def test_a_grid_of_short_lists_falls_back_to_the_full_search(contexts):
    ctx = contexts["real"]
    grid = build_piece_grid(ctx.pose[..., :2], ctx.valid, cell=20.0, count=66)
    me = _observers(ctx, torch.Generator().manual_seed(2), q=50)
    cand, d, bound = grid_candidates(grid, me)
    _, top = k_nearest(d, None, ObsConfig().num_map, ObsConfig().map_radius, ids=(cand, 1024))
    assert (~search_holds(top[..., -1], bound)).float().mean() > 0.3  # many fall back
    _assert_equal_to_full(ctx, me, _pieces(ctx, grid, me, 64, ObsConfig().map_radius))


def test_a_search_of_too_few_clusters_falls_back_to_the_full_search(contexts, monkeypatch):
    ctx = contexts["real"]
    monkeypatch.setattr(C, "MAP_KNN_CLUSTERS", 2)  # 32 candidates cannot hold 64 nearest
    me = _observers(ctx, torch.Generator().manual_seed(2), q=50)
    _assert_equal_to_full(ctx, me, _pieces(ctx, _index(ctx, "clusters"), me, 64, 200.0))


@pytest.mark.parametrize("kind", ["grid", "clusters"])
def test_a_map_of_fewer_pieces_than_observed_beside_a_large_one(contexts, kind):
    """A row with fewer valid pieces than an observer sees (its lists hold the sentinel) in a
    batch whose other row uses the narrowed search: the full search's pieces, never the
    sentinel index."""
    ctx = contexts["real"]
    valid = ctx.valid.clone()
    valid[1, valid[1].nonzero()[40:, 0]] = False  # row 1 keeps 40 pieces
    xy = ctx.pose[..., :2].masked_fill(~valid[..., None], float("inf"))
    small = type(ctx)(**{**ctx.__dict__, "valid": valid, "knn_xy": xy[:, None]})
    if kind == "grid":
        index = build_piece_grid(ctx.pose[..., :2], valid)
        assert (index.cells.value[1] == ctx.pose.shape[1]).any()  # the sentinel pads row 1
    else:
        index = build_piece_clusters(ctx.pose[..., :2], valid)
    me = _observers(small, torch.Generator().manual_seed(3), q=100)
    idx, top = _pieces(small, index, me, 64, 200.0)
    assert (idx < ctx.pose.shape[1]).all()
    _assert_equal_to_full(small, me, (idx, top))


def test_grid_cells_list_the_pieces_nearest_to_their_centre(contexts):
    ctx = contexts["real"]
    grid, m = ctx.grid, ctx.pose.shape[1]
    xy = _piece_xy(ctx)
    for b in range(ctx.valid.shape[0]):
        n = int(grid.shape[b].prod())
        cells = grid.cells.value[b, :n].long()
        centre = grid.center.value[b, :n]
        d_all = torch.cdist(centre.double(), xy[b, :m].double().nan_to_num(posinf=1e9))
        listed = d_all.gather(1, cells)
        assert (listed.diff(dim=1) >= -1e-3).all()  # nearest first
        unlisted = d_all.scatter(1, cells, math.inf).min(1).values
        assert (listed[:, -1] <= unlisted + 1e-3).all()
        assert (grid.bound.value[b, :n] <= unlisted).all()


def test_clusters_are_compact_and_cover_every_valid_piece(contexts):
    ctx = contexts["real"]
    clusters = _index(ctx, "clusters")
    for b in range(ctx.valid.shape[0]):
        valid = ctx.valid[b].numpy()
        leaves = scene_clusters(ctx.pose[b, :, :2].numpy(), valid, C.MAP_KNN_CLUSTER_SIZE)
        ids = sorted(i for leaf in leaves for i in leaf.tolist())
        assert ids == sorted(valid.nonzero()[0].tolist())
        assert all(len(leaf) <= C.MAP_KNN_CLUSTER_SIZE for leaf in leaves)
    members, center, radius = clusters.members, clusters.center, clusters.radius
    m = ctx.pose.shape[1]
    real = members < m
    xy = (
        _piece_xy(ctx)
        .gather(1, members.flatten(1)[..., None].expand(-1, -1, 2))
        .view(*members.shape, 2)
    )
    assert torch.equal(xy, clusters.member_xy)
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
    from tbsim_env.observation.rows import cat_rows

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
