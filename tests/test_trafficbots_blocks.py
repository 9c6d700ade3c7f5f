"""TrafficBots building blocks: encodings, KNN, KNARPE attention, PointNet, collision check."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

import tbsim_env  # noqa: F401  (first: avoids the policies <-> tbsim_env.env import cycle)

# isort: split

from policies.trafficbots.attention import KnarpeAttention, SelfAttentionLayer, knarpe_reference
from policies.trafficbots.collision import collision_flags, rounded_box_collision
from policies.trafficbots.config import TrafficBotsConfig
from policies.trafficbots.encodings import (
    angle_pe,
    map_node_geometry,
    pose_encoding,
    relative_pose,
    rpe,
    sinusoid_pe,
)
from policies.trafficbots.knn import knn_relative, knn_select
from policies.trafficbots.pointnet import PointNet, pointnet_reference
from tbsim_env.core.constants import KNN_DISTANCE_RESOLUTION


def test_sinusoid_and_angle_encoding_layout() -> None:
    u = torch.tensor([0.0, 2.5])
    pe = sinusoid_pe(u, 32, 1000.0)
    assert pe.shape == (2, 32)
    assert torch.allclose(pe[0, :16], torch.ones(16)) and torch.allclose(
        pe[0, 16:], torch.zeros(16)
    )
    w3 = 1000.0 ** (-2 * 3 / 32)
    assert pe[1, 3].item() == pytest.approx(math.cos(w3 * 2.5), abs=1e-6)
    assert pe[1, 16 + 3].item() == pytest.approx(math.sin(w3 * 2.5), abs=1e-6)
    a = angle_pe(torch.tensor([0.3]), 64)
    assert a[0, 4].item() == pytest.approx(math.cos(5 * 0.3), abs=1e-6)
    assert a[0, 32 + 4].item() == pytest.approx(math.sin(5 * 0.3), abs=1e-6)
    # Periodic in the angle: no wrapping needed.
    p1 = pose_encoding(torch.tensor([1.0, -2.0, 0.4]), 16, 32, 1000.0)
    p2 = pose_encoding(torch.tensor([1.0, -2.0, 0.4 + 2 * math.pi]), 16, 32, 1000.0)
    assert p1.shape == (64,) and torch.allclose(p1, p2, atol=1e-5)
    cfg = TrafficBotsConfig.paper()
    assert rpe(torch.zeros(3), cfg).shape == (128,)


def test_relative_pose_and_map_node_geometry() -> None:
    rel = relative_pose(torch.tensor([1.0, 1.0, math.pi / 2]), torch.tensor([1.0, 3.0, 0.0]))
    assert torch.allclose(rel, torch.tensor([2.0, 0.0, -math.pi / 2]), atol=1e-6)
    # Node at (0, 2) pointing along +x: closest point (0, 2), r = 2, far end |(1,2)-(0,2)| = 1.
    g = map_node_geometry(torch.tensor([0.0, 2.0, 0.0]))
    assert torch.allclose(g, torch.tensor([2.0, 0.0, 1.0, 1.0, 0.0, 1.0, 1.0]), atol=1e-6)
    # Node at (-0.5, 1) along +x: closest point (0, 1) in the middle of the segment.
    g = map_node_geometry(torch.tensor([-0.5, 1.0, 0.0]))
    assert g[0].item() == pytest.approx(1.0) and g[6].item() == pytest.approx(0.5)


def test_knn_ranks_valid_targets_includes_self_and_limits_range() -> None:
    xy = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [3.0, 0.0], [0.5, 0.0], [100.0, 0.0]]])
    valid = torch.tensor([[True, True, True, False, True]])
    idx, mask = knn_select(xy, xy, valid, k=4, dist_limit=50.0)
    assert idx[0, 0].tolist() == [0, 1, 2, 4]  # self first, invalid target 3 skipped
    assert mask[0, 0].tolist() == [True, True, True, False]  # 100 m > limit
    _, at_limit = knn_select(xy, xy, valid, k=4, dist_limit=100.0)
    assert at_limit[0, 0].tolist() == [True] * 4  # a target exactly at the limit counts
    idx2, _ = knn_select(xy, xy, valid, k=99, dist_limit=50.0)
    assert idx2.shape[-1] == 5  # capped at the number of targets
    pose = torch.cat([xy, torch.zeros(1, 5, 1)], -1)
    _, _, rel = knn_relative(pose, pose, valid, 2, 50.0)
    assert torch.allclose(rel[0, 2, 1], torch.tensor([-2.0, 0.0, 0.0]))


def test_knn_breaks_distance_ties_by_the_lower_row_whatever_follows() -> None:
    # Pieces that start at the same node are equally far from everything. 300 targets on a
    # circle around the query, shuffled into 3 groups of 100 at exactly the same points.
    gen = torch.Generator().manual_seed(0)
    angle = torch.rand(100, generator=gen) * 6.283
    ring = torch.stack([angle.cos(), angle.sin()], -1) * 10.0
    xy = ring[torch.randperm(100, generator=gen).repeat(3)][None]  # [1, 300, 2]
    query = torch.zeros(1, 1, 2)
    idx, mask = knn_select(query, xy, torch.ones(1, 300, dtype=torch.bool), k=40, dist_limit=50.0)
    picked = xy[0, idx[0, 0]]
    dist = picked.norm(dim=-1)  # ranked at KNN_DISTANCE_RESOLUTION
    assert (dist[1:] >= dist[:-1] - KNN_DISTANCE_RESOLUTION).all() and mask.all()
    # Among equal distances the lower rows win: every pick precedes its unpicked twins.
    chosen = set(idx[0, 0].tolist())
    for row in chosen:
        twins = [r for r in range(300) if torch.equal(xy[0, r], xy[0, row])]
        assert all(r in chosen for r in twins if r < row)
    # Padding rows after the targets (and their count) change nothing.
    pad = torch.cat([xy, torch.zeros(1, 77, 2)], 1)
    pad_valid = torch.arange(377)[None] < 300
    idx_pad, _ = knn_select(query, pad, pad_valid, k=40, dist_limit=50.0)
    assert torch.equal(idx_pad, idx)


def test_knn_ranks_at_the_distance_resolution_so_the_frame_does_not_matter() -> None:
    # A symmetric map: targets in mirrored pairs about the x-axis, the query on the axis, so
    # every pair is equally far (exactly, and in this frame also in float32). K = 5 splits a
    # pair. In a rotated and shifted frame the float32 distances of a pair differ by rounding.
    x = torch.tensor([3.0, 7.5, 12.25, 20.0])
    left = torch.stack([x, torch.full_like(x, 1.75)], -1)
    right = torch.stack([x, torch.full_like(x, -1.75)], -1)
    xy = torch.cat([right, left])[None]  # [1, 8, 2]: rows 0-3 right, 4-7 left
    query = torch.tensor([[[0.5, 0.0]]])
    valid = torch.ones(1, 8, dtype=torch.bool)
    idx, _ = knn_select(query, xy, valid, k=5, dist_limit=50.0)
    assert sorted(idx[0, 0].tolist()) == [0, 1, 2, 4, 5]  # the tie at 12.25 m: lower row
    yaw, shift = 1.1, torch.tensor([3000.0, -1500.0])
    rot = torch.tensor([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    for k in (1, 3, 5, 7):
        ref, _ = knn_select(query, xy, valid, k=k, dist_limit=50.0)
        for origin in (torch.zeros(2), shift):
            moved, _ = knn_select(
                query @ rot.T + origin, xy @ rot.T + origin, valid, k=k, dist_limit=50.0
            )
            assert sorted(moved[0, 0].tolist()) == sorted(ref[0, 0].tolist()), (k, origin)
    # Distances farther apart than the resolution still rank by distance.
    near = torch.tensor([[[0.0, 0.0], [1.0, 0.0], [0.98, 0.0]]])
    idx, _ = knn_select(torch.zeros(1, 1, 2), near, torch.ones(1, 3, dtype=torch.bool), 3, 9.0)
    assert idx[0, 0].tolist() == [0, 2, 1]


def _dense_reference(attn: KnarpeAttention, x, pose, valid, cfg) -> torch.Tensor:
    """Plain dense multi-head attention of every token over all valid tokens, with RPE."""
    n_sc, n, d = x.shape
    h, c = attn.n_heads, attn.head_dim
    w_q, w_k, w_v = attn.in_proj_weight.chunk(3)
    b_q, b_k, b_v = attn.in_proj_bias.chunk(3)
    out = torch.zeros_like(x)
    for b in range(n_sc):
        for i in range(n):
            q = (x[b, i] @ w_q.T + b_q).view(h, c)
            rel = relative_pose(pose[b, i][None], pose[b])  # [n, 3]
            r = attn.rpe_proj(rpe(rel, cfg))
            k = (x[b] @ w_k.T + b_k + r[:, :d]).view(n, h, c)
            v = (x[b] @ w_v.T + b_v + r[:, d:]).view(n, h, c)
            logits = torch.einsum("hc,nhc->hn", q, k) / math.sqrt(c)
            logits[:, ~valid[b]] = float("-inf")
            p = torch.softmax(logits, dim=-1)
            o = torch.einsum("hn,nhc->hc", p, v).reshape(d)
            out[b, i] = o @ attn.out_proj.weight.T + attn.out_proj.bias
    return out


def test_knarpe_equals_dense_attention_when_k_covers_all_tokens() -> None:
    torch.manual_seed(0)
    cfg = TrafficBotsConfig.small()
    d = cfg.hidden_dim
    attn = KnarpeAttention(d, cfg.n_heads, cfg.rpe_dim, dropout=0.1).eval()
    n_sc, n = 2, 7
    x = torch.randn(n_sc, n, d)
    pose = torch.cat([torch.randn(n_sc, n, 2) * 20, torch.randn(n_sc, n, 1) * 3], -1)
    valid = torch.rand(n_sc, n) > 0.3
    valid[:, 0] = True
    idx, mask, rel = knn_relative(pose, pose, valid, k=n, dist_limit=1e9)
    ref = _dense_reference(attn, x, pose, valid, cfg).detach()
    for dense in (True, False):
        with torch.no_grad():
            got = attn(x, x, idx, rpe(rel, cfg), mask, dense=dense)
            # A query whose neighbours are all invalid outputs zeros.
            none = attn(x, x, idx, rpe(rel, cfg), torch.zeros_like(mask), dense=dense)
        assert torch.allclose(got, ref, atol=1e-5)
        assert torch.count_nonzero(none) == 0


def _attention_case(seed: int, n_src: int, k: int):
    """Random cross-attention inputs: 3 scenes, 9 queries, k neighbours among n_src rows,
    some masked, and one query with none."""
    gen = torch.Generator().manual_seed(seed)
    cfg = TrafficBotsConfig.small()
    x = torch.randn(3, 9, cfg.hidden_dim, generator=gen)
    src = torch.randn(3, n_src, cfg.hidden_dim, generator=gen)
    idx = torch.randint(0, n_src, (3, 9, k), generator=gen)
    r = torch.randn(3, 9, k, cfg.rpe_dim, generator=gen)
    mask = torch.rand(3, 9, k, generator=gen) > 0.3
    mask[1, 4] = False
    return cfg, x, src, idx, r, mask


@pytest.mark.parametrize("chunked", [False, True])
@pytest.mark.parametrize("dense", [True, False, None])
@pytest.mark.parametrize("n_src", [5, 300])
def test_factored_knarpe_matches_the_spec_formula_with_gradients(
    dense, n_src: int, chunked: bool, monkeypatch
) -> None:
    """The factored attention (both ways of reaching the neighbours, whole or in chunks of
    the batch as on a CPU) is the spec's gather-then-project formula: outputs and the
    gradients of inputs and parameters."""
    from tbsim_env.core import constants

    if chunked:  # one scene per chunk (the default budget does not chunk these sizes)
        monkeypatch.setattr(constants, "CPU_ATTENTION_CHUNK_ELEMENTS", 1)
    cfg, x, src, idx, r, mask = _attention_case(3, n_src, k=6)
    torch.manual_seed(0)
    attn = KnarpeAttention(cfg.hidden_dim, cfg.n_heads, cfg.rpe_dim, dropout=0.1).eval()
    with torch.no_grad():  # non-zero biases, so that every bias term is checked
        attn.in_proj_bias.normal_()
        attn.out_proj.bias.normal_()
    outs, grads = [], []
    for fn in (lambda *a: attn(*a, dense=dense), lambda *a: knarpe_reference(attn, *a)):
        xs = [t.clone().requires_grad_() for t in (x, src, r)]
        attn.zero_grad()
        y = fn(xs[0], xs[1], idx, xs[2], mask)
        (y * torch.linspace(-1, 1, y.numel()).view_as(y)).sum().backward()
        outs.append(y.detach())
        grads.append([t.grad for t in xs] + [p.grad.clone() for p in attn.parameters()])
    assert torch.allclose(outs[0], outs[1], atol=1e-5)
    assert torch.count_nonzero(outs[0][1, 4]) == 0
    for g, g_ref in zip(*grads):
        assert torch.allclose(g, g_ref, atol=1e-4), (g - g_ref).abs().max()


class _FixedDropout(torch.nn.Module):
    """Dropout with a given keep mask [B, Q, K, h] (scaled by 1 / keep rate), applied in either
    layout of the attention weights: [..., K, h] or [..., h, K]."""

    def __init__(self, keep: torch.Tensor, rate: float) -> None:
        super().__init__()
        self.scale = keep / (1.0 - rate)

    def forward(self, a: torch.Tensor) -> torch.Tensor:
        same = a.shape[-2:] == self.scale.shape[-2:]
        return a * (self.scale if same else self.scale.transpose(-1, -2))


def test_factored_knarpe_dropout_keeps_the_value_bias_exact() -> None:
    """With dropout on the attention weights they no longer sum to 1: the value biases must
    be scaled by their sum, as gathering biased value rows does. Same dropped weights in the
    factored attention (both ways) and in the spec's formula, same result."""
    cfg, x, src, idx, r, mask = _attention_case(4, 40, k=7)
    attn = KnarpeAttention(cfg.hidden_dim, cfg.n_heads, cfg.rpe_dim, dropout=0.5)
    with torch.no_grad():
        attn.in_proj_bias.normal_()
        attn.rpe_proj.bias.normal_(std=3.0)
    gen = torch.Generator().manual_seed(6)
    keep = (torch.rand(*mask.shape, cfg.n_heads, generator=gen) > 0.5).float()
    attn.dropout = _FixedDropout(keep, 0.5)
    with torch.no_grad():
        ref = knarpe_reference(attn, x, src, idx, r, mask)
        for dense in (True, False):
            assert torch.allclose(attn(x, src, idx, r, mask, dense=dense), ref, atol=1e-5)
        attn.dropout = torch.nn.Identity()
        assert not torch.allclose(attn(x, src, idx, r, mask), ref, atol=1e-3)  # it did act


