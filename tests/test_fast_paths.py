"""The per-step fast paths against straightforward reference versions (bit-identical results).

``observe``, ``collided_with_others``, the cached road-edge distance, ``core.step`` and
``reward_and_termination`` are written to use few tensor operations; each is compared here
with a plain implementation of its definition on real and generated scenes.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from tbsim_env.core import constants as C
from tbsim_env.core.boxes import box_corners
from tbsim_env.core.torch_utils import (
    below_zero,
    gather_rows,
    true_index,
    valid_first,
    valid_order,
    where_into,
)
from tbsim_env.data import load_scenarios
from tbsim_env.data.generator import default_scenarios
from tbsim_env.env import TrafficEnv
from tbsim_env.env.agent_metrics import build_route, step_metrics
from tbsim_env.observation.tokens import observe
from tbsim_env.sim import core
from tbsim_env.sim.build import build_sim_state
from tbsim_env.sim.collision import (
    agent_distances,
    collided,
    collided_with_others,
    near_limits,
    pairwise_overlap,
)
from tbsim_env.sim.edge_grid import build_edge_grid, grid_signed_distance
from tbsim_env.sim.geometry import cos_sin
from tbsim_env.sim.offroad import _signed_and_unsigned, grid_exact_signed_distance
from tbsim_env.sim.state import RoadEdges


@pytest.fixture(scope="module")
def scenes(womd_dir):
    real = load_scenarios(womd_dir / "waymo-open-dataset" / "motion_data_one_scenario.tfrecord")
    return {"real": real[0], "generated": default_scenarios(2)[1]}


# ---------------------------------------------------------------------- references
def _wrap(a):
    return torch.remainder(a + math.pi, 2.0 * math.pi) - math.pi


def _to_local(xy, origin):
    d = xy - origin[..., :2]
    c, s = torch.cos(-origin[..., 2]), torch.sin(-origin[..., 2])
    return torch.stack([c * d[..., 0] - s * d[..., 1], s * d[..., 0] + c * d[..., 1]], -1)


def _relative_pose(query, target):
    dyaw = _wrap(target[..., 2] - query[..., 2])
    return torch.cat([_to_local(target[..., :2], query), dyaw[..., None]], -1)


def _history_features(pose, speed, frame):
    xy = _to_local(pose[..., :2], frame[..., None, :])
    yaw = pose[..., 2] - frame[..., None, 2]
    return torch.cat(
        [xy, torch.cos(yaw)[..., None], torch.sin(yaw)[..., None], speed[..., None]], -1
    )


def _buckets(d: np.ndarray) -> np.ndarray:
    """Rank of distances (float32, >= 0 or inf) in KNN buckets, computed in float32 as the
    code does (inf and anything huge share the last bucket)."""
    scaled = d * np.float32(1.0 / C.KNN_DISTANCE_RESOLUTION) + np.float32(C.KNN_BUCKET_OFFSET)
    return np.minimum(np.floor(scaled), 2.0**30)


def _nearest(dist, valid, k, radius):
    m = dist.shape[-1]
    d = dist.masked_fill(~valid, float("inf"))
    if m < k:
        d = torch.nn.functional.pad(d, (0, k - m), value=float("inf"))
    # k nearest, ties to the lower index: lexicographic order of (1 cm bucket, index).
    dn = _buckets(d.numpy())
    index = np.broadcast_to(np.arange(dn.shape[-1]), dn.shape)
    order = np.lexsort((index, dn), axis=-1)[..., :k]
    idx = torch.from_numpy(order.copy())
    top = torch.gather(d, -1, idx)
    return idx.clamp(max=m - 1), top <= radius


def _reference_observe(state, history, ctx, observers, cfg, static):
    """The observation definition gathered per observer and neighbour, one key at a time."""
    bq = torch.arange(state.batch_size)[:, None]
    bk = bq[..., None]
    me = state.pose[bq, observers]
    attrs = torch.cat([static, state.speed[..., None]], dim=-1)
    ego_valid = history.valid[bq, observers]
    ego = _history_features(history.pose[bq, observers], history.speed[bq, observers], me)
    dist = torch.linalg.vector_norm(state.pose[:, None, :, :2] - me[:, :, None, :2], dim=-1)
    other = state.valid[:, None, :].expand_as(dist).clone()
    other[bq, torch.arange(observers.shape[1]), observers] = False
    a_idx, a_mask = _nearest(dist, other, cfg.num_agents, cfg.agent_radius)
    a_f = a_mask.float()
    nb_pose = state.pose[bk, a_idx]
    nb_valid = history.valid[bk, a_idx] & a_mask[..., None]
    nb = _history_features(history.pose[bk, a_idx], history.speed[bk, a_idx], nb_pose)
    m_dist = torch.linalg.vector_norm(ctx.pose[:, None, :, :2] - me[:, :, None, :2], dim=-1)
    m_idx, m_mask = _nearest(m_dist, ctx.valid[:, None], cfg.num_map, cfg.map_radius)
    m_f = m_mask.float()
    lights, lights_valid = ctx.tl_state.value[ctx.row], ctx.tl_valid.value[ctx.row]
    t_now = state.step.clamp(max=lights.shape[-1] - 1)[:, None]
    tl_state, tl_valid = lights[bq, :, t_now][:, 0], lights_valid[bq, :, t_now][:, 0]
    t_dist = torch.linalg.vector_norm(ctx.tl_pose[:, None, :, :2] - me[:, :, None, :2], dim=-1)
    t_idx, t_mask = _nearest(t_dist, tl_valid[:, None], cfg.num_traffic_lights, 200.0)
    t_f = t_mask.float()
    return {
        "ego_history": ego * ego_valid[..., None],
        "ego_history_mask": ego_valid.float(),
        "ego_attributes": attrs[bq, observers],
        "agents": nb * nb_valid[..., None],
        "agents_history_mask": nb_valid.float(),
        "agents_attributes": attrs[bk, a_idx] * a_f[..., None],
        "agents_pose": _relative_pose(me[:, :, None], nb_pose) * a_f[..., None],
        "agents_mask": a_f,
        "map": ctx.nodes.value[ctx.row][bk, m_idx] * m_f[..., None, None],
        "map_nodes_mask": ctx.nodes_valid.value[ctx.row][bk, m_idx] * m_f[..., None],
        "map_class": torch.eye(C.NUM_MAP_CLASSES)[ctx.map_class[bk, m_idx]] * m_f[..., None],
        "map_pose": _relative_pose(me[:, :, None], ctx.pose[bk, m_idx]) * m_f[..., None],
        "map_mask": m_f,
        "traffic_lights": torch.eye(C.NUM_TL_STATES)[tl_state[bk, t_idx]] * t_f[..., None],
        "traffic_lights_pose": _relative_pose(me[:, :, None], ctx.tl_pose[bk, t_idx])
        * t_f[..., None],
        "traffic_lights_mask": t_f,
    }


def _reference_overlap(pose_a, size_a, pose_b, size_b):
    """Separating axis theorem on the 4 box axes, one axis after the other."""
    xa, ya, yaw_a = (pose_a[..., :, None, i] for i in range(3))
    xb, yb, yaw_b = (pose_b[..., None, :, i] for i in range(3))
    dx, dy = xb - xa, yb - ya
    la, wa = 0.5 * size_a[..., :, None, 0], 0.5 * size_a[..., :, None, 1]
    lb, wb = 0.5 * size_b[..., None, :, 0], 0.5 * size_b[..., None, :, 1]
    cd, sd = torch.cos(yaw_b - yaw_a).abs(), torch.sin(yaw_b - yaw_a).abs()
    ca, sa, cb, sb = torch.cos(yaw_a), torch.sin(yaw_a), torch.cos(yaw_b), torch.sin(yaw_b)
    sep = (dx * ca + dy * sa).abs() > la + lb * cd + wb * sd
    sep = sep | ((-dx * sa + dy * ca).abs() > wa + lb * sd + wb * cd)
    sep = sep | ((dx * cb + dy * sb).abs() > lb + la * cd + wa * sd)
    sep = sep | ((-dx * sb + dy * cb).abs() > wb + la * sd + wa * cd)
    return ~sep


def _reference_core_step(state, action):
    """``core.step`` as its docstring says, with per-field gathers and the plain unicycle."""
    n_t = state.log.num_steps
    nxt = (state.step + 1).clamp(max=n_t - 1)
    idx = nxt.view(-1, 1, 1).expand(state.batch_size, state.num_agents, 1)
    log_valid = state.log.take("valid").gather(2, idx)[..., 0] & state.agents.mask
    log_pose = state.log.take("pose").gather(2, idx[..., None].expand(-1, -1, 1, 3))[:, :, 0]
    log_speed = state.log.take("speed").gather(2, idx)[..., 0]
    fresh = ~(state.log.first_valid <= state.step[:, None])
    moving = state.controlled & state.valid
    limit = torch.tensor([C.MAX_ACCEL, C.MAX_YAW_RATE]).T[state.agents.object_type]
    act = torch.maximum(torch.minimum(action, limit), -limit) * moving[..., None]
    acc, yaw_rate = act[..., 0], act[..., 1]
    v_mid = state.speed + 0.5 * C.DT * acc
    yaw_mid = state.pose[..., 2] + 0.5 * C.DT * yaw_rate
    x = state.pose[..., 0] + C.DT * v_mid * torch.cos(yaw_mid)
    y = state.pose[..., 1] + C.DT * v_mid * torch.sin(yaw_mid)
    yaw = _wrap(state.pose[..., 2] + C.DT * yaw_rate)
    sim_pose, sim_speed = torch.stack([x, y, yaw], -1), state.speed + C.DT * acc
    from_log = (state.controlled & ~state.valid & fresh & log_valid) | (
        ~state.controlled & log_valid & (state.valid | fresh)
    )
    pose = torch.where(
        moving[..., None], sim_pose, torch.where(from_log[..., None], log_pose, state.pose)
    )
    speed = torch.where(moving, sim_speed, torch.where(from_log, log_speed, state.speed))
    return nxt, pose, speed, moving | from_log


# ---------------------------------------------------------------------- tests
_PATH_LIMITS = ("COMPONENT_MERGE_MIN_SLOTS", "COMPONENT_POSES_MIN", "COLUMN_GATHER_MIN")
"""The size limits that choose between a component-wise and a fewer-operation form."""


@pytest.mark.float_sensitive
@pytest.mark.parametrize("paths", ["default", "components", "fewer operations"])
@pytest.mark.parametrize("name", ["real", "generated"])
def test_observe_and_core_step_match_references(scenes, name, paths, monkeypatch):
    # Both forms of every size-chosen path give the references' values, bit for bit.
    if paths != "default":
        for limit in _PATH_LIMITS:
            monkeypatch.setattr(C, limit, 1 if paths == "components" else 2**62)
    env = TrafficEnv([scenes[name]], controlled="all", npc_policy="constant_velocity")
    env.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(30):
        with torch.inference_mode():
            s, history, setup = env.sim_state, env.episode.history, env.episode.setup
            args = (s, history, setup.ctx, setup.query, env.obs_config, setup.static)
            got = observe(*args)
            ref = _reference_observe(*args)
            slots = valid_order(s.valid)
            dist = agent_distances(s.pose[0, setup.query], gather_rows(s.pose, slots))
            shared = observe(*args, (dist, slots))  # distances over the valid slots
            every = observe(*args, (agent_distances(s.pose[0, setup.query], s.pose), None))
            for key in ref:
                assert torch.equal(got[key], ref[key]), key
                assert torch.equal(shared[key], ref[key]), key
                assert torch.equal(every[key], ref[key]), key
            action = torch.from_numpy(rng.uniform(-8, 8, (1, s.num_agents, 2)).astype(np.float32))
            nxt = core.step(s, action)
            step, pose, speed, valid = _reference_core_step(s, action)
            assert torch.equal(nxt.step, step) and torch.equal(nxt.valid, valid)
            assert torch.equal(nxt.pose, pose) and torch.equal(nxt.speed, speed)
        if not env.agents:
            break
        env.step({a: rng.uniform(-3, 3, 2).astype(np.float32) for a in env.agents})


@pytest.mark.parametrize("name", ["real", "generated"])
def test_collided_with_others_matches_collided(scenes, name):
    state = build_sim_state([scenes[name]])
    gen = torch.Generator().manual_seed(1)
    n = state.num_agents
    size = state.agents.size[..., :2]
    hits = 0
    for _ in range(20):
        # Agents squeezed together so that many bounding circles and boxes overlap.
        pose = state.pose * torch.tensor([0.05, 0.05, 1.0])
        pose = pose + torch.randn(pose.shape, generator=gen) * torch.tensor([2.0, 2.0, 1.0])
        valid = torch.rand(1, n, generator=gen) > 0.2
        query = torch.randperm(n, generator=gen)[: min(n, 9)][None]
        ref = collided(pose, size, valid)[0, query[0]][None]
        overlap = _reference_overlap(pose[0, query], size[0, query], pose, size)
        assert torch.equal(pairwise_overlap(pose[0, query], size[0, query], pose, size), overlap)
        near = torch.linalg.vector_norm(
            pose[:, None, :, :2] - pose[0, query][:, :, None, :2], dim=-1
        )
        radius = 0.5 * torch.linalg.vector_norm(size, dim=-1)
        near = (near <= radius[:, None] + radius[0, query][..., None]) & valid[:, None]
        near &= torch.arange(n) != query[..., None]
        assert torch.equal((overlap & near).any(-1) & valid[0, query[0]][None], ref)
        limit = near_limits(query, size[0, query], size)  # the per-episode prefilter limits
        got = collided_with_others(pose[0, query], size[0, query], pose, size, valid, limit)
        assert torch.equal(got & valid[0, query[0]][None], ref)
        # With the query's cos / sin precomputed.
        trig = cos_sin(pose[0, query][..., 2:])
        got = collided_with_others(pose[0, query], size[0, query], pose, size, valid, limit, trig)
        assert torch.equal(got & valid[0, query[0]][None], ref)
        hits += int(ref.sum())
    assert hits > 0


def _with_degenerate_edges(state):
    """The state's road edges plus a polyline with a repeated point (a zero-length segment)."""
    e = state.road_edges
    pts = torch.tensor([[[0.0, -30.0], [20.0, -30.0], [20.0, -30.0], [20.0, -10.0]]])
    k = e.start.shape[1]
    extra = RoadEdges(
        start=pts[:, :-1],
        end=pts[:, 1:],
        valid=torch.ones(1, 3, dtype=torch.bool),
        prev_index=torch.tensor([[k, k, k + 1]]),
        next_index=torch.tensor([[k + 1, k + 2, k + 2]]),
    )
    fields = [f for f in e.__dataclass_fields__ if f != "grid"]
    return RoadEdges(**{f: torch.cat([getattr(e, f), getattr(extra, f)], 1) for f in fields})


