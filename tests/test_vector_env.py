"""BatchedTrafficEnv: equality with TrafficEnv, batching, autoreset, determinism, bad actions."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tbsim_env.core import constants as C
from tbsim_env.core.config import EnvConfig, TerminationConfig
from tbsim_env.core.errors import ActionError
from tbsim_env.data.generator import default_scenarios
from tbsim_env.env import TrafficEnv
from tbsim_env.env.agent_metrics import Route
from tbsim_env.env.vector_env import (
    OBS_INDEXED_KEYS,
    ROUTE_KEY,
    BatchedTrafficEnv,
    route_features,
)
from tbsim_env.observation.rows import cat_rows, take_rows, with_rows


@pytest.fixture(scope="module")
def scenes():
    return default_scenarios(3)


def _compare_with_trafficenv(scenarios, controlled, npc, seed, episodes, expert=False):
    """Step TrafficEnv (random scenario order) and a B=1 batched env side by side.

    Returns:
        (steps, agents terminated mid-episode: these leave the scene, and what follows must
        still match).
    """
    env = TrafficEnv(scenarios, controlled=controlled, npc_policy=npc, scenario_order="random")
    venv = BatchedTrafficEnv(scenarios, 1, controlled=controlled, npc_policy=npc, seed=seed)
    obs, _ = env.reset(seed=seed)
    vobs, _ = venv.reset(seed=seed)
    rng = np.random.default_rng(seed)
    done_episodes, steps, checked, terminated = 0, 0, 0, 0
    while done_episodes < episodes:
        assert env.scenario.scenario_id == venv.scenarios[int(venv.scenario_index[0])].scenario_id
        names = venv.agent_names[int(venv.scenario_index[0])]
        assert [n for n in names if n in env.agents] == env.agents
        for q, name in enumerate(names):
            if name in env.agents:
                for key in obs[name]:
                    np.testing.assert_array_equal(obs[name][key], vobs[key][0, q].numpy(), key)
                    checked += 1
        if expert:
            a = venv.expert_actions()
            ref = env.expert_actions()
            for q, name in enumerate(names):
                if name in ref:
                    np.testing.assert_allclose(ref[name], a[0, q].numpy(), atol=1e-6)
            a = a.numpy()
        else:
            a = rng.uniform(-3, 3, (1, venv.num_agents, 2)).astype(np.float32)
        acts = {n: a[0, q] for q, n in enumerate(names) if n in env.agents}
        obs, rew, term, trunc, _ = env.step(acts)
        vobs, vrew, vterm, vtrunc, vinfo = venv.step(torch.from_numpy(a))
        for q, name in enumerate(names):
            if name in rew:
                assert rew[name] == pytest.approx(float(vrew[0, q]), abs=1e-6)
                assert term[name] == bool(vterm[0, q]) and trunc[name] == bool(vtrunc[0, q])
                terminated += int(term[name] and len(env.agents) > 0)
                for key in obs[name]:
                    np.testing.assert_array_equal(
                        obs[name][key], vinfo["final_obs"][key][0, q].numpy(), key
                    )
            else:
                assert float(vrew[0, q]) == 0.0 and not bool(vterm[0, q] | vtrunc[0, q])
        steps += 1
        assert bool(vinfo["done"][0]) == (not env.agents)
        if not env.agents:
            done_episodes += 1
            obs, _ = env.reset()
    assert checked > 0
    return steps, terminated


@pytest.mark.parametrize(
    ("controlled", "npc"),
    [("sdc", "constant_velocity"), ("tracks_to_predict", "log_replay")],
)
def test_batch_of_one_equals_trafficenv(scenes, controlled, npc):
    steps, terminated = _compare_with_trafficenv(scenes, controlled, npc, seed=5, episodes=3)
    assert steps >= 3
    if controlled == "tracks_to_predict":
        # Random actions drive some agents into others or off the road; they leave while the
        # rest of the episode goes on (and must still match).
        assert terminated > 0


def test_batch_of_one_equals_trafficenv_full_expert_episode(scenes):
    # Following the expert, episodes run to the goal or the end of the log.
    steps, _ = _compare_with_trafficenv(
        scenes, "sdc", "log_replay", seed=2, episodes=2, expert=True
    )
    assert steps >= 2


def test_batch_of_one_equals_trafficenv_on_real_womd(one_scenario_path):
    from tbsim_env.data import load_scenarios

    real = load_scenarios(one_scenario_path)
    _compare_with_trafficenv(real, "tracks_to_predict", "log_replay", seed=0, episodes=1)


def test_batch_of_one_equals_trafficenv_on_history_only_scenes(womd_dir):
    """WOSAC test-split scenes (11 logged steps) and a full one in one bank: every episode
    runs to step 90 with the NPCs on the policy, as in ``TrafficEnv``."""
    from tbsim_env.data import load_scenarios

    scenes = load_scenarios(womd_dir / "gpudrive_history" / "gpudrive")
    assert sorted(sc.num_logged_steps for sc in scenes) == [11, 11, 91]
    steps, _ = _compare_with_trafficenv(scenes, "sdc", "constant_velocity", seed=1, episodes=4)
    assert steps >= 4
    never = EnvConfig(termination=TerminationConfig(collision=False, offroad=False, goal=False))
    venv = BatchedTrafficEnv(scenes, 3, npc_policy="constant_velocity", seed=0, config=never)
    venv.reset(scenario_indices=[0, 1, 2])
    for _ in range(80):
        obs, rew, term, trunc, info = venv.step(torch.zeros(3, venv.num_agents, 2))
        assert torch.isfinite(rew).all() and all(torch.isfinite(v).all() for v in obs.values())
        assert torch.isfinite(info["log_divergence"]).all()
    assert bool(info["done"].all()) and bool(trunc.all())  # every slot ran to step 90


def test_slots_of_a_batch_match_single_runs(scenes):
    """Padding to the largest scenario and batching do not change any slot's results."""
    ks = [2, 0, 1]
    venv = BatchedTrafficEnv(scenes, 3, controlled="all", npc_policy="constant_velocity", seed=0)
    singles = [
        BatchedTrafficEnv([scenes[k]], 1, controlled="all", npc_policy="constant_velocity")
        for k in ks
    ]
    assert venv.num_agents == max(s.num_agents for s in singles)
    obs, _ = venv.reset(scenario_indices=ks)
    for s in singles:
        s.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(15):
        a = torch.from_numpy(rng.uniform(-1, 1, (3, venv.num_agents, 2)).astype(np.float32))
        obs, rew, term, trunc, info = venv.step(a)
        for b, s in enumerate(singles):
            q = s.num_agents
            so, sr, st, su, si = s.step(a[b : b + 1, :q])
            assert not bool(info["done"][b])
            torch.testing.assert_close(rew[b, :q], sr[0], rtol=0, atol=1e-6)
            assert torch.equal(term[b, :q], st[0]) and torch.equal(trunc[b, :q], su[0])
            assert torch.equal(info["agent_mask"][b, :q], si["agent_mask"][0])
            assert not info["agent_mask"][b, q:].any()
            for key in obs:
                torch.testing.assert_close(obs[key][b, :q], so[key][0], rtol=0, atol=1e-5)
                assert not obs[key][b, q:].any()


