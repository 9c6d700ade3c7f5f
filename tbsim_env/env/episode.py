"""The episode core of both environments: a frozen ``EpisodeState`` and pure functions over it.

Waymax-style (``SimulatorState`` + ``step(state, action)``), in torch and batched:

* ``build_bank(scenarios, queries, ...)``: every scenario's start, padded into rows once.
* ``start(bank, ks, config)``: episodes of the bank rows ``ks`` -> ``EpisodeState`` [B].
* ``step(state, actions, npc_action, config)``: one 0.1 s step -> (``EpisodeState``,
  ``StepOutput``): dynamics and log replay, metrics, rewards (``env.rewards``),
  terminations and removals, truncation at the episode end, history, observations.
* ``reset_rows(bank, state, rows, ks)``: the rows ``rows`` start new episodes.

``TrafficEnv`` runs it at B = 1 behind the PettingZoo dict API; ``BatchedTrafficEnv`` at
B slots with same-step autoreset. Neither adds a rule of its own: they parse actions, call
the NPC policy (``npc_actions``), and package what ``step`` returns.

Nothing here modifies a tensor in place, so a state can be kept, compared or restarted from
(``TrafficEnv`` reuses one start state per scenario). ``step`` is tensor code that
``torch.compile`` traces whole (``env.compiled``); three eager shortcuts (a batch of one
reading its step as a number, collision tests that stop early, off-road corners recomputed
over every edge) check ``torch.compiler.is_compiling()`` instead.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import torch

from policies.base import Policy, PolicyState
from tbsim_env.core import constants as C
from tbsim_env.core.config import EnvConfig
from tbsim_env.core.errors import PolicyError
from tbsim_env.core.torch_utils import cached_arange, cast, const, gather_rows, scalar
from tbsim_env.data.scenario import Scenario
from tbsim_env.env.agent_metrics import Route, StepMetrics, build_route, goal_mask, step_metrics
from tbsim_env.env.rewards import Baseline, reward_and_termination, reward_weights
from tbsim_env.observation.rows import cat_rows, take_rows, with_rows
from tbsim_env.observation.tokens import (
    History,
    IndexedObservation,
    MapContext,
    ObsConfig,
    agent_static_features,
    build_map_context,
    densify_flat,
    init_history,
    observe_indexed,
    push_history,
)
from tbsim_env.sim import core
from tbsim_env.sim.build import build_sim_state
from tbsim_env.sim.dynamics import action_limits, inverse_step
from tbsim_env.sim.state import SimState


@dataclass(frozen=True)
class EpisodeSetup:
    """What an episode is, fixed from its start to its end (leading dimension: rows).

    Attributes:
        ctx: the static map context (observation tokens); None in a bank of a config that
            does not observe (``StepConfig.observe``).
        query: [., Q] int64, agent slot of each externally controlled agent (padding repeats
            the first).
        qmask: [., Q] bool, a real controlled agent (not padding).
        slot_query: [., N] int64, for an external slot its column of ``query`` (0 elsewhere).
        route: logged routes of the query agents.
        has_goal: [., Q] bool, the logged route ends farther than the goal radius.
        static: [., N, 6] ``agent_static_features`` of every slot.
        external: [., N] bool, slots driven by the caller's actions.
        npc: [., N] bool, slots driven by the NPC policy (none when it replays the log).
    """

    ctx: MapContext | None
    query: torch.Tensor
    qmask: torch.Tensor
    slot_query: torch.Tensor
    route: Route
    has_goal: torch.Tensor
    static: torch.Tensor
    external: torch.Tensor
    npc: torch.Tensor


@dataclass(frozen=True)
class EpisodeBank:
    """Every scenario's first state and setup, padded to common shapes (leading dim S).

    An episode's start depends on its scenario alone, so what ``start`` hands a new episode
    besides the state is computed here once: a restart only gathers rows.

    Attributes:
        start: [S] ``SimState`` at the first simulated step (``controlled`` set).
        setup: [S] ``EpisodeSetup``.
        history: [S] ``History`` ending at the first step.
        first: [S] ``StepMetrics`` of the first state (without ``agent_distance``).
    """

    start: SimState
    setup: EpisodeSetup
    history: History
    first: StepMetrics

    @property
    def num_scenarios(self) -> int:
        return int(self.setup.query.shape[0])


@dataclass(frozen=True)
class EpisodeState:
    """Everything a batch of B episodes carries between steps.

    Attributes:
        sim: the simulator state.
        history: the last H states (observations).
        setup: the episode's fixed data (``EpisodeSetup``, B rows).
        progress: [B, Q] m, best progress along the logged route so far.
        goal_reached: [B, Q] bool, the goal was reached.
        alive: [B, Q] bool, agents that act next step (not terminated, truncated, padding).
        episode_return: [B, Q] float32, sum of rewards since the episode started.
        episode_length: [B] int64, steps since the episode started.
        scenario: [B] int64, the bank row (scenario index) of each episode.
        policy_state: the NPC policy's state (None without NPCs); ``step`` carries it through
            unchanged (the policy acts before ``step``, see ``npc_actions``).
    """

    sim: SimState
    history: History
    setup: EpisodeSetup
    progress: torch.Tensor
    goal_reached: torch.Tensor
    alive: torch.Tensor
    episode_return: torch.Tensor
    episode_length: torch.Tensor
    scenario: torch.Tensor
    policy_state: PolicyState = None

    @property
    def batch_size(self) -> int:
        return int(self.alive.shape[0])


@dataclass(frozen=True)
class StepConfig:
    """The constants of ``step``: the env's rules, the observation sizes and layout.

    Attributes:
        env: episode, reward and termination settings.
        obs: observation sizes.
        dense: ``StepOutput.obs`` in the dense layout instead of an ``IndexedObservation``:
            each observer's keys in one row, [B, Q, D] (``observation.densify_flat``;
            ``observation.dense_views`` reads the keys of ``observe``'s dict from it).
        observe: False: ``step`` leaves ``StepOutput.obs`` None (the caller observes the
            next state with ``observe_state`` when it needs to: the same values).
    """

    env: EnvConfig
    obs: ObsConfig
    dense: bool = False
    observe: bool = True

    def __post_init__(self) -> None:
        reward_weights(self.env.reward)  # an unknown reward term fails here, not mid-episode


@dataclass(frozen=True)
class StepOutput:
    """What one ``step`` returns besides the next state, [B, Q] per agent.

    Attributes:
        obs: observations of the query agents in the new state (``IndexedObservation``, or
            the dense rows of ``StepConfig.dense``), for every observer (mask with
            ``active`` or ``alive`` as the API needs).
        reward: float32, the weighted reward terms; 0 for agents not active.
        terms: {name: [B, Q]} the unweighted reward terms (``env.rewards``).
        terminated: bool, the agent's episode ended by an event this step.
        truncated: bool, the episode reached its last step (and the agent did not terminate).
        active: bool, agents that acted this step (``alive`` before it).
        metrics: ``step_metrics`` of the new state (before removals).
        done: [B] bool, no agent of the row is alive any more.
        stale: [B] bool, set only under ``torch.compile``: rows where the graph's bounded
            off-road search could not vouch for its result; the caller must redo the step
            eagerly (``env.compiled``). Eagerly None.
    """

    obs: Any
    reward: torch.Tensor
    terms: dict[str, torch.Tensor]
    terminated: torch.Tensor
    truncated: torch.Tensor
    active: torch.Tensor
    metrics: StepMetrics
    done: torch.Tensor
    stale: torch.Tensor | None = None


# ---------------------------------------------------------------------- building
def build_bank(
    scenarios: list[Scenario],
    queries: list[list[int]],
    exact_replay: bool,
    config: StepConfig,
    device: torch.device,
) -> EpisodeBank:
    """The start of every scenario's episode, padded into one bank.

    Args:
        scenarios: S scenarios on the episode's time grid.
        queries: per scenario, the track indices of the externally controlled agents (at
            least one each; Q = the longest list).
        exact_replay: the NPC policy replays the log (then no slot is an NPC slot).
        config: the step's constants (start step, observation sizes, goal radius).
        device: torch device of the bank.

    Without ``config.observe`` the bank has no observation map context (``setup.ctx`` None):
    its steps do not observe.
    """
    start_step = config.env.start_step
    state = build_sim_state(scenarios, start_step=start_step, device=device)
    ctx = build_map_context(scenarios, state.origin, config.obs) if config.observe else None
    s, q, n = len(scenarios), max(len(x) for x in queries), state.num_agents
    query = torch.zeros((s, q), dtype=torch.int64)
    qmask = torch.zeros((s, q), dtype=torch.bool)
    slot_query = torch.zeros((s, n), dtype=torch.int64)
    for i, idx in enumerate(queries):
        query[i, : len(idx)] = torch.tensor(idx)
        query[i, len(idx) :] = idx[0]
        qmask[i, : len(idx)] = True
        slot_query[i, idx] = torch.arange(len(idx))
    query, qmask, slot_query = query.to(device), qmask.to(device), slot_query.to(device)
    external = torch.zeros_like(state.valid)
    external[torch.arange(s, device=device)[:, None], query] = True
    npc = torch.zeros_like(external) if exact_replay else state.agents.mask & ~external
    state = state.replace(controlled=external | npc)
    route = build_route(state, query)
    setup = EpisodeSetup(
        ctx=ctx,
        query=query,
        qmask=qmask,
        slot_query=slot_query,
        route=route,
        has_goal=goal_mask(route, start_step, config.env.reward.goal_radius),
        static=agent_static_features(state),
        external=external,
        npc=npc,
    )
    return EpisodeBank(
        start=state,
        setup=setup,
        history=init_history(state, config.obs.history),
        first=_first_metrics(state, setup),
    )


def _first_metrics(state: SimState, setup: EpisodeSetup) -> StepMetrics:
    """``step_metrics`` of the bank's first states without ``agent_distance``, in chunks of
    ``C.BANK_METRICS_CHUNK`` scenarios (its [S, Q, N] distances would be large for a big
    bank)."""
    s, step = setup.query.shape[0], C.BANK_METRICS_CHUNK
    if s <= step:
        return dataclasses.replace(
            step_metrics(state, setup.query, setup.route), agent_distance=None
        )
    parts = []
    for lo in range(0, s, step):
        rows = torch.arange(lo, min(lo + step, s), device=setup.query.device)
        parts.append(_first_metrics(take_rows(state, rows), take_rows(setup, rows)))
    return cat_rows(parts)


def start(
    bank: EpisodeBank, ks: torch.Tensor, reuse: EpisodeState | None = None
) -> tuple[EpisodeState, StepMetrics]:
    """New episodes of the bank rows ``ks`` [B] (``policy_state`` None): rows of the bank.

    Args:
        reuse: optional episodes of B rows whose tensors receive the new ones where they can
            (``rows.take_rows``' ``out``): overwritten, so only for their owner's own state.

    Returns:
        (the episodes' first state, ``step_metrics`` of it: the first infos).
    """
    sim = take_rows(bank.start, ks, None if reuse is None else reuse.sim)
    setup = take_rows(bank.setup, ks, None if reuse is None else reuse.setup)
    history = take_rows(bank.history, ks, None if reuse is None else reuse.history)
    metrics = take_rows(bank.first, ks)
    state = EpisodeState(
        sim=sim,
        history=history,
        setup=setup,
        progress=metrics.progress,
        goal_reached=torch.zeros_like(setup.qmask),
        alive=setup.qmask.clone(),
        episode_return=torch.zeros(setup.qmask.shape, device=ks.device),
        episode_length=torch.zeros_like(ks),
        scenario=ks.clone(),
    )
    return state, metrics


def reset_rows(
    bank: EpisodeBank,
    state: EpisodeState,
    rows: torch.Tensor,
    ks: torch.Tensor,
    in_place: bool = False,
) -> EpisodeState:
    """``state`` with the rows ``rows`` [R] (distinct) restarted on the bank rows ``ks`` [R]
    (``start``'s episodes of them, read straight from the bank: no R-row copy is made
    first); the other rows and ``policy_state`` are unchanged (restarting the policy is the
    caller's: it needs the scenarios and the random generator). ``in_place``: as
    ``merge_rows``."""

    def put(dst, src):  # the bank rows ks of src into the rows of dst
        return with_rows(dst, rows, src, in_place=in_place, src_rows=ks)

    def zero(x: torch.Tensor) -> torch.Tensor:
        return with_rows(x, rows, x.new_zeros((len(rows), *x.shape[1:])), in_place=in_place)

    return dataclasses.replace(
        state,
        sim=put(state.sim, bank.start),
        history=put(state.history, bank.history),
        setup=put(state.setup, bank.setup),
        progress=put(state.progress, bank.first.progress),
        goal_reached=zero(state.goal_reached),
        alive=put(state.alive, bank.setup.qmask),
        episode_return=zero(state.episode_return),
        episode_length=zero(state.episode_length),
        scenario=with_rows(state.scenario, rows, ks, in_place=in_place),
    )


def merge_rows(
    state: EpisodeState, rows: torch.Tensor, fresh: EpisodeState, in_place: bool = False
) -> EpisodeState:
    """``state`` with the rows ``rows`` [R] (distinct) replaced by the R rows of ``fresh``
    (``start``'s episodes, policy state None); ``state.policy_state`` is kept. ``in_place``:
    write the rows into ``state``'s tensors (``rows.with_rows``), for a caller that alone holds
    them."""
    if rows.numel() == state.batch_size:  # every row (``rows`` are distinct): no merge
        if bool((rows != cached_arange(state.batch_size, rows.device)).any()):
            fresh = take_rows(fresh, torch.argsort(rows))
        return dataclasses.replace(fresh, policy_state=state.policy_state)
    body = dataclasses.replace(state, policy_state=None)
    merged = with_rows(body, rows, fresh, in_place=in_place)
    return dataclasses.replace(merged, policy_state=state.policy_state)


# ---------------------------------------------------------------------- stepping
def npc_actions(
    policy: Policy, state: EpisodeState, generator: torch.Generator
) -> tuple[torch.Tensor, PolicyState]:
    """The NPC policy's actions [B, N, 2] and its next state.

    Raises:
        PolicyError: the policy gave a NaN or infinite action to an NPC it drives (naming the
            policy, and the batch rows and track ids of those NPCs); the dynamics never see it.
    """
    action, policy_state = policy.act(state.sim, state.policy_state, generator)
    if bool(torch.isfinite(action).all()):  # the usual case, in two operations
        return action, policy_state
    sim = state.sim
    bad = state.setup.npc & sim.valid & ~torch.isfinite(action).all(-1)
    if bool(bad.any()):
        rows, slots = bad.nonzero(as_tuple=True)
        ids = sim.agents.track_id[rows, slots].tolist()
        agents = [f"row {r} track {t}" for r, t in zip(rows.tolist(), ids)]
        more = f" and {len(agents) - 5} more" if len(agents) > 5 else ""
        name = getattr(policy, "name", type(policy).__name__)
        raise PolicyError(
            f"NPC policy {name!r} returned a non-finite action at step "
            f"{int(sim.step.max())} for {len(agents)} agent(s): {', '.join(agents[:5])}{more}"
        )
    return action, policy_state


def slot_actions(
    state: EpisodeState, actions: torch.Tensor, npc_action: torch.Tensor | None
) -> torch.Tensor:
    """[B, N, 2] actions of every slot: ``actions`` [B, Q, 2] at the alive external agents,
    ``npc_action`` [B, N, 2] (or None) at the NPC slots, zero elsewhere (values elsewhere in
    either input, NaN included, are never read)."""
    setup = state.setup
    b, n = setup.slot_query.shape
    if actions.shape[1] == 1:  # one query column: every slot reads it (views, no gather)
        ext, alive = actions.expand(b, n, 2), state.alive.expand(b, n)
    else:
        ext = gather_rows(actions, setup.slot_query)
        alive = gather_rows(state.alive, setup.slot_query)
    on = torch.bitwise_and(setup.external, alive)
    if npc_action is None:
        return core.merge_actions((on, ext))
    return core.merge_actions((setup.npc, npc_action), (on, ext))


def step(
    state: EpisodeState,
    actions: torch.Tensor,
    npc_action: torch.Tensor | None,
    config: StepConfig,
) -> tuple[EpisodeState, StepOutput]:
    """Advance every episode of the batch by one step (0.1 s).

    Args:
        state: the episodes now.
        actions: [B, Q] x (acceleration m/s^2, yaw rate rad/s) float32 of the external
            agents (read where ``state.alive``; clipped to the type limits by the dynamics).
        npc_action: [B, N, 2] the NPC policy's actions (``npc_actions``), None without NPCs.
        config: the step's constants.

    Returns:
        (the next state, what the step produced). Terminated agents leave the scene when
        ``config.env.remove_terminated``; the history and observations see the state after.
    """
    setup, env = state.setup, config.env
    # Without NPC actions only the external agents move (the others replay the log).
    movers = setup.query if npc_action is None else None
    sim = core.step(state.sim, slot_actions(state, actions, npc_action), movers)
    metrics = step_metrics(sim, setup.query, setup.route)
    baseline = Baseline(state.progress, state.goal_reached, setup.has_goal)
    speed = gather_rows(sim.speed, setup.query)
    outcome = reward_and_termination(metrics, speed, baseline, env.reward, env.termination)
    active = state.alive
    terminated = torch.bitwise_and(outcome.terminated, active)
    # Eagerly, skip the removal when nobody leaves; a compiled graph cannot branch on data.
    if env.remove_terminated and (torch.compiler.is_compiling() or bool(terminated.any())):
        sim = remove_agents(sim, setup.query, terminated)
    history = push_history(state.history, sim)
    obs = None
    if config.observe:  # removals leave every pose as step_metrics saw it: its distances serve
        obs = observe_indexed(
            sim,
            history,
            setup.ctx,
            setup.query,
            config.obs,
            setup.static,
            metrics.agent_distance,
            observer_mask=active,
        )
        if config.dense:
            obs = densify_flat(obs, config.obs.tokens.piece_segments)
    stale = None
    if torch.compiler.is_compiling():
        stale = metrics.offroad_stale.any(-1)
    reward = torch.where(active, outcome.reward, const(0.0, outcome.reward))
    last = sim.step.view(-1, 1) >= scalar(env.last_step, sim.step.dtype, sim.device)
    # Truncated: active, at the last step and not terminated (terminated implies active).
    # (For flags, ``x > y`` is ``x & ~y``: one operation.)
    truncated = torch.gt(torch.bitwise_and(active, last), terminated)
    alive = torch.gt(active, torch.bitwise_or(terminated, truncated))
    nxt = dataclasses.replace(
        state,
        sim=sim,
        history=history,
        progress=outcome.progress_best,
        goal_reached=torch.bitwise_or(state.goal_reached, outcome.goal_now),
        alive=alive,
        episode_return=state.episode_return + reward,
        episode_length=torch.add(state.episode_length, scalar(1, torch.int64, sim.device)),
    )
    out = StepOutput(
        obs=obs,
        reward=reward,
        terms=outcome.terms,
        terminated=terminated,
        truncated=truncated,
        active=active,
        metrics=metrics,
        done=~alive.any(-1),
        stale=stale,
    )
    return nxt, out


def remove_agents(sim: SimState, query: torch.Tensor, remove: torch.Tensor) -> SimState:
    """``sim`` without the query agents flagged in ``remove`` [B, Q] (they leave for good)."""
    # Counts per slot (padding columns repeat a slot, never flagged): deterministic.
    gone = torch.zeros(sim.valid.shape, dtype=torch.int32, device=sim.device)
    gone = gone.scatter_add_(1, query, cast(remove, torch.int32))
    return sim.replace(valid=torch.bitwise_and(sim.valid, gone == 0))


# ---------------------------------------------------------------------- reading
def observe_state(
    state: EpisodeState, config: StepConfig, observers: torch.Tensor | None = None
) -> IndexedObservation | torch.Tensor:
    """Observations of the query agents in the current state, as ``step`` makes them (the
    dense rows with ``config.dense``).

    Args:
        observers: [B, Q] bool, the agents that observe (default ``state.alive``; ``step``
            observes for the agents active before it, ``StepOutput.active``).
    """
    setup = state.setup
    obs = observe_indexed(
        state.sim,
        state.history,
        setup.ctx,
        setup.query,
        config.obs,
        setup.static,
        observer_mask=state.alive if observers is None else observers,
    )
    return densify_flat(obs, config.obs.tokens.piece_segments) if config.dense else obs


def agent_infos(state: EpisodeState, metrics: StepMetrics) -> dict[str, torch.Tensor]:
    """The per-agent info columns of both envs, each [B, Q]: the metrics of ``state``
    (``metrics``), whether the goal was reached, and the speed m/s."""
    return {
        "collision": metrics.collision,
        "offroad": metrics.offroad,
        "offroad_distance": metrics.offroad_distance,
        "progress": metrics.progress,
        "goal_distance": metrics.goal_distance,
        "goal_reached": state.goal_reached,
        "log_divergence": metrics.log_divergence,
        "speed": gather_rows(state.sim.speed, state.setup.query),
    }


def expert_actions(state: EpisodeState) -> torch.Tensor:
    """[B, Q, 2] actions that steer each alive query agent onto its logged state of the next
    step (one inverse-dynamics step, ``inverse_step``); zero where the log has no next state
    or the agent is not alive. Following them from the start reproduces the log within
    centimetres where the log is feasible."""
    sim, query = state.sim, state.setup.query
    n_t = sim.log.num_steps
    rows = cached_arange(state.batch_size, sim.device)[:, None]
    t1 = (sim.step + 1).clamp(max=n_t - 1)[:, None].expand_as(query)
    max_acc, max_yaw = action_limits(sim.agents.object_type[rows, query])
    act = inverse_step(
        sim.pose[rows, query],
        sim.speed[rows, query],
        sim.log.of_slots("pose", query, t1),
        sim.log.of_slots("speed", query, t1),
        max_acc,
        max_yaw,
    )
    keep = sim.log.of_slots("valid", query, t1) & state.alive
    return act * keep[..., None]


__all__ = [
    "EpisodeBank",
    "EpisodeSetup",
    "EpisodeState",
    "StepConfig",
    "StepOutput",
    "agent_infos",
    "build_bank",
    "expert_actions",
    "npc_actions",
    "observe_state",
    "remove_agents",
    "merge_rows",
    "reset_rows",
    "slot_actions",
    "start",
    "step",
]