@pytest.mark.parametrize("name", ["real", "generated"])
def test_grid_edge_distance_matches_reference(scenes, name):
    state = build_sim_state([scenes[name]])
    edges = _with_degenerate_edges(state)
    gen = torch.Generator().manual_seed(2)
    q = torch.nonzero(state.valid[0])[:, 0][None]
    pose = state.pose[:, q[0]].clone()
    pose[0, 0] = torch.tensor([20.0, -29.0, 0.3])  # near the zero-length segment
    size = state.agents.size[:, q[0], :2]
    segments = [(edges.start[0].double().numpy(), edges.end[0].double().numpy())]
    # A grid listing 16 segments per cell, and one listing 2 (many points then recomputed).
    recomputed = {}
    for count in (16, 2):
        grid = build_edge_grid(segments, count=count)
        with_grid = dataclasses.replace(edges, grid=grid)
        for _ in range(10):
            moved = pose + torch.randn(pose.shape, generator=gen) * torch.tensor([1.0, 1.0, 0.3])
            corners = box_corners(moved, size[..., 0], size[..., 1])  # [1, K, 4, 2]
            points = corners.reshape(1, -1, 2)
            got, unresolved = grid_exact_signed_distance(points, with_grid)
            ref, _ = _signed_and_unsigned(points, edges, None)
            assert torch.equal(got, ref) and not unresolved.any()
            _, stale = grid_signed_distance(points, with_grid, grid)
            recomputed[count] = recomputed.get(count, 0) + int(stale.sum())
    assert recomputed[2] > 2 * recomputed[16]