@pytest.mark.parametrize("kept", [True, False])
def test_autoreset_restarts_finished_slots(scenes, kept, monkeypatch):
    """Finished slots restart in the same step with the new episode's first observation:
    gathered from the bank's first observations when they are kept, else observed anew
    (``FIRST_OBS_BANK_MAX_BYTES``); both equal a fresh env's."""
    if not kept:
        monkeypatch.setattr(C, "FIRST_OBS_BANK_MAX_BYTES", 0)
    venv = BatchedTrafficEnv(scenes, 2, controlled="sdc", npc_policy="log_replay", seed=1)
    obs, _ = venv.reset()
    # Slot 0 drives into trouble at full throttle, slot 1 follows the log.
    returns = torch.zeros(2)
    draws = []
    restarted = 0
    for _ in range(200):
        a = venv.expert_actions()
        a[0] = torch.tensor([5.0, 1.0])
        before = venv.scenario_index.clone()
        obs, rew, term, trunc, info = venv.step(a)
        returns += rew[:, 0]
        for b in info["done"].nonzero(as_tuple=True)[0].tolist():
            restarted += 1
            assert bool(term[b, 0] | trunc[b, 0])
            assert float(info["episode_return"][b, 0]) == pytest.approx(float(returns[b]), 1e-5)
            returns[b] = 0.0
            draws.append(int(venv.scenario_index[b]))
            assert bool(venv.agent_mask[b, 0]) and bool(info["agent_mask"][b, 0])
            # The returned observation is the fresh start of the new episode.
            fresh = BatchedTrafficEnv(scenes, 1, controlled="sdc", npc_policy="log_replay")
            fobs, _ = fresh.reset(scenario_indices=[int(venv.scenario_index[b])])
            for key in obs:
                torch.testing.assert_close(obs[key][b], fobs[key][0], rtol=0, atol=0)
            # ... and the final one is not (the whole observation: an SDC that stands still,
            # e.g. at a red light, has the same ego history at the end and at the start).
            final = info["final_obs"]
            assert any(not torch.equal(final[key][b], obs[key][b]) for key in obs)
        assert torch.equal(venv.scenario_index[~info["done"]], before[~info["done"]])
    assert restarted >= 3
    assert (venv._first_observations() is not None) == kept
    # Scenarios are drawn from the env's seeded generator, one draw per restart.
    rng = np.random.default_rng(1)
    expected = [int(rng.integers(len(scenes))) for _ in range(2 + len(draws))][2:]
    assert draws == expected


