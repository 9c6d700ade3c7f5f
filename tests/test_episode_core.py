"""The episode core (``tbsim_env.env.episode``): pure functions over an immutable state."""

from __future__ import annotations

import dataclasses

import pytest
import torch

from policies import make_policy
from tbsim_env.core.config import EnvConfig
from tbsim_env.data.generator import default_scenarios
from tbsim_env.env import episode as ep
from tbsim_env.env.agent_metrics import step_metrics
from tbsim_env.env.setup import select_scenarios
from tbsim_env.observation.rows import take_rows
from tbsim_env.observation.tokens import ObsConfig, init_history


@pytest.fixture(scope="module")
def core():
    """(bank, config) of three generated scenes with every agent controlled."""
    config = ep.StepConfig(EnvConfig(), ObsConfig())
    policy = make_policy("log_replay")
    sel = select_scenarios(default_scenarios(3), "all", config.env, policy, False)
    bank = ep.build_bank(sel.scenarios, sel.queries, True, config, torch.device("cpu"))
    return bank, config


def _tensors(tree) -> list[torch.Tensor]:
    if isinstance(tree, torch.Tensor):
        return [tree]
    if dataclasses.is_dataclass(tree):
        return [t for f in dataclasses.fields(tree) for t in _tensors(getattr(tree, f.name))]
    if isinstance(tree, (list, tuple)):
        return [t for x in tree for t in _tensors(x)]
    if isinstance(tree, dict):
        return [t for x in tree.values() for t in _tensors(x)]
    return []


def _equal(a, b) -> bool:
    ta, tb = _tensors(a), _tensors(b)
    return len(ta) == len(tb) and all(torch.equal(x, y) for x, y in zip(ta, tb))


def test_step_and_reset_modify_nothing(core):
    bank, config = core
    state, _ = ep.start(bank, torch.tensor([0, 1, 2]))
    before = [t.clone() for t in _tensors(state)]
    bank_before = [t.clone() for t in _tensors(bank)]
    gen = torch.Generator().manual_seed(0)
    for _ in range(5):
        actions = torch.randn(3, bank.setup.query.shape[1], 2, generator=gen)
        nxt, _ = ep.step(state, actions, None, config)
        ep.reset_rows(bank, nxt, torch.tensor([1]), torch.tensor([2]))
    assert all(torch.equal(x, y) for x, y in zip(_tensors(state), before))
    assert all(torch.equal(x, y) for x, y in zip(_tensors(bank), bank_before))


def test_step_is_a_function_of_its_inputs(core):
    bank, config = core
    state, _ = ep.start(bank, torch.tensor([2, 0]))
    gen = torch.Generator().manual_seed(1)
    actions = torch.randn(2, bank.setup.query.shape[1], 2, generator=gen)
    a_state, a_out = ep.step(state, actions, None, config)
    b_state, b_out = ep.step(state, actions, None, config)
    assert _equal(a_state, b_state) and _equal(a_out, b_out)


@pytest.mark.parametrize("in_place", [False, True])
@pytest.mark.parametrize("rows", [[1], [2, 0], [0, 1, 2], [2, 0, 1], [1, 0, 2], [5, 0, 3, 1, 4]])
def test_reset_rows_equals_a_fresh_start_of_those_rows(core, rows, in_place):
    """The rows restart as ``start`` of their bank rows, read straight from the bank (a row
    at a time up to ``ROW_COPY_MAX`` rows in place, gathered beyond); the others keep their
    episodes."""
    bank, config = core
    state, _ = ep.start(bank, torch.tensor([0, 1, 2, 0, 1, 2]))
    actions = torch.zeros(6, bank.setup.query.shape[1], 2)
    for _ in range(3):
        state, _ = ep.step(state, actions, None, config)
    before = take_rows(state, torch.arange(6))  # a copy
    rows_t = torch.tensor(rows)
    ks = torch.tensor([(r + 1) % 3 for r in rows])
    out = ep.reset_rows(bank, state, rows_t, ks, in_place=in_place)
    fresh, _ = ep.start(bank, ks)
    for i, r in enumerate(rows):
        assert _equal(take_rows(out, torch.tensor([r])), take_rows(fresh, torch.tensor([i])))
    for r in set(range(6)) - set(rows):
        assert _equal(take_rows(out, torch.tensor([r])), take_rows(before, torch.tensor([r])))
    if not in_place:
        assert _equal(state, before), "reset_rows returns a new tree"


