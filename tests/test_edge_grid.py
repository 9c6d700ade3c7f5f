"""The road-edge grid of the off-road check equals the all-segment computation."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from tbsim_env.sim.edge_grid import build_edge_grid, grid_signed_distance
from tbsim_env.sim.offroad import grid_exact_signed_distance, signed_distance_to_edges
from tbsim_env.sim.state import RoadEdges

pytestmark = [pytest.mark.usefixtures("torch_one_thread"), pytest.mark.float_sensitive]


def _edges(polylines: list[np.ndarray]) -> tuple[RoadEdges, list[tuple[np.ndarray, np.ndarray]]]:
    """One scenario's RoadEdges (open polylines) and its (start, end) arrays."""
    starts, ends, prevs, nexts, off = [], [], [], [], 0
    for pl in polylines:
        n = len(pl) - 1
        local = np.arange(n)
        starts.append(pl[:-1])
        ends.append(pl[1:])
        prevs.append(np.where(local > 0, local - 1, 0) + off)
        nexts.append(np.where(local < n - 1, local + 1, n - 1) + off)
        off += n
    st, en = np.concatenate(starts), np.concatenate(ends)
    edges = RoadEdges(
        start=torch.tensor(st, dtype=torch.float32)[None],
        end=torch.tensor(en, dtype=torch.float32)[None],
        valid=torch.ones(1, len(st), dtype=torch.bool),
        prev_index=torch.tensor(np.concatenate(prevs))[None],
        next_index=torch.tensor(np.concatenate(nexts))[None],
    )
    return edges, [(st, en)]


def _wiggly_roads(seed: int) -> list[np.ndarray]:
    """A few long, curved, finely sampled edges (like WOMD's 0.5 m sampling)."""
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(6):
        s = np.linspace(0.0, 200.0, 400)
        phase, amp = rng.uniform(0, 6), rng.uniform(2, 20)
        base = rng.uniform(-80, 80, 2)
        ang = rng.uniform(0, np.pi)
        x, y = s, amp * np.sin(s / 30.0 + phase)
        c, si = np.cos(ang), np.sin(ang)
        out.append(np.stack([c * x - si * y, si * x + c * y], -1) + base)
    return out


@pytest.mark.parametrize("cell, count", [(4.0, 16), (2.0, 8), (8.0, 4)])
def test_exact_equals_every_segment_and_flags_what_it_cannot_vouch_for(cell, count):
    edges, segs = _edges(_wiggly_roads(0))
    grid = build_edge_grid(segs, cell=cell, count=count, margin=10.0)
    g = torch.Generator().manual_seed(1)
    # Points on the map, near the edges, and far outside the grid.
    pts = torch.cat(
        [
            torch.rand(1, 3000, 2, generator=g) * 400 - 200,
            edges.start[:, :2000] + torch.randn(1, 2000, 2, generator=g),
            torch.randn(1, 200, 2, generator=g) * 2000,
        ],
        1,
    )
    full = signed_distance_to_edges(pts, edges)
    fast, stale = grid_signed_distance(pts, edges, grid)
    ok = ~stale  # few listed segments of 0.5 m pieces vouch for little: only exactness counts
    torch.testing.assert_close(fast[ok], full[ok], rtol=0, atol=0)
    exact, _ = grid_exact_signed_distance(pts, dataclasses.replace(edges, grid=grid))
    torch.testing.assert_close(exact, full, rtol=0, atol=0)
    # Points far outside the grid are mostly beyond what a border cell's list can vouch for.
    assert stale[0, -200:].float().mean() > 0.5


def test_grid_segment_table_is_the_edges_start_and_vector():
    """The grid's column table holds each edge row's start and end - start (what the lookup
    reads instead of gathering both ends), bit for bit."""
    edges, segments = _edges(_wiggly_roads(3))
    grid = build_edge_grid(segments + segments[:1])  # two rows of the same scene
    table = grid.segments.value  # [K, 5, E]
    e = edges.start.shape[1]
    for k in range(2):
        assert torch.equal(table[k, :2, :e].T, edges.start[0])
        assert torch.equal(table[k, 2:4, :e].T, edges.end[0] - edges.start[0])


def test_no_edges_and_fewer_segments_than_candidates():
    one, segs = _edges([np.array([[0.0, 0.0], [10.0, 0.0], [20.0, 5.0]])])
    grid = build_edge_grid(segs, cell=4.0, count=16, margin=5.0)
    pts = torch.tensor([[[5.0, 1.0], [5.0, -1.0], [25.0, 5.0], [500.0, 0.0]]])
    exact, stale = grid_exact_signed_distance(pts, dataclasses.replace(one, grid=grid))
    torch.testing.assert_close(exact, signed_distance_to_edges(pts, one))
    assert not stale.any()  # every segment is listed: nothing to vouch for
    assert exact[0, 0] < 0 < exact[0, 1]  # the road is on the left of the edge
    empty = RoadEdges(
        start=torch.zeros(1, 1, 2),
        end=torch.zeros(1, 1, 2),
        valid=torch.zeros(1, 1, dtype=torch.bool),
        prev_index=torch.zeros(1, 1, dtype=torch.int64),
        next_index=torch.zeros(1, 1, dtype=torch.int64),
    )
    grid = build_edge_grid([(np.zeros((0, 2)), np.zeros((0, 2)))])
    out, stale = grid_exact_signed_distance(pts, dataclasses.replace(empty, grid=grid))
    assert (out == -1.0e10).all() and not stale.any()