@pytest.mark.parametrize("batch, layout", [(3, "dense"), (1, "indexed"), (3, "indexed")])
def test_restarting_every_slot_reuses_the_batch_memory(scenes, batch, layout):
    """Restarting every slot at once (episodes of one length end in the same step) writes
    the new episodes into the batch's own tables; they go on as in fresh envs, and nothing
    handed out before changes."""
    kw = dict(controlled="sdc", npc_policy="log_replay", obs_layout=layout)
    venv = BatchedTrafficEnv(scenes, batch, seed=2, **kw)
    venv.reset()
    tables = venv.episode.setup.ctx.pose.data_ptr()  # per-row piece poses
    for _ in range(5):
        before, *_ = venv.step(venv.expert_actions())
    kept = {k: v.clone() for k, v in before.items()}
    obs = venv.reset_slots(list(range(batch)))
    assert venv.episode.setup.ctx.pose.data_ptr() == tables
    # The logs and the map tokens are the bank's tables, read through each row's row map:
    # never copied.
    assert venv.sim_state.log.by_step.value is venv.bank.start.log.by_step.value
    assert venv.episode.setup.ctx.tokens.value is venv.bank.setup.ctx.tokens.value
    assert all(torch.equal(before[k], kept[k]) for k in kept)
    fresh = BatchedTrafficEnv(scenes, batch, **kw)
    fobs, _ = fresh.reset(scenario_indices=venv.scenario_index.tolist())
    assert all(torch.equal(obs[k], fobs[k]) for k in obs)
    for _ in range(3):
        a = venv.expert_actions()
        o1, r1, *_ = venv.step(a)
        o2, r2, *_ = fresh.step(a)
        assert torch.equal(r1, r2) and all(torch.equal(o1[k], o2[k]) for k in o1)


def test_determinism_and_seed_dependence(scenes):
    def run(seed):
        venv = BatchedTrafficEnv(
            scenes, 3, controlled="tracks_to_predict", npc_policy="constant_velocity", seed=seed
        )
        obs, _ = venv.reset()
        rng = np.random.default_rng(0)
        trace = []
        for _ in range(100):
            a = torch.from_numpy(rng.uniform(-2, 2, (3, venv.num_agents, 2)).astype(np.float32))
            obs, rew, term, trunc, info = venv.step(a)
            trace.append((obs["agents"].clone(), rew, term, trunc, info["scenario_index"]))
        return trace

    a, b, c = run(3), run(3), run(4)
    for x, y in zip(a, b):
        for u, v in zip(x, y):
            assert torch.equal(u, v)
    assert any(not torch.equal(x[4], y[4]) for x, y in zip(a, c))