@pytest.mark.parametrize("name", ["real", "generated"])
def test_step_metrics_over_the_valid_slots_match_every_slot(scenes, name):
    """With enough query agents, distances and collisions are measured over each row's valid
    slots (``valid_first``): the same as over every slot, where the agents are squeezed
    together so that many boxes overlap."""
    state = build_sim_state([scenes[name]])
    gen = torch.Generator().manual_seed(5)
    n = state.num_agents
    hits = 0
    for _ in range(10):
        pose = state.pose * torch.tensor([0.05, 0.05, 1.0])
        pose = pose + torch.randn(pose.shape, generator=gen) * torch.tensor([2.0, 2.0, 1.0])
        valid = torch.rand(1, n, generator=gen) > 0.3
        st = state.replace(pose=pose, valid=valid)
        query = torch.randperm(n, generator=gen)[: C.VALID_FIRST_MIN_QUERIES][None]
        got = step_metrics(st, query, build_route(st, query))
        dist, slots = got.agent_distance
        assert slots is not None and dist.shape[-1] == int(valid.sum())
        assert torch.equal(dist, agent_distances(pose[0, query], pose)[..., slots[0]])
        ref = collided(pose, st.agents.size[..., :2], valid)[0, query[0]][None]
        assert torch.equal(got.collision, ref & valid[0, query[0]][None])
        hits += int(ref.sum())
    assert hits > 0


