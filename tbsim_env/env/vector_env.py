"""``BatchedTrafficEnv``: B scenarios stepped at once, torch tensors in and out, autoreset.

The training-side counterpart of ``TrafficEnv``: the same simulation core, observations,
metrics, rewards and terminations, but on a batch of B scenario *slots* with a fixed shape,
so a learner gets ``[B, Q, ...]`` tensors (Q = the most controlled agents any scenario has,
padded) without any per-agent Python dictionaries.

It is a shell over the episode core (``tbsim_env.env.episode``), as ``TrafficEnv`` is at
B = 1: the core holds every rule, this class checks actions, runs the NPC policy, packages the
core's outputs and restarts finished slots.

* **Scenario bank.** Every scenario's start is converted once at construction into one
  padded ``EpisodeBank``; an episode is a row gather of it (``episode.start``).
* **Same-step autoreset.** A slot whose agents are all done restarts in the same step (as
  SB3 and Isaac-style vector envs do): the next scenario is drawn with the env's seeded
  generator and ``episode.reset_rows`` replaces that slot's rows; only its history, metrics
  baseline and policy state are rebuilt, on a sub-batch. No re-batching of the other slots,
  no re-padding, no Python work per agent.
* Padding to the largest scenario does not change any result: padding agents are never
  valid, padding map pieces, lights and road edges are never valid (``TrafficEnv`` equality
  is tested on full episodes).

Scenes of any log length share one bank: every scenario is put on the episode's time grid
(``EnvConfig.last_step``, see ``tbsim_env.sim.horizon``), so full WOMD scenes and history-only
ones (the WOSAC test split) mix; as in ``TrafficEnv`` the NPC policy drives NPCs past the end of
their log, and log-replayed NPCs refuse a scene whose log ends before the episode.

Step semantics per slot follow ``TrafficEnv.step`` exactly: the reward of a controlled agent
is the ``RewardConfig`` combination of the ``step_metrics`` of the new state, agents terminate
on the ``TerminationConfig`` events (and leave the scene when
``EnvConfig.remove_terminated``), every remaining agent is truncated at the episode end. An
agent that is done is masked out (``agent_mask`` False, reward 0) until its slot resets.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from policies.base import Policy, PolicyState
from tbsim_env.core import constants as C
from tbsim_env.core.config import EnvConfig
from tbsim_env.core.errors import ActionError
from tbsim_env.core.torch_utils import cached_arange, gather_rows, torch_threads
from tbsim_env.env import episode as ep
from tbsim_env.env.agent_metrics import Route, StepMetrics
from tbsim_env.env.compiled import StepFunction
from tbsim_env.env.episode import EpisodeBank, EpisodeState, StepConfig
from tbsim_env.env.setup import (
    ControlledSpec,
    agent_name,
    make_npc_policy,
    resolve_device,
    select_scenarios,
)
from tbsim_env.observation.rows import take_rows, with_rows
from tbsim_env.observation.tokens import (
    IndexedObservation,
    ObsConfig,
    dense_views,
    densify_flat,
    observation_shapes,
)
from tbsim_env.sim.dynamics import action_limits
from tbsim_env.sim.geometry import to_local
from tbsim_env.sim.state import SimState

ROUTE_KEY = "route"
"""Optional extra observation key: upcoming points of the logged route in the ego frame."""

OBS_INDEXED_KEYS = {
    "scene": "[B] int64, the slot's scenario: its row of ``map_token_bank``",
    "agent_tokens": "[B, R, H * 5 + H + 7] float32, agent tokens this step: history in "
    "its own frame, history mask, attributes (length, width, type one-hot, speed); a row per "
    "agent slot (R = N), or, when that is fewer rows, per observer and neighbour it sees "
    "(R = Q (1 + Ka)); fixed per env",
    "light_tokens": "[B, L, 5] float32, traffic-light state one-hot this step",
    "ego": "[B, Q] int64, each observer's own row of agent_tokens",
    "index": "[B, Q, Ka + Km + Kt] int64, the agent_tokens rows, map pieces and lights it sees",
    "pose": "[B, Q, Ka + Km + Kt, 3] float32, their (dx, dy, dyaw) in the observer's frame",
    "mask": "[B, Q, Ka + Km + Kt] float32, 1 where seen",
    "observer_mask": "[B, Q] float32, 1 for active observers (all else is zero for others)",
}
"""Keys of an ``obs_layout="indexed"`` observation (``observation.IndexedObservation``)."""


# ---------------------------------------------------------------------- route features
def route_features(
    route: Route, progress: torch.Tensor, pose: torch.Tensor, num_points: int, spacing: float
) -> torch.Tensor:
    """Upcoming points of each agent's logged route, in the agent's frame.

    Points lie at arc lengths ``progress + k * spacing`` (k = 1..num_points), clamped to the
    end of the route (the goal), so the last points repeat the goal once it is near.

    Args:
        route: logged routes, ``points`` [B, Q, T, 2], ``arc`` [B, Q, T].
        progress: [B, Q] m, current progress along the route.
        pose: [B, Q, 3] current pose (x, y, yaw).
        num_points: R.
        spacing: m between points.

    Returns:
        [B, Q, R, 2] float32 (x forward, y left) m.
    """
    k = torch.arange(1, num_points + 1, device=pose.device, dtype=torch.float32)
    total = route.arc[..., -1:]  # [B, Q, 1]
    s = torch.minimum(progress[..., None] + k * spacing, total)  # [B, Q, R]
    n_t = route.arc.shape[-1]
    idx = torch.searchsorted(route.arc.contiguous(), s.contiguous(), right=True).clamp(1, n_t - 1)
    a_s, b_s = route.arc.gather(-1, idx - 1), route.arc.gather(-1, idx)
    frac = ((s - a_s) / (b_s - a_s).clamp_min(1e-9)).clamp(0.0, 1.0)
    a = route.points.gather(-2, (idx - 1)[..., None].expand(-1, -1, -1, 2))
    b = route.points.gather(-2, idx[..., None].expand(-1, -1, -1, 2))
    pts = a + frac[..., None] * (b - a)
    return to_local(pts, pose[..., None, :]).float()


# ---------------------------------------------------------------------- the env
class BatchedTrafficEnv:
    """B scenario slots stepped together; torch tensors ``[B, Q, ...]`` in and out.

    Args:
        scenarios: as ``TrafficEnv``: None (embedded generated scenes), a path / glob /
            folder, or a list of ``Scenario``.
        batch_size: B, number of scenario slots stepped at once.
        controlled: ``"sdc"``, ``"tracks_to_predict"``, ``"all"`` or a list of track ids.
            Scenarios where nothing is controllable are left out of the draw
            (``UnusableScenarioError`` naming them when none is left).
        npc_policy: ``"log_replay"``, ``"constant_velocity"``, ``"trafficbots"``, a
            registered name or a ``Policy``. A stateful policy's state must be a tree
            (dataclass / dict / tuple) of tensors with the batch as leading dimension and
            trailing shapes that do not depend on the batch's scenarios, so that one slot can
            be reset by ``initial_state`` on that slot alone (other leaves are batch-wide
            metadata and kept). A policy with a ``for_scenarios(scenarios)`` method is
            replaced by what it returns for the scenario bank (``"trafficbots"`` then runs on
            the token rows the bank uses instead of the padded limits).
        npc_kwargs: keyword arguments of the registered policy factory (e.g.
            ``{"checkpoint": path}`` for ``"trafficbots"``; its ``device`` is set to ours).
        device: torch device of the simulation and of the returned tensors.
        config: episode, reward and termination settings (shared with ``TrafficEnv``).
        obs_config: observation sizes.
        seed: seed of the scenario draws and of the policies' random generator.
        route_points: if > 0, adds the observation key ``"route"`` [B, Q, R, 2]: the next R
            points of the agent's logged route in its frame (not in ``TrafficEnv``).
        route_spacing: m between route points.
        obs_layout: ``"dense"`` (default): every observer gets its own copy of every token it
            sees, the ``TrafficEnv`` keys as [B, Q, ...] float32. ``"indexed"``: each token
            once, and per observer only which tokens it sees (``OBS_INDEXED_KEYS``): about 15x
            fewer bytes per agent step; ``densify(obs)`` gives the dense layout from it,
            equal to what ``"dense"`` returns.
        compile: run the core's step (dynamics, metrics, rewards, history, observations) as
            one ``torch.compile`` graph where that is the faster path: on a GPU, and on the
            CPU for batches of at most ``COMPILE_CPU_MAX_BATCH`` scenarios and
            ``COMPILE_CPU_MAX_OBSERVERS`` controlled agents (a larger CPU batch steps eagerly,
            with a warning: the graph tests every agent pair and map piece, and measured
            0.4-0.5x of eager with all agents controlled from B = 16); ``"always"`` forces the
            graph. Results
            equal the eager ones to float rounding. The first step compiles (tens of seconds,
            a C++ compiler on the CPU), and again once for another batch shape.
        torch_threads: intra-op threads inside ``reset`` / ``step`` (restored afterwards);
            1 (default) is fastest on a shared CPU (a step is many small tensor operations);
            None leaves torch's setting alone (e.g. on a GPU or large idle CPUs).

    Attributes:
        num_agents: Q, controlled-agent slots per scenario slot.
        scenarios: the scenarios of the draw (on the episode's time grid).
        bank: the ``EpisodeBank`` every episode starts from (row = scenario index).
        agent_names: per scenario, the PettingZoo names of its controlled agents.
    """

    def __init__(
        self,
        scenarios: Any = None,
        batch_size: int = 1,
        *,
        controlled: ControlledSpec = "sdc",
        npc_policy: str | Policy = "log_replay",
        npc_kwargs: dict[str, Any] | None = None,
        device: str | torch.device = "cpu",
        config: EnvConfig | None = None,
        obs_config: ObsConfig | None = None,
        seed: int | None = None,
        route_points: int = 0,
        route_spacing: float = 5.0,
        obs_layout: str = "dense",
        compile: bool | str = False,
        torch_threads: int | None = 1,
    ) -> None:
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if route_points < 0 or route_spacing <= 0:
            raise ValueError("route_points must be >= 0 and route_spacing > 0")
        if obs_layout not in ("dense", "indexed"):
            raise ValueError(f"obs_layout must be 'dense' or 'indexed', got {obs_layout!r}")
        self.batch_size = int(batch_size)
        self.device = resolve_device(device)
        self.config = config or EnvConfig()
        self.obs_config = obs_config or ObsConfig()
        self.obs_layout = obs_layout
        self.route_points = int(route_points)
        self.route_spacing = float(route_spacing)
        self.torch_threads = torch_threads
        npc = make_npc_policy(npc_policy, npc_kwargs, self.device)
        sel = select_scenarios(scenarios, controlled, self.config, npc, drop_unusable=True)
        self.scenarios = sel.scenarios
        # A slot restarts alone into the batch's policy state, so the state's shapes must not
        # depend on which scenarios the slots hold: a policy that can fix them for the bank
        # (``for_scenarios``, e.g. a trimming TrafficBots policy) does so here.
        bind = getattr(npc, "for_scenarios", None)
        self.npc_policy = bind(self.scenarios) if callable(bind) else npc
        self.num_agents = max(len(q) for q in sel.queries)
        self._step_config = StepConfig(self.config, self.obs_config, dense=obs_layout == "dense")
        self._step_fn = StepFunction(
            self._step_config,
            compile,
            self.batch_size,
            self.device,
            self.batch_size * self.num_agents,
        )
        exact = bool(getattr(self.npc_policy, "exact_replay", False))
        with torch.no_grad():
            self.bank: EpisodeBank = ep.build_bank(
                self.scenarios, sel.queries, exact, self._step_config, self.device
            )
        self.agent_names: list[list[str]] = [
            [agent_name(sc.tracks.id[i]) for i in q] for sc, q in zip(self.scenarios, sel.queries)
        ]
        self._shapes = dict(observation_shapes(self.obs_config))
        if self.route_points:
            self._shapes[ROUTE_KEY] = (self.route_points, 2)
        setup = self.bank.setup
        types = self.bank.start.agents.object_type.gather(1, setup.query)
        max_acc, max_yaw = action_limits(types[setup.qmask])
        # The loosest limits over the controlled agents (actions are clipped per type).
        self.action_high = np.array([float(max_acc.max()), float(max_yaw.max())], np.float32)
        self.np_random, _ = gym.utils.seeding.np_random(seed)
        self._generator = torch.Generator(device="cpu")
        if seed is not None:
            self._generator.manual_seed(int(seed))
        self._pending_seed = seed
        self._episode: EpisodeState | None = None
        self._has_npc = False
        self._first_obs: dict[str, torch.Tensor] | None = None  # ``_first_observations``

    # ------------------------------------------------------------------ spaces
    @property
    def observation_shapes(self) -> dict[str, tuple[int, ...]]:
        """Per-agent shape of each observation key (the tensors are [B, Q, *shape])."""
        return dict(self._shapes)

    def single_observation_space(self) -> gym.spaces.Dict:
        """Gymnasium ``Dict`` space of one agent's observation (as ``TrafficEnv``'s)."""
        from tbsim_env.observation.tokens import observation_space

        space = dict(observation_space(self.obs_config).spaces)
        if self.route_points:
            space[ROUTE_KEY] = gym.spaces.Box(-np.inf, np.inf, (self.route_points, 2), np.float32)
        return gym.spaces.Dict(space)

    def single_action_space(self) -> gym.spaces.Box:
        """Box of one agent's action (the loosest type limits; actions are clipped per type)."""
        return gym.spaces.Box(-self.action_high, self.action_high, dtype=np.float32)

    # ------------------------------------------------------------------ state
    @property
    def episode(self) -> EpisodeState:
        """The current ``EpisodeState`` of the B slots (``step`` replaces it). Its tensors are
        the env's: restarting a slot writes the new episode's rows into them, so clone what
        must outlive a step (``rows.take_rows``)."""
        if self._episode is None:
            raise RuntimeError("call reset() first")
        return self._episode

    @property
    def agent_mask(self) -> torch.Tensor:
        """[B, Q] bool, agents active now (they need an action)."""
        return self.episode.alive

    @property
    def scenario_index(self) -> torch.Tensor:
        """[B] int64, index into ``scenarios`` of each slot's episode."""
        return self.episode.scenario

    @property
    def sim_state(self) -> SimState:
        """The current batched simulator state (B slots)."""
        return self.episode.sim

    @property
    def controlled_slots(self) -> torch.Tensor:
        """[B, Q] int64 agent slot in ``sim_state`` of each controlled agent."""
        return self.episode.setup.query

    @property
    def step_function(self) -> StepFunction:
        """The (eager or compiled) core step this env calls."""
        return self._step_fn

    # ------------------------------------------------------------------ reset
    def _draw(self, count: int) -> torch.Tensor:
        """Next ``count`` scenario indices from the seeded generator (one draw each)."""
        ks = [int(self.np_random.integers(len(self.scenarios))) for _ in range(count)]
        return torch.tensor(ks, dtype=torch.int64, device=self.device)

    def reset(
        self, seed: int | None = None, scenario_indices: Sequence[int] | None = None
    ) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        """Start new episodes in every slot.

        Args:
            seed: reseeds the scenario draws and the policy generator.
            scenario_indices: B scenario indices to start with (drawn when None).

        Returns:
            (observations dict of [B, Q, ...] float32, infos; see ``step``).
        """
        with torch_threads(self.torch_threads), torch.no_grad():
            return self._reset(seed, scenario_indices)

    def _reset(
        self, seed: int | None, scenario_indices: Sequence[int] | None
    ) -> tuple[dict[str, torch.Tensor], dict[str, Any]]:
        if seed is None and self._pending_seed is not None and self._episode is None:
            seed = self._pending_seed
        if seed is not None:
            self.np_random, _ = gym.utils.seeding.np_random(seed)
            self._generator.manual_seed(int(seed))
        b = self.batch_size
        if scenario_indices is None:
            ks = self._draw(b)
        else:
            if len(scenario_indices) != b:
                raise ValueError(f"scenario_indices needs {b} entries")
            ks = torch.as_tensor(list(scenario_indices), dtype=torch.int64, device=self.device)
            if bool(((ks < 0) | (ks >= len(self.scenarios))).any()):
                raise ValueError(f"scenario_indices outside [0, {len(self.scenarios)})")
        state, metrics = ep.start(self.bank, ks)
        # A stateless policy's state may be None: whether NPCs act is kept apart.
        self._has_npc = bool(state.setup.npc.any())
        policy_state = self._policy_start(state.sim, ks) if self._has_npc else None
        self._episode = dataclasses.replace(state, policy_state=policy_state)
        return self._observe(self._episode), self._infos(self._episode, metrics)

    def _policy_start(self, sim: SimState, ks: torch.Tensor) -> PolicyState:
        """The NPC policy's initial state for the rows of ``sim`` (scenarios ``ks``)."""
        return self.npc_policy.initial_state(
            sim, [self.scenarios[int(k)] for k in ks], self._generator
        )

    def _restart(
        self, state: EpisodeState, rows: torch.Tensor, observe: bool = True
    ) -> tuple[EpisodeState, dict[str, torch.Tensor] | None]:
        """(``state`` with new episodes in the slots ``rows`` [R], everything else untouched;
        the observation dict of the R new episodes, None unless ``observe``)."""
        ks = self._draw(len(rows))
        # Every slot at once (episodes of one length end together): the new episodes go into
        # the batch's own tensors (nothing handed out is a view of them: ``_package``).
        every = len(rows) == state.batch_size
        every = every and bool((rows == cached_arange(len(rows), rows.device)).all())
        if every:
            fresh, _ = ep.start(self.bank, ks, reuse=state)
            state = ep.merge_rows(state, rows, fresh, in_place=True)
            fresh_sim = fresh.sim
        else:
            # In place, from the bank's rows: a restart costs the restarted rows, not a copy
            # of every table of the batch.
            state = ep.reset_rows(self.bank, state, rows, ks, in_place=True)
            fresh, fresh_sim = None, None
        seen = state if fresh is None else fresh
        obs = self._first_observation(seen, rows, ks) if observe else None
        policy_state = state.policy_state
        if self._has_npc:
            if fresh_sim is None:
                fresh_sim = take_rows(self.bank.start, ks)
            started = self._policy_start(fresh_sim, ks)
            # Every slot restarted in order: the new state is the batch's (no row copies).
            in_place = bool(getattr(self.npc_policy, "owns_state", False))
            policy_state = (
                started if every else with_rows(policy_state, rows, started, False, in_place)
            )
        elif bool(self.bank.setup.npc[ks].any()):
            # No slot had NPCs so far: start the policy on the whole batch.
            self._has_npc = True
            policy_state = self._policy_start(state.sim, state.scenario)
        return dataclasses.replace(state, policy_state=policy_state), obs

    def _first_observation(
        self, state: EpisodeState, rows: torch.Tensor, ks: torch.Tensor
    ) -> dict[str, torch.Tensor]:
        """The observation dict of the new episodes (bank rows ``ks`` [R]) in the slots
        ``rows`` [R] of ``state`` (or, with R = B rows, ``state`` the new episodes alone):
        the rows of the bank's first observations (``_first_observations``), or observed
        anew where those are not kept."""
        first = self._first_observations()
        if first is not None:
            return {k: v.index_select(0, ks) for k, v in first.items()}
        if state.batch_size != len(rows):
            state = take_rows(dataclasses.replace(state, policy_state=None), rows)
        return self._observe(state)

    def _first_observations(self) -> dict[str, torch.Tensor] | None:
        """The observation dict of every bank row's first state, [S, ...] each, observed at
        the first restart (chunks of ``BANK_METRICS_CHUNK`` rows) and kept when it takes at
        most ``FIRST_OBS_BANK_MAX_BYTES`` (else None): an episode's first observation
        depends on its scenario alone, so a restart gathers it instead of observing."""
        if self._first_obs is None:
            s = self.bank.num_scenarios
            ks = torch.arange(s, device=self.device)
            one = self._observe(ep.start(self.bank, ks[:1])[0])
            size = sum(v.numel() * v.element_size() for v in one.values())
            if size * s > C.FIRST_OBS_BANK_MAX_BYTES:
                self._first_obs = {}
            else:
                parts = [
                    self._observe(ep.start(self.bank, ks[lo : lo + C.BANK_METRICS_CHUNK])[0])
                    for lo in range(0, s, C.BANK_METRICS_CHUNK)
                ]
                self._first_obs = {k: torch.cat([p[k] for p in parts]) for k in one}
        return self._first_obs or None

    def reset_slots(self, slots: Sequence[int] | torch.Tensor) -> dict[str, torch.Tensor]:
        """Start new episodes (drawn from the seeded generator) in some slots now, as the
        autoreset does for finished ones; the other slots go on.

        Args:
            slots: distinct slot indices in [0, B).

        Returns:
            The observation dict of every slot [B, Q, ...] (fresh in ``slots``).
        """
        rows = torch.as_tensor(list(slots) if not isinstance(slots, torch.Tensor) else slots)
        rows = rows.to(device=self.device, dtype=torch.int64)
        if rows.numel() == 0:
            raise ValueError("reset_slots needs at least one slot")
        outside = bool(((rows < 0) | (rows >= self.batch_size)).any())
        if outside or rows.unique().numel() != rows.numel():
            raise ValueError(
                f"slots must be distinct indices in [0, {self.batch_size}), got {rows.tolist()}"
            )
        with torch_threads(self.torch_threads), torch.no_grad():
            self._episode = self._restart(self.episode, rows, observe=False)[0]
            return self._observe(self.episode)

    # ------------------------------------------------------------------ step
    def _check_actions(self, actions: torch.Tensor) -> torch.Tensor:
        actions = torch.as_tensor(actions)
        shape = (self.batch_size, self.num_agents, 2)
        if tuple(actions.shape) != shape:
            raise ActionError(
                f"actions have shape {tuple(actions.shape)}; expected {shape} = "
                "[B, Q, (acceleration m/s^2, yaw rate rad/s)]"
            )
        actions = actions.to(self.device, torch.float32)
        bad = ~torch.isfinite(actions).all(-1) & self.agent_mask
        if bool(bad.any()):
            where = bad.nonzero().tolist()
            raise ActionError(f"actions of active agents [slot, agent] {where} are not finite")
        return actions

    def step(
        self, actions: torch.Tensor
    ) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        """Advance every slot by one step (0.1 s); finished slots restart at once.

        Args:
            actions: [B, Q, 2] (acceleration m/s^2, yaw rate rad/s); read only where
                ``agent_mask`` (others may hold anything, NaN included). NaN or infinite
                actions of active agents raise ``ActionError``; the rest are clipped to the
                agent type's limits.

        Returns:
            (obs, rewards, terminated, truncated, infos):

            * obs: dict of [B, Q, ...] float32; for a slot that finished this step, the first
              observation of its next episode (the last one is in ``infos["final_obs"]``).
            * rewards: [B, Q] float32, 0 for agents not active before the step.
            * terminated / truncated: [B, Q] bool, the agent's episode ended this step.
            * infos: ``agent_mask`` [B, Q] (agents active after the step and reset),
              ``active`` [B, Q] (agents that acted this step), per-agent metrics [B, Q]
              (``collision``, ``offroad``, ``offroad_distance``, ``goal_reached``,
              ``progress``, ``goal_distance``, ``log_divergence``, ``speed``),
              ``reward_terms`` ({term: [B, Q]} unweighted, see ``env.rewards``), ``done``
              [B] (slot restarted), ``episode_return`` [B, Q] and ``episode_length`` [B]
              (valid where ``done``), ``final_obs`` (dict like obs, valid where ``done``),
              ``scenario_index`` [B].
        """
        with torch_threads(self.torch_threads), torch.no_grad():
            return self._step(actions)

    def _step(
        self, actions: torch.Tensor
    ) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        """``step`` without the thread / grad context."""
        state = self.episode
        act = self._check_actions(actions)
        npc_action = None
        if self._has_npc:
            npc_action, policy_state = ep.npc_actions(self.npc_policy, state, self._generator)
            state = dataclasses.replace(state, policy_state=policy_state)
        state, out = self._step_fn(state, act, npc_action)
        obs = self._package(out.obs, out.active, state)
        infos = self._infos(state, out.metrics)
        infos.update(
            active=out.active,
            reward_terms=out.terms,
            done=out.done,
            episode_return=state.episode_return.clone(),
            episode_length=state.episode_length.clone(),
            final_obs=obs,
        )
        if bool(out.done.any()):
            rows = out.done.nonzero(as_tuple=True)[0]
            state, sub = self._restart(state, rows)
            obs = {k: v.index_copy(0, rows, sub[k]) for k, v in obs.items()}
        self._episode = state
        infos["agent_mask"] = state.alive.clone()
        return obs, out.reward, out.terminated, out.truncated, infos

    # ------------------------------------------------------------------ packaging
    def _observe(self, state: EpisodeState) -> dict[str, torch.Tensor]:
        """The observation dict of ``state``'s rows (their agents outside ``alive`` zero)."""
        return self._package(ep.observe_state(state, self._step_config), state.alive, state)

    def _package(
        self,
        obs: IndexedObservation | torch.Tensor,
        mask: torch.Tensor,
        state: EpisodeState,
    ) -> dict[str, torch.Tensor]:
        """The observation dict of ``obs_layout`` from the core's observation of ``state``,
        zero for observers outside ``mask`` [B, Q]. No tensor of it is the state's or a view
        of it (a restart may write into the state's tensors)."""
        m = mask.float()
        extra = {}
        if self.route_points:
            setup = state.setup
            pose = gather_rows(state.sim.pose, setup.query)
            route_xy = route_features(
                setup.route, state.progress, pose, self.route_points, self.route_spacing
            )
            extra[ROUTE_KEY] = route_xy * m[..., None, None]
        if isinstance(obs, IndexedObservation):
            return {
                "scene": state.scenario.clone(),
                "agent_tokens": obs.agent_tokens,
                # A view of the state's lights at B = 1 (read by number there).
                "light_tokens": obs.light_tokens.clone(),
                "ego": obs.ego.clone(),
                "index": obs.index,
                # The core saw ``mask`` (``observer_mask``): others see no token already.
                "pose": obs.pose,
                "mask": obs.mask,
                "observer_mask": m,
                **extra,
            }
        return {**self._dense_keys(obs * m.unsqueeze(-1)), **extra}

    def _dense_keys(self, rows: torch.Tensor) -> dict[str, torch.Tensor]:
        """The dense keys of rows [B, Q, D] (``episode.StepConfig.dense``): views."""
        cfg = self.obs_config
        sizes = (cfg.num_agents, cfg.num_map, cfg.num_traffic_lights)
        return dense_views(rows, sizes, cfg.tokens.piece_segments)

    def densify(self, obs: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """The dense layout of an ``obs_layout="indexed"`` observation (``step``'s, ``reset``'s
        or ``infos["final_obs"]``): [B, Q, ...] float32 per key, equal to what the dense
        layout returns for the same step.

        Map tokens are gathered from ``map_token_bank`` by ``obs["scene"]``, so a final
        observation refers to the map of the episode it ended.
        """
        if self.obs_layout != "indexed":
            raise ValueError("densify needs an observation of obs_layout='indexed'")
        obs_cfg = self.obs_config
        ind = IndexedObservation(
            agent_tokens=obs["agent_tokens"],
            map_tokens=self.map_token_bank,
            light_tokens=obs["light_tokens"],
            ego=obs["ego"],
            index=obs["index"],
            pose=obs["pose"],
            mask=obs["mask"],
            sizes=(obs_cfg.num_agents, obs_cfg.num_map, obs_cfg.num_traffic_lights),
            map_rows=obs["scene"],
        )
        m = obs["observer_mask"]
        o = self._dense_keys(densify_flat(ind, obs_cfg.tokens.piece_segments) * m.unsqueeze(-1))
        if ROUTE_KEY in obs:
            o[ROUTE_KEY] = obs[ROUTE_KEY]
        return o

    @property
    def map_token_bank(self) -> torch.Tensor:
        """[S, M, P * 4 + P + NUM_MAP_CLASSES] float32 map-piece tokens of every scenario of
        the env (row = ``obs["scene"]``), fixed for the env's life: what the ``"index"``
        entries of map pieces refer to in an indexed observation. Read-only."""
        return self.bank.setup.ctx.tokens.value

    def _infos(self, state: EpisodeState, metrics: StepMetrics) -> dict[str, Any]:
        # Tensors of the state are cloned: a caller writing into an info must not change it.
        infos = ep.agent_infos(state, metrics)
        infos["goal_reached"] = infos["goal_reached"].clone()
        infos["agent_mask"] = state.alive.clone()
        infos["scenario_index"] = state.scenario.clone()
        return infos

    @torch.no_grad()
    def expert_actions(self) -> torch.Tensor:
        """[B, Q, 2] actions that steer each controlled agent back onto its log next step.

        The batched counterpart of ``TrafficEnv.expert_actions`` (``episode.expert_actions``:
        zero where the log has no next state or the agent is not active).
        """
        return ep.expert_actions(self.episode)


__all__ = [
    "OBS_INDEXED_KEYS",
    "ROUTE_KEY",
    "BatchedTrafficEnv",
    "route_features",
]