def test_bad_actions(scenes):
    venv = BatchedTrafficEnv(scenes, 2, controlled="sdc", seed=0)
    with pytest.raises(RuntimeError):
        venv.step(torch.zeros(2, 1, 2))
    venv.reset()
    with pytest.raises(ActionError, match="shape"):
        venv.step(torch.zeros(2, 2))
    bad = torch.zeros(2, 1, 2)
    bad[1, 0, 0] = float("nan")
    with pytest.raises(ActionError, match="not finite"):
        venv.step(bad)
    bad[1, 0, 0] = float("inf")
    with pytest.raises(ActionError):
        venv.step(bad)
    # NaN is fine where no agent is active (padding slots).
    venv = BatchedTrafficEnv(scenes, 2, controlled="tracks_to_predict", seed=0)
    venv.reset(scenario_indices=[0, 1])
    a = torch.zeros(2, venv.num_agents, 2)
    a[~venv.agent_mask] = float("nan")
    if (~venv.agent_mask).any():
        venv.step(a)
    with pytest.raises(ValueError):
        BatchedTrafficEnv(scenes, 0)


def test_route_features_on_a_straight_route():
    t = 11
    x = torch.linspace(0.0, 50.0, t)
    pts = torch.stack([x, torch.zeros(t)], -1)[None, None]
    arc = x[None, None]
    route = Route(points=pts, arc=arc, goal=pts[..., -1, :], valid=torch.ones(1, 1, dtype=bool))
    pose = torch.tensor([[[10.0, 0.0, np.pi / 2]]])  # facing +y: forward is the route's left
    out = route_features(route, torch.tensor([[10.0]]), pose, num_points=10, spacing=5.0)
    assert out.shape == (1, 1, 10, 2)
    ahead = torch.tensor([5.0, 10, 15, 20, 25, 30, 35, 40, 40, 40])  # clamped at the goal
    torch.testing.assert_close(out[0, 0, :, 0], torch.zeros(10), atol=1e-5, rtol=0)
    torch.testing.assert_close(out[0, 0, :, 1], -ahead, atol=1e-5, rtol=0)


def test_route_observation_key(scenes):
    venv = BatchedTrafficEnv(scenes, 2, route_points=4, seed=0)
    obs, _ = venv.reset()
    assert obs[ROUTE_KEY].shape == (2, 1, 4, 2)
    assert venv.single_observation_space()[ROUTE_KEY].shape == (4, 2)
    # Along a logged route the first point lies roughly ahead.
    assert (obs[ROUTE_KEY][:, 0, 0, 0] > 0).all()


def test_take_and_with_rows_round_trip(scenes):
    venv = BatchedTrafficEnv(scenes, 3, seed=0)
    venv.reset(scenario_indices=[0, 1, 2])
    state = venv.sim_state
    rows = torch.tensor([2, 0])
    sub = take_rows(state, rows)
    assert sub.batch_size == 2 and torch.equal(sub.pose[0], state.pose[2])
    before = state.agents.size.clone()
    copy = with_rows(state, torch.tensor([1]), take_rows(state, torch.tensor([0])))
    assert torch.equal(copy.agents.size[1], state.agents.size[0])
    assert torch.equal(copy.agents.size[2], state.agents.size[2])
    assert torch.equal(state.agents.size, before), "with_rows returns a new tree"
    # Shared tables (the logs) pass through; their row maps are rows like any other.
    assert copy.log.pose is state.log.pose and copy.log.row.tolist() == [0, 0, 2]
    assert torch.equal(copy.log.take("pose")[1], state.log.take("pose")[0])
    with pytest.raises(ValueError, match="cannot take"):
        with_rows(state.pose, torch.tensor([0]), state.pose[:1, :3])
    with pytest.raises(TypeError):
        take_rows(object(), rows)


def test_cat_rows_inverts_taking_rows(scenes):
    venv = BatchedTrafficEnv(scenes, 3, seed=0)
    venv.reset(scenario_indices=[0, 1, 2])
    state = venv.sim_state
    parts = [take_rows(state, torch.tensor([i])) for i in (2, 0, 1)]
    whole = take_rows(state, torch.tensor([2, 0, 1]))
    joined = cat_rows(parts)
    assert type(joined) is type(state) and joined.batch_size == 3
    assert torch.equal(joined.log.take("pose"), whole.log.take("pose"))
    assert torch.equal(joined.pose, whole.pose) and joined.log.pose is state.log.pose
    other = BatchedTrafficEnv(scenes, 1, seed=0)  # another bank's tables
    other.reset()
    with pytest.raises(ValueError, match="share their tables"):
        cat_rows([state, other.sim_state])
    nested = cat_rows([{"a": (torch.ones(1), None)}, {"a": (torch.zeros(2), None)}])
    assert nested["a"][0].tolist() == [1.0, 0.0, 0.0] and nested["a"][1] is None
    with pytest.raises(ValueError, match="at least one"):
        cat_rows([])
    with pytest.raises(TypeError):
        cat_rows([state, state.pose])