def test_step_metrics_batch_rows_and_hand_built_routes_agree(scenes):
    """A batch of two (indexed log reads) equals each row alone (the batch-of-one path), and a
    route without the per-episode fields gives the same metrics as one from ``build_route``."""
    from dataclasses import fields, replace

    scs = [scenes["real"], scenes["generated"]]
    state = build_sim_state(scs)
    gen = torch.Generator().manual_seed(4)
    query = torch.stack([torch.randperm(int(m.sum()), generator=gen)[:3] for m in state.valid])
    route = build_route(state, query)
    rows = [build_sim_state([sc]) for sc in scs]
    for step in range(12):
        pose = state.pose + torch.randn(state.pose.shape, generator=gen) * 0.3
        st = state.replace(pose=pose, step=state.step + step)
        got = step_metrics(st, query, route)
        # core.step's indexed log reads (B > 1) against the reference.
        controlled = torch.rand(st.valid.shape, generator=gen) > 0.5
        cs = st.replace(controlled=controlled, valid=st.valid & (torch.rand(2, 1) > 0.3))
        action = torch.randn(*pose.shape[:2], 2, generator=gen) * 4
        nxt = core.step(cs, action)
        ref_step, ref_pose, ref_speed, ref_valid = _reference_core_step(cs, action)
        assert torch.equal(nxt.step, ref_step) and torch.equal(nxt.valid, ref_valid)
        assert torch.equal(nxt.pose, ref_pose) and torch.equal(nxt.speed, ref_speed)
        for b, row in enumerate(rows):
            n = row.num_agents
            sub = row.replace(pose=pose[b : b + 1, :n], step=st.step[b : b + 1])
            one = step_metrics(sub, query[b : b + 1], build_route(row, query[b : b + 1]))
            bare = build_route(row, query[b : b + 1])
            bare = replace(bare, **{f.name: None for f in fields(bare)[9:]})
            two = step_metrics(sub, query[b : b + 1], bare)
            for f in fields(got):
                if f.name == "offroad_stale":  # set under torch.compile only
                    assert got.offroad_stale is one.offroad_stale is two.offroad_stale is None
                    continue
                if f.name == "agent_distance":  # 3 queries: to every slot; the batch pads them
                    assert got.agent_distance[1] is None
                    x = got.agent_distance[0][b : b + 1, :, :n]
                    assert torch.equal(x, one.agent_distance[0])
                    assert torch.equal(x, two.agent_distance[0])
                    continue
                x = getattr(got, f.name)[b : b + 1]
                assert torch.equal(x, getattr(one, f.name)), f.name
                assert torch.equal(x, getattr(two, f.name)), f.name