def test_self_layer_zeroes_invalid_tokens_and_ignores_their_features() -> None:
    torch.manual_seed(1)
    cfg = TrafficBotsConfig.small()
    layer = SelfAttentionLayer(cfg.hidden_dim, cfg.n_heads, 128, cfg.rpe_dim, 0.1).eval()
    x = torch.randn(1, 6, cfg.hidden_dim)
    pose = torch.randn(1, 6, 3)
    valid = torch.tensor([[True, True, False, True, False, True]])
    idx, mask, rel = knn_relative(pose, pose, valid, 6, 1e9)
    with torch.no_grad():
        y1 = layer(x, valid, idx, mask, rpe(rel, cfg))
        x2 = x.clone()
        x2[0, 2] += 5.0
        y2 = layer(x2, valid, idx, mask, rpe(rel, cfg))
    assert torch.count_nonzero(y1[0, ~valid[0]]) == 0
    assert torch.allclose(y1, y2)


def test_pointnet_masks_invalid_nodes() -> None:
    torch.manual_seed(2)
    net = PointNet(32, 3, dropout=0.1).eval()
    x = torch.randn(2, 5, 32)
    valid = torch.tensor([[True, False, True, True, False], [False] * 5])
    with torch.no_grad():
        y1 = net(x, valid)
        x2 = x.clone()
        x2[0, 1] = 100.0
        y2 = net(x2, valid)
    assert y1.shape == (2, 32)
    assert torch.allclose(y1, y2)
    assert torch.count_nonzero(y1[1]) == 0