def test_with_rows_in_place_writes_owned_tensors_only(scenes):
    """In place, the rows go into tensors that own their storage (the same values as the new
    tree); a view into a larger tensor or an expanded one is copied, never written through."""
    venv = BatchedTrafficEnv(scenes, 3, seed=0)
    venv.reset(scenario_indices=[0, 1, 2])
    state = take_rows(venv.sim_state, torch.arange(3))  # tensors of our own
    rows, fresh = torch.tensor([2, 0]), take_rows(state, torch.tensor([1, 1]))
    expected = with_rows(state, rows, fresh)
    size = state.agents.size
    merged = with_rows(state, rows, fresh, in_place=True)
    assert merged.agents.size is size and torch.equal(size, expected.agents.size)
    assert torch.equal(merged.pose, expected.pose) and torch.equal(merged.valid, expected.valid)
    base = torch.zeros(4, 3)
    for view in (base[1:3], base[:1].expand(2, 3)):
        out = with_rows(view, torch.tensor([0]), torch.ones(1, 3), in_place=True)
        assert out.data_ptr() != view.data_ptr() and out[0].eq(1).all()
    assert not base.any(), "a view was written through"


def test_trimmed_trafficbots_npcs_match_the_padded_ones_across_slot_restarts(scenes):
    """``BatchedTrafficEnv`` runs a trimming TrafficBots policy on the token rows its bank uses
    (``for_scenarios``): fixed state shapes through restarts into differently sized scenes,
    and the padded policy's observations and rewards."""
    from policies.trafficbots.batch import TokenBatch
    from policies.trafficbots.config import TrafficBotsConfig
    from policies.trafficbots.model import TrafficBots
    from policies.trafficbots.policy import TrafficBotsPolicy
    from tbsim_env.data.preprocess import preprocess_scenario

    torch.manual_seed(0)
    model = TrafficBots(TrafficBotsConfig.small())
    used = [TokenBatch.from_tokens(preprocess_scenario(sc)).rows_used() for sc in scenes]
    union = tuple(max(u[i] for u in used) for i in range(3))
    assert len(set(used)) == len(scenes) and union < (64, 1024, 128)

    def run(trim: bool):
        cfg = EnvConfig(termination=TerminationConfig(offroad=True))
        policy = TrafficBotsPolicy(model, trim=trim)
        venv = BatchedTrafficEnv(scenes, 2, npc_policy=policy, config=cfg, seed=4)
        venv.reset(scenario_indices=[1, 0])
        a = torch.zeros(2, 1, 2)
        a[0, 0] = torch.tensor([5.0, 1.5])  # slot 0 leaves the road: its episodes restart
        trace, drawn, n_rows = [], {1, 0}, set()
        for _ in range(40):
            obs, rew, *_, info = venv.step(a)
            trace.append((obs["agents"].clone(), rew.clone()))
            drawn.update(venv.scenario_index.tolist())
            n_rows.add(venv.episode.policy_state.ctx.mp.feat.shape[1])
        return trace, drawn, n_rows, venv

    padded, _, pad_rows, _ = run(False)
    trimmed, drawn, trim_rows, venv = run(True)
    assert venv.npc_policy.min_rows == union and drawn == {0, 1, 2}
    assert pad_rows == {1024} and trim_rows == {union[1]}
    for (oa, ra), (ob, rb) in zip(padded, trimmed, strict=True):
        torch.testing.assert_close(oa, ob, rtol=0, atol=1e-3)
        torch.testing.assert_close(ra, rb, rtol=0, atol=1e-4)
    assert (
        BatchedTrafficEnv(scenes, 1, npc_policy=TrafficBotsPolicy(model)).npc_policy.min_rows
        is None
    )