def test_observe_batch_of_two_matches_reference(scenes):
    """The indexed reads of a batch (lights at each row's step) against the reference."""
    from tbsim_env.observation.tokens import (
        ObsConfig,
        agent_static_features,
        build_map_context,
        init_history,
    )

    scs = [scenes["real"], scenes["generated"]]
    state = build_sim_state(scs)
    cfg = ObsConfig()
    ctx = build_map_context(scs, state.origin, cfg)
    static = agent_static_features(state)
    observers = torch.tensor([[0, 1, 2], [2, 1, 0]])
    for shift in ([0, 0], [5, 30], [80, 2]):
        st = state.replace(step=torch.tensor(shift))
        hist = init_history(st, cfg.history)
        got = observe(st, hist, ctx, observers, cfg, static)
        ref = _reference_observe(st, hist, ctx, observers, cfg, static)
        for key in ref:
            assert torch.equal(got[key], ref[key]), key


def test_reset_reuses_the_start_of_a_scenario_without_sharing_outputs(scenes):
    """Resets of a scenario return what a fresh env returns, whatever the caller did with the
    previous episode's arrays and dicts."""
    env = TrafficEnv([scenes["real"]], controlled="tracks_to_predict", npc_policy="log_replay")
    fresh = TrafficEnv([scenes["real"]], controlled="tracks_to_predict", npc_policy="log_replay")
    obs, infos = env.reset(seed=0)
    for o in obs.values():
        for v in o.values():
            v += 1.0
    for info in infos.values():
        info["progress"] = -1.0
    env.step({a: np.ones(2, np.float32) for a in env.agents})
    obs, infos = env.reset()
    ref_obs, ref_infos = fresh.reset(seed=0)
    assert infos == ref_infos and list(obs) == list(ref_obs)
    for a in obs:
        for key in obs[a]:
            np.testing.assert_array_equal(obs[a][key], ref_obs[a][key], key)


