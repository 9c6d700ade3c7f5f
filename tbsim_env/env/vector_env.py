"""``BatchedTrafficEnv``: B scenarios stepped at once, torch tensors in and out, autoreset.

The training-side counterpart of ``TrafficEnv``: the same simulation core, observations,
metrics, rewards and terminations, but on a batch of B scenario *slots* with a fixed shape,
so a learner gets ``[B, Q, ...]`` tensors (Q = the most controlled agents any scenario has,
padded) without any per-agent Python dictionaries.

Design (why it is fast and still exact):

* **Scenario bank.** Every scenario is converted once at construction into one padded bank
  (``build_sim_state`` and ``build_map_context`` over all scenarios, routes, controlled slots,
  static agent features). The live batch is a row gather of the bank.
* **Autoreset by row copy.** A slot whose agents are all done is reset in the *same* step
  (same-step autoreset, as SB3 and Isaac-style vector envs do): the next scenario is drawn
  with the env's seeded generator, the bank rows are copied into the slot in place, and only
  that slot's history, metrics baseline and policy state are rebuilt on a sub-batch. No
  re-batching of the other B - 1 slots, no re-padding, no Python work per agent.
* Padding to the largest scenario does not change any result: padding agents are never
  valid, padding map pieces, lights and road edges are never valid (``TrafficEnv`` equality
  is tested on a full episode).

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
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch

from policies import make_policy
from policies.base import Policy, PolicyState
from tbsim_env.config import EnvConfig
from tbsim_env.data.scenario import Scenario
from tbsim_env.env.agent_metrics import Route, StepMetrics, build_route, goal_mask, step_metrics
from tbsim_env.env.fused import StepFunction, advance_and_observe_indexed
from tbsim_env.env.parallel_env import (
    ControlledSpec,
    agent_name,
    controlled_indices,
    resolve_scenarios,
)
from tbsim_env.env.transition import Controllers, npc_actions
from tbsim_env.errors import ActionError, UnusableScenarioError
from tbsim_env.observation import (
    History,
    IndexedObservation,
    ObsConfig,
    agent_static_features,
    build_map_context,
    densify,
    init_history,
    observation_shapes,
    observe_indexed,
)
from tbsim_env.sim.build import build_sim_state
from tbsim_env.sim.dynamics import action_limits, inverse_step
from tbsim_env.sim.geometry import to_local
from tbsim_env.sim.horizon import episode_scenario
from tbsim_env.sim.state import SimState
from tbsim_env.torch_utils import gather_rows, torch_threads

ROUTE_KEY = "route"
"""Optional extra observation key: upcoming points of the logged route in the ego frame."""

OBS_INDEXED_KEYS = {
    "scene": "[B] int64, the slot's scenario: its row of ``map_token_bank``",
    "agent_tokens": "[B, N, H * 5 + H + 7] float32, every agent slot this step: history in "
    "its own frame, history mask, attributes (length, width, type one-hot, speed)",
    "light_tokens": "[B, L, 5] float32, traffic-light state one-hot this step",
    "ego": "[B, Q] int64, each observer's agent slot (its row of agent_tokens)",
    "index": "[B, Q, Ka + Km + Kt] int64, the agent slots, map pieces and lights it sees",
    "pose": "[B, Q, Ka + Km + Kt, 3] float32, their (dx, dy, dyaw) in the observer's frame",
    "mask": "[B, Q, Ka + Km + Kt] float32, 1 where seen",
    "observer_mask": "[B, Q] float32, 1 for active observers (all else is zero for others)",
}
"""Keys of an ``obs_layout="indexed"`` observation (``observation.IndexedObservation``)."""


# ---------------------------------------------------------------------- row helpers
def take_rows(tree: Any, rows: torch.Tensor) -> Any:
    """Gather rows (leading batch dimension) of every tensor of a dataclass / dict / tuple tree.

    Args:
        tree: a tensor, None, or a (frozen) dataclass, dict, list or tuple of those.
        rows: [R] int64 row indices.

    Returns:
        The same structure with every tensor ``x`` replaced by ``x[rows]`` (a copy).
    """
    if tree is None:
        return None
    if isinstance(tree, torch.Tensor):
        return tree[rows]
    if dataclasses.is_dataclass(tree) and not isinstance(tree, type):
        return dataclasses.replace(
            tree,
            **{f.name: take_rows(getattr(tree, f.name), rows) for f in dataclasses.fields(tree)},
        )
    if isinstance(tree, dict):
        return {k: take_rows(v, rows) for k, v in tree.items()}
    if isinstance(tree, (list, tuple)):
        return type(tree)(take_rows(v, rows) for v in tree)
    raise TypeError(f"cannot take rows of {type(tree).__name__}; use tensors and dataclasses")


def put_rows(dst: Any, rows: torch.Tensor, src: Any, strict: bool = True) -> None:
    """In place: ``dst_tensor[rows] = src_tensor`` for every tensor of two matching trees.

    Args:
        dst: tree (tensor, dataclass, dict, list, tuple) whose tensors have a leading batch.
        rows: [R] int64 rows of ``dst`` to overwrite.
        src: the same structure with R rows.
        strict: raise on non-tensor leaves (other than None); when False they are kept as
            in ``dst`` (batch-wide metadata such as a policy's step counter).

    Raises:
        ValueError: a tensor's trailing shape differs between the trees.
        TypeError: the structures differ, or a non-tensor leaf with ``strict``.
    """
    if dst is None and src is None:
        return
    if isinstance(dst, torch.Tensor):
        if not isinstance(src, torch.Tensor) or dst.shape[1:] != src.shape[1:]:
            got = tuple(src.shape) if isinstance(src, torch.Tensor) else type(src).__name__
            raise ValueError(f"put_rows: {tuple(dst.shape)} rows cannot take {got}")
        dst[rows] = src.to(dst.dtype)
        return
    if dataclasses.is_dataclass(dst) and not isinstance(dst, type):
        if type(src) is not type(dst):
            raise TypeError(f"put_rows: {type(dst).__name__} vs {type(src).__name__}")
        for f in dataclasses.fields(dst):
            put_rows(getattr(dst, f.name), rows, getattr(src, f.name), strict)
        return
    if isinstance(dst, dict):
        for k in dst:
            put_rows(dst[k], rows, src[k], strict)
        return
    if isinstance(dst, (list, tuple)):
        for a, b in zip(dst, src, strict=True):
            put_rows(a, rows, b, strict)
        return
    if not strict and type(src) is type(dst):
        return
    raise TypeError(f"cannot put rows into {type(dst).__name__}; use tensors and dataclasses")


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
@dataclass(frozen=True)
class _Bank:
    """Per-scenario padded data every slot is reset from (leading dimension = scenario)."""

    state: SimState
    ctx: Any  # MapContext
    ext: torch.Tensor  # [S, Q] int64 agent slots (padding repeats the first)
    qmask: torch.Tensor  # [S, Q] bool, real controlled agent
    route: Route
    has_goal: torch.Tensor  # [S, Q] bool
    static: torch.Tensor  # [S, N, 6] agent static features
    external: torch.Tensor  # [S, N] bool
    npc: torch.Tensor  # [S, N] bool


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
        compile: run the step after the NPC actions (dynamics, metrics, rewards, history,
            observations) as one ``torch.compile`` graph; results equal the eager ones to
            float rounding. The first step compiles (tens of seconds, a C++ compiler on the
            CPU), and again once for another batch shape.
        torch_threads: intra-op threads inside ``reset`` / ``step`` (restored afterwards);
            1 (default) is fastest on a shared CPU (a step is many small tensor operations);
            None leaves torch's setting alone (e.g. on a GPU or large idle CPUs).

    Attributes:
        num_agents: Q, controlled-agent slots per scenario slot.
        agent_mask: [B, Q] bool, agents active now (they need an action).
        scenario_index: [B] int64, index into ``scenarios`` of each slot's episode.
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
        compile: bool = False,
        torch_threads: int | None = 1,
    ) -> None:
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        if route_points < 0 or route_spacing <= 0:
            raise ValueError("route_points must be >= 0 and route_spacing > 0")
        self.batch_size = int(batch_size)
        self.device = torch.device(device)
        self.config = config or EnvConfig()
        self.obs_config = obs_config or ObsConfig()
        kwargs = dict(npc_kwargs or {})
        if npc_policy == "trafficbots":
            # Runs on the token rows the scenario bank uses (fixed by ``for_scenarios`` below).
            kwargs.setdefault("device", str(self.device))
            kwargs.setdefault("trim", True)
        npc = make_policy(npc_policy, **kwargs)
        if obs_layout not in ("dense", "indexed"):
            raise ValueError(f"obs_layout must be 'dense' or 'indexed', got {obs_layout!r}")
        self.obs_layout = obs_layout
        self._step_fn = StepFunction(compile, advance_and_observe_indexed)
        self.route_points = int(route_points)
        self.route_spacing = float(route_spacing)
        self.torch_threads = torch_threads
        replays = bool(getattr(npc, "exact_replay", False))
        all_scenarios = [
            episode_scenario(sc, self.config, replays_log=replays)
            for sc in resolve_scenarios(scenarios)
        ]
        start = self.config.start_step
        kept, ext_lists = [], []
        for sc in all_scenarios:
            idx = controlled_indices(sc, controlled, start)
            if idx:
                kept.append(sc)
                ext_lists.append(idx)
        if not kept:
            names = ", ".join(f"{sc.scenario_id} ({sc.source})" for sc in all_scenarios[:3])
            more = f" and {len(all_scenarios) - 3} more" if len(all_scenarios) > 3 else ""
            raise UnusableScenarioError(
                f"controlled={controlled!r} selects no agent valid at the start step {start} "
                f"in any of the scenarios: {names}{more}"
            )
        self.scenarios: list[Scenario] = kept
        # A slot restarts alone into the batch's policy state, so the state's shapes must not
        # depend on which scenarios the slots hold: a policy that can fix them for the bank
        # (``for_scenarios``, e.g. a trimming TrafficBots policy) does so here.
        bind = getattr(npc, "for_scenarios", None)
        self.npc_policy = bind(kept) if callable(bind) else npc
        self.num_agents = max(len(x) for x in ext_lists)
        self._end = self.config.last_step
        with torch.no_grad():
            self._bank = self._build_bank(ext_lists)
        self.agent_names: list[list[str]] = [
            [agent_name(sc.tracks.id[i]) for i in ext] for sc, ext in zip(kept, ext_lists)
        ]
        self._shapes = dict(observation_shapes(self.obs_config))
        if self.route_points:
            self._shapes[ROUTE_KEY] = (self.route_points, 2)
        types = self._bank.state.agents.object_type[
            torch.arange(len(kept), device=self.device)[:, None], self._bank.ext
        ]
        max_acc, max_yaw = action_limits(types[self._bank.qmask])
        self.action_high = np.array(
            [float(max_acc.max()), float(max_yaw.max())], np.float32
        )  # loosest limits over the controlled agents (actions are clipped per type)
        self.np_random, _ = gym.utils.seeding.np_random(seed)
        self._generator = torch.Generator(device="cpu")
        if seed is not None:
            self._generator.manual_seed(int(seed))
        self._pending_seed = seed
        self._ready = False

    # ------------------------------------------------------------------ construction
    def _build_bank(self, ext_lists: list[list[int]]) -> _Bank:
        start, dev = self.config.start_step, self.device
        state = build_sim_state(self.scenarios, start_step=start, device=dev)
        ctx = build_map_context(self.scenarios, state.origin, self.obs_config)
        s, q = len(self.scenarios), self.num_agents
        ext = torch.zeros((s, q), dtype=torch.int64)
        qmask = torch.zeros((s, q), dtype=torch.bool)
        for i, idx in enumerate(ext_lists):
            ext[i, : len(idx)] = torch.tensor(idx)
            ext[i, len(idx) :] = idx[0]
            qmask[i, : len(idx)] = True
        ext, qmask = ext.to(dev), qmask.to(dev)
        rows = torch.arange(s, device=dev)[:, None]
        external = torch.zeros_like(state.valid)
        external[rows, ext] = True
        exact = getattr(self.npc_policy, "exact_replay", False)
        npc = torch.zeros_like(external) if exact else state.agents.mask & ~external
        state = state.replace(controlled=external | npc)
        route = build_route(state, ext)
        has_goal = goal_mask(route, start, self.config.reward.goal_radius)
        return _Bank(
            state=state,
            ctx=ctx,
            ext=ext,
            qmask=qmask,
            route=route,
            has_goal=has_goal,
            static=agent_static_features(state),
            external=external,
            npc=npc,
        )

    # ------------------------------------------------------------------ spaces
    @property
    def observation_shapes(self) -> dict[str, tuple[int, ...]]:
        """Per-agent shape of each observation key (the tensors are [B, Q, *shape])."""
        return dict(self._shapes)

    def single_observation_space(self) -> gym.spaces.Dict:
        """Gymnasium ``Dict`` space of one agent's observation (as ``TrafficEnv``'s)."""
        from tbsim_env.observation import observation_space

        space = dict(observation_space(self.obs_config).spaces)
        if self.route_points:
            space[ROUTE_KEY] = gym.spaces.Box(-np.inf, np.inf, (self.route_points, 2), np.float32)
        return gym.spaces.Dict(space)

    def single_action_space(self) -> gym.spaces.Box:
        """Box of one agent's action (the loosest type limits; actions are clipped per type)."""
        return gym.spaces.Box(-self.action_high, self.action_high, dtype=np.float32)

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
        if seed is None and self._pending_seed is not None and not self._ready:
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
        bank = self._bank
        self.scenario_index = ks.clone()
        self._state: SimState = take_rows(bank.state, ks)
        self._ctx = take_rows(bank.ctx, ks)
        self._ext = bank.ext[ks].clone()
        self._qmask = bank.qmask[ks].clone()
        self._route: Route = take_rows(bank.route, ks)
        self._has_goal = bank.has_goal[ks].clone()
        self._static = bank.static[ks].clone()
        npc = bank.npc[ks].clone()
        # Restarting slots update external / npc in place; has_npc only ever turns on.
        self._ctrl = Controllers(
            external=bank.external[ks].clone(),
            npc=npc,
            policy=self.npc_policy,
            has_npc=bool(npc.any()),
        )
        self._policy_state: PolicyState = (
            self.npc_policy.initial_state(
                self._state, [self.scenarios[int(k)] for k in ks], self._generator
            )
            if self._ctrl.has_npc
            else None
        )
        self._history: History = init_history(self._state, self.obs_config.history)
        metrics = step_metrics(self._state, self._ext, self._route)
        self._progress = metrics.progress.clone()
        self._goal_reached = torch.zeros_like(self._qmask)
        self.agent_mask = self._qmask.clone()
        self._ep_return = torch.zeros(self._qmask.shape, device=self.device)
        self._ep_length = torch.zeros(b, dtype=torch.int64, device=self.device)
        self._ready = True
        obs = self._observe()
        return obs, self._infos(metrics)

    def _reset_rows(self, rows: torch.Tensor) -> None:
        """Start new episodes in the slots ``rows`` [R] (everything else untouched)."""
        bank = self._bank
        ks = self._draw(len(rows))
        self.scenario_index[rows] = ks
        put_rows(self._state, rows, take_rows(bank.state, ks))
        # core.step / put_rows keep the dynamic fields as separate tensors of the batch.
        put_rows(self._ctx, rows, take_rows(bank.ctx, ks))
        self._ext[rows] = bank.ext[ks]
        self._qmask[rows] = bank.qmask[ks]
        put_rows(self._route, rows, take_rows(bank.route, ks))
        self._has_goal[rows] = bank.has_goal[ks]
        self._static[rows] = bank.static[ks]
        self._ctrl.external[rows] = bank.external[ks]
        self._ctrl.npc[rows] = bank.npc[ks]
        sub = take_rows(self._state, rows)
        if self._ctrl.has_npc or bool(bank.npc[ks].any()):
            if not self._ctrl.has_npc:
                # No slot had NPCs so far: start the policy on the whole batch.
                self._ctrl = dataclasses.replace(self._ctrl, has_npc=True)
                self._policy_state = self.npc_policy.initial_state(
                    self._state,
                    [self.scenarios[int(k)] for k in self.scenario_index],
                    self._generator,
                )
            else:
                fresh = self.npc_policy.initial_state(
                    sub, [self.scenarios[int(k)] for k in ks], self._generator
                )
                put_rows(self._policy_state, rows, fresh, strict=False)
        put_rows(self._history, rows, init_history(sub, self.obs_config.history))
        sub_route = take_rows(self._route, rows)
        metrics = step_metrics(sub, self._ext[rows], sub_route)
        self._progress[rows] = metrics.progress
        self._goal_reached[rows] = False
        self.agent_mask[rows] = self._qmask[rows]
        self._ep_return[rows] = 0.0
        self._ep_length[rows] = 0

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
              (``collision``, ``offroad``, ``goal_reached``, ``progress``,
              ``log_divergence``, ``goal_distance``), ``done`` [B] (slot restarted),
              ``episode_return`` [B, Q] and ``episode_length`` [B] (valid where ``done``),
              ``final_obs`` (dict like obs, valid where ``done``), ``scenario_index`` [B].
        """
        with torch_threads(self.torch_threads), torch.no_grad():
            return self._step(actions)

    def _step(
        self, actions: torch.Tensor
    ) -> tuple[dict[str, torch.Tensor], torch.Tensor, torch.Tensor, torch.Tensor, dict[str, Any]]:
        """``step`` without the thread / grad context."""
        if not self._ready:
            raise RuntimeError("call reset() before step()")
        act = self._check_actions(actions)
        active = self.agent_mask.clone()
        ext_action = torch.zeros(*self._state.pose.shape[:2], 2, device=self.device)
        bi, qi = active.nonzero(as_tuple=True)
        ext_action[bi, self._ext[bi, qi]] = act[bi, qi]
        action, self._policy_state = npc_actions(
            self._state, ext_action, self._ctrl, self._policy_state, self._generator
        )
        fused = self._step_fn(
            self._state,
            action,
            self._ext,
            self._route,
            self._progress,
            self._goal_reached,
            self._has_goal,
            self.config,
            self._history,
            self._ctx,
            self.obs_config,
            self._static,
            active,
        )
        tr = fused.transition
        state, out = tr.state, tr.outcome
        self._progress = out.progress_best
        self._goal_reached = tr.goal_reached
        reward = out.reward * active
        term = out.terminated & active
        trunc_slot = state.step >= self._end  # [B]
        trunc = active & trunc_slot[:, None] & ~term
        self._state = state
        self._history = fused.history
        self.agent_mask = active & ~term & ~trunc
        self._ep_return += reward
        self._ep_length += 1
        obs = self._package(fused.obs, active, state, self._ext, self._route, self._progress)
        if self.obs_layout == "indexed":
            obs["scene"] = self.scenario_index.clone()
        done = ~self.agent_mask.any(-1)  # [B]
        infos = self._infos(tr.metrics)
        infos["active"] = active
        infos["done"] = done
        infos["episode_return"] = self._ep_return.clone()
        infos["episode_length"] = self._ep_length.clone()
        infos["final_obs"] = obs
        if bool(done.any()):
            rows = done.nonzero(as_tuple=True)[0]
            obs = {k: v.clone() for k, v in obs.items()}
            self._reset_rows(rows)
            sub = self._observe(rows)
            for k in obs:
                obs[k][rows] = sub[k]
        infos["agent_mask"] = self.agent_mask.clone()
        return obs, reward, term, trunc, infos

    # ------------------------------------------------------------------ helpers
    def _observe(
        self, rows: torch.Tensor | None = None, mask: torch.Tensor | None = None
    ) -> dict[str, torch.Tensor]:
        """Observations [B or R, Q, ...] of the controlled agents.

        Args:
            rows: [R] slots to observe (all when None).
            mask: [B, Q] agents whose observation is kept (others are zero);
                ``agent_mask`` by default. Only with ``rows=None``.
        """
        if rows is None:
            state, hist, ctx, ext = self._state, self._history, self._ctx, self._ext
            static, route = self._static, self._route
            mask = self.agent_mask if mask is None else mask
            progress, scene = self._progress, self.scenario_index
        else:
            state, hist = take_rows(self._state, rows), take_rows(self._history, rows)
            ctx, ext = take_rows(self._ctx, rows), self._ext[rows]
            static, mask = self._static[rows], self.agent_mask[rows]
            route, progress = take_rows(self._route, rows), self._progress[rows]
            scene = self.scenario_index[rows]
        ind = observe_indexed(state, hist, ctx, ext, self.obs_config, agent_static=static)
        obs = self._package(ind, mask, state, ext, route, progress)
        if self.obs_layout == "indexed":
            obs["scene"] = scene.clone()
        return obs

    def _package(
        self,
        ind: IndexedObservation,
        mask: torch.Tensor,
        state: SimState,
        ext: torch.Tensor,
        route: Route,
        progress: torch.Tensor,
    ) -> dict[str, torch.Tensor]:
        """The observation dict of ``obs_layout`` from ``observe_indexed``'s result, zero for
        observers outside ``mask`` [B, Q] (an indexed one's ``"scene"`` is the caller's)."""
        m = mask.float()
        extra = {}
        if self.route_points:
            pose = gather_rows(state.pose, ext)
            route_xy = route_features(route, progress, pose, self.route_points, self.route_spacing)
            extra[ROUTE_KEY] = route_xy * m[..., None, None]
        if self.obs_layout == "indexed":
            return {
                "agent_tokens": ind.agent_tokens,
                "light_tokens": ind.light_tokens,
                "ego": ind.ego.clone(),
                "index": ind.index,
                "pose": ind.pose * m[..., None, None],
                "mask": ind.mask * m[..., None],
                "observer_mask": m,
                **extra,
            }
        o = densify(ind, self.obs_config.tokens.piece_segments)
        o = {k: v * m.view(*m.shape, *([1] * (v.dim() - 2))) for k, v in o.items()}
        return {**o, **extra}

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
            map_tokens=self.map_token_bank[obs["scene"]],
            light_tokens=obs["light_tokens"],
            ego=obs["ego"],
            index=obs["index"],
            pose=obs["pose"],
            mask=obs["mask"],
            sizes=(obs_cfg.num_agents, obs_cfg.num_map, obs_cfg.num_traffic_lights),
        )
        m = obs["observer_mask"]
        o = densify(ind, obs_cfg.tokens.piece_segments)
        o = {k: v * m.view(*m.shape, *([1] * (v.dim() - 2))) for k, v in o.items()}
        if ROUTE_KEY in obs:
            o[ROUTE_KEY] = obs[ROUTE_KEY]
        return o

    @property
    def map_token_bank(self) -> torch.Tensor:
        """[S, M, P * 4 + P + NUM_MAP_CLASSES] float32 map-piece tokens of every scenario of
        the env (row = ``obs["scene"]``), fixed for the env's life: what the ``"index"``
        entries of map pieces refer to in an indexed observation. Read-only."""
        return self._bank.ctx.tokens[..., :-3]

    def _infos(self, m: StepMetrics) -> dict[str, Any]:
        return {
            "agent_mask": self.agent_mask.clone(),
            "collision": m.collision,
            "offroad": m.offroad,
            "offroad_distance": m.offroad_distance,
            "progress": m.progress,
            "goal_distance": m.goal_distance,
            "goal_reached": self._goal_reached.clone(),
            "log_divergence": m.log_divergence,
            "scenario_index": self.scenario_index.clone(),
        }

    @property
    def sim_state(self) -> SimState:
        """The current batched simulator state (B slots)."""
        if not self._ready:
            raise RuntimeError("call reset() first")
        return self._state

    @property
    def controlled_slots(self) -> torch.Tensor:
        """[B, Q] int64 agent slot in ``sim_state`` of each controlled agent."""
        return self._ext

    @torch.no_grad()
    def expert_actions(self) -> torch.Tensor:
        """[B, Q, 2] actions that steer each controlled agent back onto its log next step.

        The batched counterpart of ``TrafficEnv.expert_actions`` (zero where the log has no
        next state or the agent is not active).
        """
        s = self.sim_state
        n_t = s.log.valid.shape[-1]
        t1 = (s.step + 1).clamp(max=n_t - 1)[:, None].expand_as(self._ext)
        b_idx = torch.arange(self.batch_size, device=self.device)[:, None]
        slots = self._ext
        max_acc, max_yaw = action_limits(s.agents.object_type[b_idx, slots])
        act = inverse_step(
            s.pose[b_idx, slots],
            s.speed[b_idx, slots],
            s.log.pose[b_idx, slots, t1],
            s.log.speed[b_idx, slots, t1],
            max_acc,
            max_yaw,
        )
        keep = s.log.valid[b_idx, slots, t1] & self.agent_mask
        return act * keep[..., None]


__all__ = [
    "OBS_INDEXED_KEYS",
    "ROUTE_KEY",
    "BatchedTrafficEnv",
    "put_rows",
    "route_features",
    "take_rows",
]