def test_start_into_a_state_reuses_its_tensors_and_equals_a_fresh_start(core):
    """``start(reuse=state)`` writes the new episodes into ``state``'s own tensors (a whole
    batch restarting reuses its memory) and gives what a fresh start gives."""
    bank, config = core
    state, _ = ep.start(bank, torch.tensor([0, 1, 2]))
    actions = torch.zeros(3, bank.setup.query.shape[1], 2)
    for _ in range(3):
        state, _ = ep.step(state, actions, None, config)
    ks = torch.tensor([2, 2, 0])
    owned = {t.data_ptr() for t in _tensors(state.sim) + _tensors(state.setup)}
    got, got_metrics = ep.start(bank, ks, reuse=state)
    want, want_metrics = ep.start(bank, ks)
    assert _equal(got, want) and _equal(got_metrics, want_metrics)
    # The bank's first metrics and history are those of the first state.
    sim, setup = got.sim, got.setup
    direct = dataclasses.replace(step_metrics(sim, setup.query, setup.route), agent_distance=None)
    assert _equal(got_metrics, direct) and torch.equal(got.progress, direct.progress)
    assert torch.equal(got.history.data, init_history(sim, config.obs.history).data)
    reused = [t for t in _tensors(got.sim) + _tensors(got.setup) if t.data_ptr() in owned]
    big = max(_tensors(got.sim), key=torch.Tensor.numel)
    assert big.data_ptr() in owned and len(reused) > 10


def test_bank_first_metrics_in_chunks_equal_one_batch(core, monkeypatch):
    bank, config = core
    policy = make_policy("log_replay")
    sel = select_scenarios(default_scenarios(3), "all", config.env, policy, False)
    monkeypatch.setattr(ep.C, "BANK_METRICS_CHUNK", 2)  # 3 scenes: chunks of 2 and 1
    chunked = ep.build_bank(sel.scenarios, sel.queries, True, config, torch.device("cpu"))
    assert _equal(chunked.first, bank.first)


def test_take_rows_writes_only_into_tensors_that_own_their_storage() -> None:
    table = {"a": torch.arange(12.0).view(4, 3), "b": torch.arange(4), "c": torch.ones(4, 2)}
    rows = torch.tensor([3, 0])
    whole = torch.zeros(2, 3)
    view = torch.zeros(4, 3)[:2]  # shares its storage with two more rows
    out = take_rows(table, rows, {"a": whole, "b": view, "c": torch.zeros(2, 2, 1)})
    assert out["a"] is whole and torch.equal(whole, table["a"][rows])
    assert out["b"] is not view and not view.any()  # wrong shape, and a view: not written
    assert torch.equal(out["b"], table["b"][rows]) and torch.equal(out["c"], table["c"][rows])
    assert torch.equal(take_rows(table, rows, None)["a"], table["a"][rows])


def test_slot_actions_read_only_alive_external_agents(core):
    bank, config = core
    state, _ = ep.start(bank, torch.tensor([0]))
    q = state.setup.query.shape[1]
    actions = torch.full((1, q, 2), float("nan"))
    alive = state.alive.clone()
    alive[0, 1:] = False  # only the first controlled agent acts
    state = dataclasses.replace(state, alive=alive)
    actions[0, 0] = torch.tensor([1.0, -0.5])
    slots = ep.slot_actions(state, actions, None)
    assert torch.isfinite(slots).all()
    first = int(state.setup.query[0, 0])
    assert torch.equal(slots[0, first], torch.tensor([1.0, -0.5]))
    others = torch.ones(slots.shape[1], dtype=torch.bool)
    others[first] = False
    assert not slots[0, others].any()