@pytest.mark.parametrize("within", [math.inf, 100.0])  # int64 key, int32 key
def test_nearest_breaks_ties_by_index_whatever_the_padding(within: float) -> None:
    """Lane pieces branching from one point are equally far; the pick must not depend on how
    far the distance row is padded (batched envs pad to the largest scene), on the device,
    or on the world frame's rounding (distances within one 1 cm bucket tie)."""
    from tbsim_env.sim.knn import k_nearest as nearest

    gen = torch.Generator().manual_seed(0)
    d = torch.randint(0, 4, (2, 3, 40), generator=gen).float() * 0.7  # many exact ties
    d[0, 0, 5] = float("inf")  # an invalid target
    d[1, 1, 7] += 1e-5  # equal but for rounding: still a tie
    idx, top = nearest(d, None, 16, within)
    lex = np.lexsort((np.broadcast_to(np.arange(40), d.shape), _buckets(d.numpy())), axis=-1)
    lex = lex[..., :16]
    assert torch.equal(idx, torch.from_numpy(lex.copy()))
    padded = torch.nn.functional.pad(d, (0, 300), value=float("inf"))
    idx_p, top_p = nearest(padded, None, 16, within)
    assert torch.equal(idx_p, idx) and torch.equal(top_p, top)


@pytest.mark.parametrize("batch", [1, 3])
def test_gather_rows_is_batched_advanced_indexing(batch):
    from tbsim_env.core.torch_utils import gather_rows

    g = torch.Generator().manual_seed(batch)
    for x in (
        torch.randn(batch, 7, 4, 5, generator=g),  # rows with trailing dims
        torch.randn(batch, 7, generator=g),  # scalar rows
        torch.rand(batch, 7, generator=g) > 0.5,  # bool rows
    ):
        for shape in ((batch, 3), (batch, 2, 6)):
            idx = torch.randint(0, 7, shape, generator=g)
            b = torch.arange(batch).view((batch,) + (1,) * (len(shape) - 1))
            assert torch.equal(gather_rows(x, idx), x[b, idx])