def test_points_gathered_from_several_rows_read_their_own_scenes_edges():
    """``rows``: a list of points from several scenes (as the env lists the agents still
    present) gets exactly the distances of the per-scene layout, recomputed points included."""
    from tbsim_env.data.generator import default_scenarios
    from tbsim_env.sim.build import build_sim_state

    edges = build_sim_state(default_scenarios(3)).road_edges
    assert edges.grid is not None
    g = torch.Generator().manual_seed(2)
    e = edges.start.shape[1]
    near = edges.start + torch.randn(3, e, 2, generator=g)
    pts = torch.cat([near, torch.randn(3, 20, 2, generator=g) * 3000], 1)  # far: recomputed
    full, _ = grid_exact_signed_distance(pts, edges)
    b = torch.randint(0, 3, (500,), generator=g)
    k = torch.randint(0, pts.shape[1], (500,), generator=g)
    listed, stale = grid_exact_signed_distance(pts[b, k][:, None], edges, rows=b)
    assert torch.equal(listed[:, 0], full[b, k]) and not stale.any()
    assert (full[:, :e] < 0).any() and (full[:, :e] > 0).any()


@pytest.mark.parametrize("leaf", [1, 4, 8])
@pytest.mark.parametrize("cell, count", [(6.0, 16), (9.0, 96), (50.0, 4)])
def test_each_cell_lists_its_nearest_segments_and_bounds_the_rest(cell, count, leaf, monkeypatch):
    """The tiled build (tiles quartered down to ``leaf`` cells a side) against every (cell,
    segment) distance: each cell lists ``count`` segments at the ``count`` smallest distances
    (ties in any order) and its bound is the next distance (less the slack)."""
    import tbsim_env.sim.edge_grid as eg
    from tbsim_env.sim.edge_grid import _BOUND_SLACK, scene_edge_grid

    monkeypatch.setattr(eg, "_LEAF_CELLS", leaf)

    _, [(st, en)] = _edges(_wiggly_roads(3))
    grid = scene_edge_grid(st, en, cell, count, 15.0)
    q = torch.from_numpy(grid["center"]).double()
    a, b = torch.from_numpy(st), torch.from_numpy(en)
    ab = b - a
    rel = q[:, None] - a[None]
    t = ((rel * ab).sum(-1) / (ab * ab).sum(-1)).clamp(0, 1)
    d = (rel - t[..., None] * ab).norm(dim=-1)  # [G, E], float64
    ordered = d.sort(1).values
    listed = torch.gather(d, 1, torch.from_numpy(grid["cells"])).sort(1).values
    torch.testing.assert_close(listed, ordered[:, :count], rtol=0, atol=1e-4)
    bound = torch.from_numpy(grid["bound"]).double() + _BOUND_SLACK
    torch.testing.assert_close(bound, ordered[:, count], rtol=0, atol=1e-4)


def test_chunked_tiles_give_the_same_grid(monkeypatch):
    """Chunks of one tile each (a tile larger than the work budget included) list what one
    big chunk lists."""
    import tbsim_env.sim.edge_grid as eg

    _, [(st, en)] = _edges(_wiggly_roads(5))
    whole = eg.scene_edge_grid(st, en, 3.0, 16, 15.0)
    monkeypatch.setattr(eg, "_TILE_WORK", 1)
    pieces = eg.scene_edge_grid(st, en, 3.0, 16, 15.0)
    # The same lists and bounds up to ties: consecutive segments are equally far from their
    # joint, and float32 distances that differ by less than their rounding (~1e-5 m at map
    # coordinates) may rank either way with another chunk width on another kernel path.
    np.testing.assert_allclose(pieces["bound"], whole["bound"], rtol=0, atol=1e-4)
    q = torch.from_numpy(whole["center"]).double()
    a, ab = torch.from_numpy(st), torch.from_numpy(en - st)

    def listed(cells: np.ndarray) -> torch.Tensor:
        idx = torch.from_numpy(cells)
        rel = q[:, None] - a[idx]
        t = ((rel * ab[idx]).sum(-1) / (ab[idx] ** 2).sum(-1)).clamp(0, 1)
        return (rel - t[..., None] * ab[idx]).norm(dim=-1).sort(1).values

    torch.testing.assert_close(listed(pieces["cells"]), listed(whole["cells"]), rtol=0, atol=1e-4)


def test_a_grid_asked_for_again_is_kept_and_each_caller_gets_its_own_copy():
    """``scene_edge_grid`` keeps grids by their segments: the same segments give the grid
    computed anew (a caller writing into its copy changes nothing kept); moved segments are
    another grid."""
    import tbsim_env.sim.edge_grid as eg

    _, [(st, en)] = _edges(_wiggly_roads(4))
    first = eg.scene_edge_grid(st, en, 3.0, 16, 15.0)
    first["cells"][:] = -1
    first["bound"][:] = 0.0
    again = eg.scene_edge_grid(st, en, 3.0, 16, 15.0)
    fresh = eg._scene_edge_grid(st, en, 3.0, 16, 15.0)
    assert again.keys() == fresh.keys()
    for key in fresh:
        np.testing.assert_array_equal(again[key], fresh[key], err_msg=key)
    moved = eg.scene_edge_grid(st + 7.0, en + 7.0, 3.0, 16, 15.0)
    np.testing.assert_allclose(moved["lower"], fresh["lower"] + 7.0)