def test_factored_pointnet_is_the_spec_order_pointnet() -> None:
    """``PointNet`` (factored: per-token pooled term, no zeroing, no concatenation) computes
    the spec's steps (``pointnet_reference``): outputs, gradients, and dropout draws."""
    torch.manual_seed(3)
    net = PointNet(64, 3, dropout=0.1)
    x = torch.randn(4, 7, 11, 64)
    valid = torch.rand(4, 7, 11) > 0.4
    valid[0, :2] = False  # tokens without a valid node
    valid[1, 3] = False
    valid[1, 3, 5] = True  # a single valid node
    x[~valid] = 50.0 * torch.randn_like(x[~valid])  # invalid nodes must not matter
    for train in (False, True):
        net.train(train)
        outs, grads = [], []
        for fn in (net.forward, lambda a, b: pointnet_reference(net, a, b)):
            torch.manual_seed(9)
            net.zero_grad()
            y = fn(x, valid)
            (y * torch.linspace(-1, 1, 64)).sum().backward()
            outs.append(y)
            grads.append(torch.cat([p.grad.flatten() for p in net.parameters()]))
        torch.testing.assert_close(outs[0], outs[1], rtol=1e-5, atol=1e-5)
        torch.testing.assert_close(grads[0], grads[1], rtol=1e-4, atol=1e-4)
        assert torch.count_nonzero(outs[0][0, :2]) == 0 and grads[0].abs().sum() > 0
        assert (outs[0][..., :32] == outs[0][..., 32:]).all()