def test_stateful_npc_policy_resets_one_slot_without_touching_the_others(scenes):
    """TrafficBots NPCs (random small model): a slot restart leaves the other slots' NPCs alone."""
    from policies.trafficbots.config import TrafficBotsConfig
    from policies.trafficbots.model import TrafficBots
    from policies.trafficbots.policy import TrafficBotsPolicy

    torch.manual_seed(0)
    policy = TrafficBotsPolicy(TrafficBots(TrafficBotsConfig.small()))

    def run(crash: bool):
        # Episodes end by leaving the road only (slot 0's crash): neither the goal nor a
        # collision of slot 1's SDC, which holds its speed in a generated queue, may end slot
        # 1 within the compared steps.
        term = TerminationConfig(offroad=True, goal=False, collision=False)
        cfg = EnvConfig(termination=term)
        venv = BatchedTrafficEnv(scenes[:2], 2, npc_policy=policy, config=cfg, seed=0)
        venv.reset(scenario_indices=[0, 1])
        a = torch.zeros(2, 1, 2)
        if crash:
            a[0, 0] = torch.tensor([5.0, 1.5])  # slot 0 leaves the road and its episode ends
        trace, first_restart = [], None
        for k in range(50):
            obs, rew, *_, info = venv.step(a)
            if first_restart is None and bool(info["done"].any()):
                first_restart = k
            trace.append((obs["agents"][1].clone(), rew[1].clone()))
        return trace, first_restart, venv

    calm, calm_restart, _ = run(False)
    crashed, crash_restart, venv = run(True)
    calm_restart = len(calm) if calm_restart is None else calm_restart
    # Slot 0 restarts first in the crash run; until the calm run's first restart the two runs
    # differ only by that restart, so slot 1 must be unaffected.
    assert crash_restart is not None and calm_restart - crash_restart >= 3
    for (oa, ra), (ob, rb) in zip(calm[:calm_restart], crashed[:calm_restart]):
        torch.testing.assert_close(oa, ob, rtol=0, atol=1e-4)
        torch.testing.assert_close(ra, rb, rtol=0, atol=1e-6)
    assert venv.episode.policy_state.rollout.hist_pose.shape[0] == 2


@pytest.mark.parametrize("controlled", ["all", "sdc"])
def test_indexed_layout_densifies_to_the_dense_layout_through_restarts(scenes, controlled):
    kw = dict(controlled=controlled, npc_policy="constant_velocity", seed=3, route_points=4)
    dense = BatchedTrafficEnv(scenes, 3, **kw)
    indexed = BatchedTrafficEnv(scenes, 3, obs_layout="indexed", **kw)
    d_obs, _ = dense.reset()
    i_obs, _ = indexed.reset()
    assert set(i_obs) == set(OBS_INDEXED_KEYS) | {ROUTE_KEY}
    # A row per agent slot, or per observer and neighbour where that is fewer (one learner).
    n, q, ka = indexed.bank.start.pose.shape[1], indexed.num_agents, indexed.obs_config.num_agents
    rows = q * (1 + ka) if q * (1 + ka) < n else n
    assert i_obs["agent_tokens"].shape[1] == rows and (rows < n) == (controlled == "sdc")
    rng = np.random.default_rng(0)
    restarts = 0
    for _ in range(120):
        got = indexed.densify(i_obs)
        assert got.keys() == d_obs.keys()
        for key in d_obs:
            assert torch.equal(got[key], d_obs[key]), key
        a = torch.from_numpy(rng.uniform(-4, 4, (3, dense.num_agents, 2)).astype(np.float32))
        d_obs, d_rew, *_, d_info = dense.step(a)
        i_obs, i_rew, *_, i_info = indexed.step(a)
        assert torch.equal(d_rew, i_rew)
        final = indexed.densify(i_info["final_obs"])
        for key in d_info["final_obs"]:
            assert torch.equal(final[key], d_info["final_obs"][key]), key
        restarts += int(i_info["done"].sum())
    assert restarts >= 3
    # Per agent step the indexed layout moves a fraction of the dense bytes.
    per_dense = sum(v[0, 0].numel() for v in d_obs.values())
    per_indexed = sum(i_obs[k][0, 0].numel() for k in ("index", "pose", "mask"))
    assert per_indexed * 10 < per_dense