def test_valid_order_lists_each_rows_valid_slots_in_order_then_the_others():
    valid = torch.tensor(
        [[False, True, False, True, True, False], [True, False, False, False, False, True]]
    )
    slots = valid_order(valid)
    assert slots.tolist() == [[1, 3, 4], [0, 5, 1]]  # C = 3; row 1 pads with invalid slots
    assert valid_order(torch.zeros(2, 4, dtype=torch.bool)).shape == (2, 1)  # never empty
    assert valid_order(torch.zeros(0, 4, dtype=torch.bool)).shape == (0, 1)
    assert valid_order(torch.zeros(2, 0, dtype=torch.bool)).shape == (2, 0)
    g = torch.Generator().manual_seed(0)
    for n in (1, 7, 257):  # every row: its valid slots in order, then its others in order
        many = torch.rand(9, n, generator=g) < torch.rand(9, 1, generator=g)
        got = valid_order(many)
        for row, mask in zip(got.tolist(), many.tolist()):
            ranked = [k for k in range(n) if mask[k]] + [k for k in range(n) if not mask[k]]
            assert row == ranked[: len(row)] and len(row) == max(int(many.sum(1).max()), 1)
    # Worth it from VALID_FIRST_MIN_QUERIES query agents per row.
    assert valid_first(valid, C.VALID_FIRST_MIN_QUERIES - 1) is None
    assert torch.equal(valid_first(valid, C.VALID_FIRST_MIN_QUERIES), slots)


def test_true_index_lists_the_flat_positions_of_every_true_entry_in_order():
    """numpy's flatnonzero on the CPU: the flat indices ATen's nonzero gives, int64, for any
    shape, an empty mask or one with no True entry, and a non-contiguous view."""
    g = torch.Generator().manual_seed(0)
    masks = [
        torch.rand(*shape, generator=g) < 0.3 for shape in ((0,), (5, 0, 3), (1,), (64, 57, 153))
    ]
    masks += [torch.zeros(4, 6, dtype=torch.bool), (torch.rand(7, 9, generator=g) < 0.5).t()]
    for mask in masks:
        got = true_index(mask)
        assert got.dtype == torch.int64 and got.shape == (int(mask.sum()),)
        assert torch.equal(got, mask.reshape(-1).nonzero()[:, 0])
    assert true_index(torch.tensor([False, True, True, False, True])).tolist() == [1, 2, 4]