def test_rounded_box_collision_cases() -> None:
    size = torch.tensor([4.0, 2.0])
    origin = torch.zeros(3)
    scaled = 4.0 * 1.1, 2.0 * 1.1

    def hit(x: float, y: float, yaw: float = 0.0) -> bool:
        return bool(rounded_box_collision(origin, size, torch.tensor([x, y, yaw]), size))

    assert hit(0.0, 0.0)
    assert hit(scaled[0] - 0.05, 0.0)  # bumper overlap
    assert not hit(scaled[0] + 0.05, 0.0)
    assert hit(0.0, scaled[1] - 0.05) and not hit(0.0, scaled[1] + 0.05)
    # Sharp corners would overlap diagonally, the rounded corners do not.
    assert not hit(scaled[0] - 0.1, scaled[1] - 0.1)
    assert hit(1.0, 1.0, 0.7)


def test_rounded_box_collision_matches_shapely() -> None:
    shapely = pytest.importorskip("shapely")
    from shapely.geometry import Polygon

    from tbsim_env.core.boxes import box_corners

    gen = torch.Generator().manual_seed(3)
    n = 300
    pose_a = torch.cat([torch.zeros(n, 2), torch.rand(n, 1, generator=gen) * 6.3], -1)
    pose_b = torch.cat(
        [torch.rand(n, 2, generator=gen) * 12 - 6, torch.rand(n, 1, generator=gen) * 6.3], -1
    )
    size_a = torch.rand(n, 2, generator=gen) * 4 + 0.5
    size_b = torch.rand(n, 2, generator=gen) * 4 + 0.5
    got = rounded_box_collision(pose_a, size_a, pose_b, size_b)

    def shape(pose, size):
        lw = size * 1.1
        s = 0.7 * lw.min() / 2
        corners = box_corners(pose, lw[0] - 2 * s, lw[1] - 2 * s)  # the inner box
        return Polygon(corners.tolist()).buffer(float(s), quad_segs=64)

    ref = [shape(pose_a[i], size_a[i]).intersects(shape(pose_b[i], size_b[i])) for i in range(n)]
    agree = (got == torch.tensor(ref)).float().mean().item()
    assert shapely is not None and agree > 0.99, agree
    assert 0 < sum(ref) < n