def test_reset_slots_restarts_only_those_slots(scenes):
    kw = dict(controlled="all", npc_policy="constant_velocity", seed=5)
    venv = BatchedTrafficEnv(scenes, 3, **kw)
    twin = BatchedTrafficEnv(scenes, 3, **kw)
    venv.reset()
    twin.reset()
    rng = np.random.default_rng(0)
    for _ in range(7):
        a = torch.from_numpy(rng.uniform(-2, 2, (3, venv.num_agents, 2)).astype(np.float32))
        venv.step(a)
        twin.step(a)
    obs = venv.reset_slots([1])
    # The new scenario is the next draw of the env's seeded generator.
    draws = np.random.default_rng(5)
    expected = [int(draws.integers(len(scenes))) for _ in range(4)][3]
    assert int(venv.scenario_index[1]) == expected
    fresh = BatchedTrafficEnv(scenes, 1, **kw)
    fobs, _ = fresh.reset(scenario_indices=[expected])
    keep = [0, 2]
    for key in obs:
        torch.testing.assert_close(obs[key][1], fobs[key][0], rtol=0, atol=0)
    # The other slots go on exactly as in a twin that never reset.
    for _ in range(5):
        a = torch.from_numpy(rng.uniform(-2, 2, (3, venv.num_agents, 2)).astype(np.float32))
        o1, r1, *_, info = venv.step(a)
        o2, r2, *_ = twin.step(a)
        assert not info["done"][keep].any()  # a restart would draw differently
        assert torch.equal(r1[keep], r2[keep])
        for key in o1:
            assert torch.equal(o1[key][keep], o2[key][keep]), key
    with pytest.raises(ValueError, match="distinct"):
        venv.reset_slots([0, 0])
    with pytest.raises(ValueError, match="distinct"):
        venv.reset_slots([3])
    with pytest.raises(ValueError, match="at least one"):
        venv.reset_slots([])


def test_trafficbots_restarts_from_its_scene_caches_exactly(scenes):
    """A bound TrafficBots policy keeps each scene's tokens and encoding (map, TL, destination
    distribution); the rollouts across slot restarts are those of a policy that computes them
    every time."""

    def run(cache: bool) -> tuple[list[torch.Tensor], int]:
        venv = BatchedTrafficEnv(scenes, 2, controlled="sdc", npc_policy="trafficbots", seed=4)
        if not cache:  # preprocess and encode on every restart
            venv.npc_policy.scene_cache.clear()
            venv.npc_policy.cache_scenes = False
        venv.reset()
        poses, restarts = [], 0
        for _ in range(100):
            *_, info = venv.step(venv.expert_actions())
            restarts += int(info["done"].sum())
            poses.append(venv.sim_state.pose.clone())
        return poses, restarts

    (cached, n1), (fresh, n2) = run(True), run(False)
    assert n1 == n2 >= 2
    assert all(torch.equal(a, b) for a, b in zip(cached, fresh))


def test_a_policy_that_owns_its_state_restarts_in_place_with_the_same_results(scenes):
    """``IDMPolicy.owns_state``: restarted slots' rows are written into the batch's policy
    state in place; the episodes are those of the copying path, slot restarts included."""
    from policies.idm import IDMPolicy

    runs = []
    for owns in (True, False):
        policy = IDMPolicy()
        policy.owns_state = owns
        venv = BatchedTrafficEnv(scenes, 3, controlled="sdc", npc_policy=policy, seed=3)
        venv.reset()
        g = torch.Generator().manual_seed(0)
        trace, restarts = [], 0
        for t in range(60):
            a = torch.randn(3, venv.num_agents, 2, generator=g) * torch.tensor([4.0, 0.8])
            obs, rew, *_, info = venv.step(a)
            restarts += int(info["done"].sum())
            if t == 20:
                venv.reset_slots([1])
            trace.append((rew.clone(), {k: v.clone() for k, v in obs.items()}))
        runs.append((trace, restarts))
    (a_trace, a_restarts), (b_trace, _) = runs
    assert a_restarts >= 2
    for (ra, oa), (rb, ob) in zip(a_trace, b_trace, strict=True):
        assert torch.equal(ra, rb) and all(torch.equal(oa[k], ob[k]) for k in oa)