def test_below_zero_is_the_comparison_with_zero():
    """numpy's comparison on the CPU: ATen's ``x < 0`` for float32 and float64, a transposed
    view, signed zeros, infinities and NaN (never below zero), and an empty tensor."""
    g = torch.Generator().manual_seed(0)
    x = torch.randn(64, 57, 153, generator=g)
    x.view(-1)[:5] = torch.tensor([-0.0, 0.0, float("-inf"), float("inf"), float("nan")])
    for t in (x, x.double(), x[0].t(), torch.zeros(0, 3)):
        got = below_zero(t)
        assert got.dtype == torch.bool and torch.equal(got, t < 0)
    assert below_zero(x).view(-1)[:5].tolist() == [False, False, True, False, False]


def test_gather_columns_reads_each_column_of_the_table_rows():
    from tbsim_env.core.torch_utils import gather_columns

    g = torch.Generator().manual_seed(0)
    x = torch.randn(4, 3, 9, generator=g)  # K = 4 table rows, C = 3 columns, E = 9
    rows = torch.tensor([2, 0, 2])
    idx = torch.randint(0, 9, (3, 5, 2), generator=g, dtype=torch.int32)
    cols = gather_columns(x, idx, rows)
    assert len(cols) == 3
    for c, got in enumerate(cols):
        assert got.is_contiguous() and got.shape == idx.shape
        assert torch.equal(got, x[rows.view(3, 1, 1), c, idx.long()])


def test_segment_projection_layouts_agree_bit_for_bit():
    """The vector and the x / y layouts of the point-segment projection are one rule."""
    from tbsim_env.sim.geometry import segment_projection, segment_projection_xy

    g = torch.Generator().manual_seed(0)
    for scale in (1.0, 1e3, 1e5):  # metres up to a 100 km frame
        q = torch.randn(20, 30, 1, 2, generator=g) * scale
        a = torch.randn(20, 30, 16, 2, generator=g) * scale
        ab = torch.randn(20, 30, 16, 2, generator=g) * scale * 1e-2
        ab[:, :, :3] = 0.0  # zero-length segments
        want = segment_projection(q, a, ab)
        got = segment_projection_xy(*q.unbind(-1), *a.unbind(-1), *ab.unbind(-1))
        assert torch.equal(got[0], want[0]) and torch.equal(got[1], want[1])


def test_merge_actions_by_component_is_the_masked_broadcast_where():
    g = torch.Generator().manual_seed(0)
    b, n = 5, 9
    masks = [torch.rand(b, n, generator=g) < 0.5 for _ in range(3)]
    actions = [torch.randn(b, n, 2, generator=g) for _ in range(3)]
    actions[0][0, 0] = float("nan")  # a value outside its mask is never read
    masks[0][0, 0] = masks[1][0, 0] = masks[2][0, 0] = False
    ref = torch.zeros(b, n, 2)
    for mask, action in zip(masks, actions):
        ref = torch.where(mask[..., None], action, ref)
    got = core.merge_actions(*zip(masks, actions))
    assert torch.equal(got, ref)
    assert torch.equal(
        core.merge_actions((masks[1], actions[1])),
        torch.where(masks[1][..., None], actions[1], 0.0),
    )
    expanded = actions[2][:, :1].expand(b, n, 2)  # a view, as one query column's actions
    assert torch.equal(
        core.merge_actions((masks[2], expanded)), torch.where(masks[2][..., None], expanded, 0.0)
    )


def _merge_by_component(mask, a, b):
    out = torch.empty_like(b)
    for k in range(b.shape[-1]):
        where_into(out[..., k], mask, a[..., k], b[..., k])
    return out


def test_where_into_writes_a_component_eagerly_and_in_a_compiled_graph():
    g = torch.Generator().manual_seed(1)
    mask = torch.rand(4, 7, generator=g) < 0.5
    a, b = torch.randn(4, 7, 3, generator=g), torch.randn(4, 7, 3, generator=g)
    ref = torch.where(mask[..., None], a, b)
    assert torch.equal(_merge_by_component(mask, a, b), ref)
    compiled = torch.compile(_merge_by_component, dynamic=False, fullgraph=True)
    assert torch.equal(compiled(mask, a, b), ref)  # no strided out=: a copy in the graph