def test_collision_flags_broad_phase_is_exact() -> None:
    """The broad-phase ``collision_flags`` equals the exact test on every pair and step."""
    gen = torch.Generator().manual_seed(5)
    n_b, n_ag, n_t = 3, 14, 23
    # Agents crowded into 30 m x 30 m so that many pairs come near and some collide.
    xy = torch.rand(n_b, n_ag, 1, 2, generator=gen) * 30
    xy = xy + torch.cumsum(torch.randn(n_b, n_ag, n_t, 2, generator=gen) * 0.6, 2)
    yaw = torch.rand(n_b, n_ag, n_t, 1, generator=gen) * 6.3
    pose = torch.cat([xy, yaw], -1)
    valid = torch.rand(n_b, n_ag, n_t, generator=gen) > 0.2
    size = torch.rand(n_b, n_ag, 3, generator=gen) * torch.tensor([5.0, 2.0, 1.0]) + 0.5
    start = 4
    want = torch.zeros(n_b, n_ag, dtype=torch.bool)
    for t in range(start, n_t):  # every pair, every step
        p, v, lw = pose[:, :, t], valid[:, :, t], size[..., :2]
        hit = rounded_box_collision(p[:, :, None], lw[:, :, None], p[:, None], lw[:, None])
        hit = hit & v[:, :, None] & v[:, None] & ~torch.eye(n_ag, dtype=torch.bool)
        want |= hit.any(-1)
    got = collision_flags(pose, valid, size, start, steps_per_chunk=5)
    assert 0 < int(want.sum()) < want.numel()
    assert torch.equal(got, want)


def _tl_case(seed: int):
    """A small TL encoder and a batch of 4 scenes, two of them without a valid TL token."""
    from policies.trafficbots.map_encoder import MapTokens
    from policies.trafficbots.tl_encoder import TLEncoder, tl_context
    from tbsim_env.core.constants import NUM_TL_STATES

    cfg = TrafficBotsConfig.small()
    gen = torch.Generator().manual_seed(seed)
    n_b, n_map, n_tl, d = 4, 30, 6, cfg.hidden_dim
    pose = torch.cat([torch.rand(n_b, n_map, 2, generator=gen) * 80, torch.rand(n_b, n_map, 1)], -1)
    mp = MapTokens(
        feat=torch.randn(n_b, n_map, d, generator=gen),
        pose=pose,
        valid=torch.ones(n_b, n_map, dtype=torch.bool),
        node_pose=pose[:, :, None].expand(-1, -1, 2, -1),
        node_valid=torch.ones(n_b, n_map, 2, dtype=torch.bool),
        cls=torch.zeros(n_b, n_map, dtype=torch.long),
    )
    piece = torch.randint(0, n_map, (n_b, n_tl), generator=gen)
    tl_valid = torch.rand(n_b, n_tl, generator=gen) < 0.7
    tl_valid[1] = False
    tl_valid[3] = False
    ctx = tl_context(cfg, piece, tl_valid, mp)
    enc = TLEncoder(cfg, cfg.n_history).eval()
    state = torch.randint(0, NUM_TL_STATES, (n_b, n_tl, cfg.n_history), generator=gen)
    step_valid = torch.rand(n_b, n_tl, cfg.n_history, generator=gen) < 0.9
    return enc, state, step_valid, ctx, mp.feat


def _tl_reference(enc, state, step_valid, ctx, map_feat) -> torch.Tensor:
    """The TL encoder as docs/model.md §3.2 writes it: the MLP on every step's one-hot inputs,
    PointNet over the window, decoder layers, on every scene."""
    import torch.nn.functional as F

    from policies.trafficbots.attention import Neighbours
    from tbsim_env.core.constants import NUM_TL_STATES

    one_hot = F.one_hot(state, NUM_TL_STATES).float()
    time_1h = torch.eye(enc.n_time).expand(*state.shape, -1)
    x = enc.input_mlp(torch.cat([one_hot, time_1h], -1)) + ctx.lane_feat[:, :, None]
    x = enc.pointnet(x, step_valid & ctx.valid[..., None]) * ctx.valid[..., None]
    own = Neighbours(ctx.self_idx, ctx.self_mask, ctx.self_rpe)
    near = Neighbours(ctx.map_idx, ctx.map_mask, ctx.map_rpe)
    for layer in enc.layers:
        x = layer(x, ctx.valid, own, layer.context_kv(map_feat), near)
    return x


def test_tl_encoder_skips_scenes_without_signals_and_tabulates_its_input() -> None:
    enc, state, step_valid, ctx, map_feat = _tl_case(0)
    kv = enc.map_kv(map_feat)
    with torch.no_grad():
        got = enc(state, step_valid, ctx, kv)
        want = _tl_reference(enc, state, step_valid, ctx, map_feat)
        empty = dataclasses.replace(ctx, valid=torch.zeros_like(ctx.valid))
        none_lit = enc(state, step_valid, empty, kv)
    assert got[1].abs().sum() == 0 and got[3].abs().sum() == 0
    assert got[0].abs().sum() > 0 and got[2].abs().sum() > 0
    torch.testing.assert_close(got, want, rtol=0, atol=1e-5)
    assert none_lit.abs().sum() == 0  # no scene with a signal: zeros
    # Training runs every scene (dropout draws must not depend on which scenes have lights).
    enc.train()
    for m in enc.modules():
        if isinstance(m, torch.nn.Dropout):
            m.p = 0.0
    torch.testing.assert_close(enc(state, step_valid, ctx, kv), want, rtol=0, atol=1e-5)
