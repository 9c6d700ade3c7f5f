"""``TrafficEnv``: a PettingZoo ``ParallelEnv`` over real or generated driving scenarios.

The PettingZoo agents are the *externally controlled* agents (an RL learner, a planner, a
script), named ``track_<WOMD track id>``. Every other agent is an NPC driven by ``npc_policy``:
exact log replay, constant velocity, TrafficBots V1.5, or any ``policies.base.Policy``.

Actions are physical: ``np.float32[2]`` = (acceleration m/s^2, yaw rate rad/s). Actions outside
the agent type's limits (vehicle 5 m/s^2 / 1.5 rad/s, cyclist 6 / 3, pedestrian 7 / 7) are
clipped; NaN or infinite actions, unknown agent names and missing agents raise ``ActionError``.

An episode starts at the WOMD current step (10) with the logged history and ends at
``EnvConfig.last_step`` (90 by default, whatever the log's length): every remaining agent is
truncated then. An agent terminates (and leaves the scene for good) on the events
``EnvConfig.termination`` selects.

Scenes whose log ends before the episode does (WOSAC test-split scenes log only the 11 history
steps) run the whole episode: the NPC policy drives every NPC, whether its log goes on or not.
Rewards that compare with the log are masked where it has no state (``agent_metrics``).
Log-replayed NPCs (``npc_policy="log_replay"``) need the log up to the last step: the env
refuses such a scene with a ``MissingFutureError`` naming it.

The env is a shell over the episode core (``tbsim_env.env.episode``) at a batch of one: the
core holds every rule; this class turns agent dicts into tensors and back. It therefore equals
``BatchedTrafficEnv`` with ``batch_size=1`` bit for bit (tested over full episodes).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterator, Mapping
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.utils import EzPickle
from pettingzoo import ParallelEnv

from policies.base import Policy
from tbsim_env.core import constants as C
from tbsim_env.core.config import EnvConfig
from tbsim_env.core.errors import ActionError
from tbsim_env.core.torch_utils import torch_threads
from tbsim_env.data.scenario import Scenario
from tbsim_env.env import episode as ep
from tbsim_env.env.agent_metrics import StepMetrics
from tbsim_env.env.compiled import StepFunction
from tbsim_env.env.episode import EpisodeState, StepConfig, StepOutput
from tbsim_env.env.setup import (
    ControlledSpec,
    agent_name,
    controlled_indices,
    make_npc_policy,
    resolve_device,
    resolve_scenarios,
    select_scenarios,
)
from tbsim_env.observation.tokens import (
    MapContext,
    ObsConfig,
    build_map_context,
    dense_views,
    observation_space,
)
from tbsim_env.sim.state import SimState

AgentDict = dict[str, Any]


@dataclass(frozen=True)
class _Start:
    """The start of one scenario's episodes (they all start from the same state)."""

    state: EpisodeState
    names: list[str]
    obs: dict[str, dict[str, np.ndarray]]
    infos: dict[str, dict[str, Any]]


class _LazyObservations(Mapping):
    """{agent: observation} computed on first read (``TrafficEnv(lazy_observations=True)``)."""

    def __init__(
        self, names: list[str], observe: Callable[[list[str]], dict[str, dict[str, np.ndarray]]]
    ) -> None:
        self._names, self._observe = names, observe
        self._values: dict[str, dict[str, np.ndarray]] | None = None

    def __getitem__(self, name: str) -> dict[str, np.ndarray]:
        if name not in self._names:
            raise KeyError(name)
        if self._values is None:
            self._values = self._observe(self._names)
        return self._values[name]

    def __iter__(self) -> Iterator[str]:
        return iter(self._names)

    def __len__(self) -> int:
        return len(self._names)


class TrafficEnv(ParallelEnv, EzPickle):
    """Multi-agent driving on WOMD-style scenarios with NPCs driven by a policy.

    Args:
        scenarios: None for the embedded generated scenes, a TFRecord / GPUDrive JSON path,
            glob or folder, or a list of ``Scenario`` objects. ``self.scenarios`` holds them
            on the episode's time grid (``Scenario.on_time_grid``; the same objects for full
            WOMD scenes).
        controlled: which agents the caller controls: ``"sdc"`` (default),
            ``"tracks_to_predict"`` (those plus the SDC), ``"all"`` valid at the start, or a
            list of WOMD track ids. A scenario where it selects no agent valid at the start
            is refused (``UnusableScenarioError`` naming it and its file).
        npc_policy: ``"trafficbots"`` (default: the shipped pretrained TrafficBots V1.5, see
            docs/MODEL_CARD.md), ``"log_replay"`` (exact), ``"constant_velocity"``, or a policy
            object.
        config: episode, reward and termination settings.
        obs_config: observation sizes.
        render_mode: None or ``"rgb_array"``.
        device: torch device of the simulation.
        scenario_order: ``"cycle"`` through the scenarios in order on each reset, or
            ``"random"`` (drawn with the env's seeded generator).
        torch_threads: intra-op threads used inside ``reset`` / ``step`` (the caller's setting
            is restored afterwards); 1 is fastest for one scenario on CPU; None leaves torch's
            setting alone.
        npc_checkpoint: TrafficBots checkpoint for ``npc_policy="trafficbots"`` (default: the
            shipped weights).
        compile: run the core's step (all but the NPC policy) as one ``torch.compile`` graph:
            about three times the steps/s on the CPU after ~15 s of compiling on the first
            step; results equal the eager ones up to float rounding (``env.compiled``).
        lazy_observations: ``reset`` and ``step`` return the observations as a read-only
            mapping that computes them (the same values) when first read, and a scene's
            observation map context is built then; for loops that mostly read the simulator
            state instead (the planner benchmark's built-in planners): a step whose
            observations nobody reads skips their cost.

    Attributes:
        controlled_tracks: per scenario, the track indices of its controlled agents.
    """

    metadata = {
        "render_modes": ["rgb_array"],
        "name": "tbsim_traffic_v0",
        "is_parallelizable": True,
        "render_fps": 10,
    }

    def __init__(
        self,
        scenarios: Any = None,
        *,
        controlled: ControlledSpec = "sdc",
        npc_policy: str | Policy = "trafficbots",
        config: EnvConfig | None = None,
        obs_config: ObsConfig | None = None,
        render_mode: str | None = None,
        device: str | torch.device = "cpu",
        scenario_order: str = "cycle",
        torch_threads: int | None = 1,
        npc_checkpoint: str | None = None,
        compile: bool = False,
        lazy_observations: bool = False,
    ) -> None:
        EzPickle.__init__(
            self,
            scenarios,
            controlled=controlled,
            npc_policy=npc_policy,
            config=config,
            obs_config=obs_config,
            render_mode=render_mode,
            device=device,
            scenario_order=scenario_order,
            torch_threads=torch_threads,
            npc_checkpoint=npc_checkpoint,
            compile=compile,
            lazy_observations=lazy_observations,
        )
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode={render_mode!r}; supported: None, 'rgb_array'")
        if scenario_order not in ("cycle", "random"):
            raise ValueError("scenario_order must be 'cycle' or 'random'")
        self.config = config or EnvConfig()
        self.obs_config = obs_config or ObsConfig()
        self.render_mode = render_mode
        self.device = resolve_device(device)
        self.scenario_order = scenario_order
        self.torch_threads = torch_threads
        self.controlled_spec = controlled
        kwargs = {"checkpoint": npc_checkpoint} if npc_checkpoint else {}
        self.npc_policy = make_npc_policy(npc_policy, kwargs, self.device)
        sel = select_scenarios(scenarios, controlled, self.config, self.npc_policy, False)
        self.scenarios = sel.scenarios
        self.controlled_tracks: list[list[int]] = sel.queries
        self._lazy_obs = lazy_observations
        self._step_config = StepConfig(
            self.config, self.obs_config, dense=True, observe=not lazy_observations
        )
        self._step_fn = StepFunction(self._step_config, compile)
        self._act_spaces: dict[str, gym.spaces.Box] = {}
        for sc, idx in zip(self.scenarios, self.controlled_tracks):
            for i in idx:
                name = agent_name(sc.tracks.id[i])
                if name not in self._act_spaces:
                    t = int(sc.tracks.object_type[i])
                    hi = np.array([C.MAX_ACCEL[t], C.MAX_YAW_RATE[t]], np.float32)
                    self._act_spaces[name] = gym.spaces.Box(-hi, hi, dtype=np.float32)
        self.possible_agents = list(self._act_spaces)
        self._obs_space = observation_space(self.obs_config)
        self.agents: list[str] = []
        self._starts: dict[int, _Start] = {}
        self._contexts: dict[int, MapContext] = {}  # lazy_observations: built so far
        self._state: EpisodeState | None = None
        self._names: list[str] = []
        self._slot_of: dict[str, int] = {}
        self._has_npc = False
        self._episode = -1  # episodes started since the last seed (the "cycle" order)
        self.np_random, _ = gym.utils.seeding.np_random(None)
        self._generator = torch.Generator(device="cpu")
        self._scenario_index = 0
        self._renderer = None

    # ------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> gym.spaces.Dict:
        return self._obs_space

    def action_space(self, agent: str) -> gym.spaces.Box:
        if agent not in self._act_spaces:
            raise ActionError(f"unknown agent {agent!r}; possible agents: {self.possible_agents}")
        return self._act_spaces[agent]

    # ------------------------------------------------------------------ state
    @property
    def scenario(self) -> Scenario:
        """The scenario of the current episode."""
        return self.scenarios[self._scenario_index]

    @property
    def scenario_index(self) -> int:
        """Index into ``scenarios`` of the current episode's scenario."""
        return self._scenario_index

    @property
    def episode(self) -> EpisodeState:
        """The current ``EpisodeState`` (a batch of one; immutable, ``step`` replaces it)."""
        if self._state is None:
            raise RuntimeError("call reset() first")
        return self._state

    @property
    def sim_state(self) -> SimState:
        """The current batched simulator state (batch of one)."""
        return self.episode.sim

    @property
    def step_function(self) -> StepFunction:
        """The (eager or compiled) core step this env calls."""
        return self._step_fn

    @property
    def agent_columns(self) -> dict[str, int]:
        """Each agent's column in the controlled-agent tensors of the episode
        (``episode.setup.query``, ``episode.progress``): a copy, for this scenario."""
        return dict(self._slot_of)

    @property
    def episode_steps(self) -> int:
        """Steps of a full episode (from the start step to the last step)."""
        return self.config.last_step - self.config.start_step

    # ------------------------------------------------------------------ reset
    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[dict[str, dict[str, np.ndarray]], dict[str, dict]]:
        """Start an episode.

        Args:
            seed: reseeds the env's generators (scenario choice, stochastic policies).
            options: ``{"scenario_index": k}`` or ``{"scenario_id": s}`` picks the scenario.
        """
        with torch_threads(self.torch_threads), torch.inference_mode():
            return self._reset(seed, options)

    def _pick(self, options: dict) -> int:
        """The scenario index of the next episode."""
        if "scenario_index" in options:
            k = int(options["scenario_index"])
            if not 0 <= k < len(self.scenarios):
                raise ValueError(f"scenario_index {k} outside [0, {len(self.scenarios)})")
            return k
        if "scenario_id" in options:
            ids = [s.scenario_id for s in self.scenarios]
            if options["scenario_id"] not in ids:
                raise ValueError(f"unknown scenario_id {options['scenario_id']!r}")
            return ids.index(options["scenario_id"])
        if self.scenario_order == "random":
            return int(self.np_random.integers(len(self.scenarios)))
        return self._episode % len(self.scenarios)

    def _reset(
        self, seed: int | None, options: dict | None
    ) -> tuple[dict[str, dict[str, np.ndarray]], dict[str, dict]]:
        if seed is not None:
            self.np_random, _ = gym.utils.seeding.np_random(seed)
            self._generator.manual_seed(int(seed))
            self._episode = -1
        self._episode += 1
        k = self._pick(options or {})
        self._scenario_index = k
        if k not in self._starts:
            self._starts[k] = self._start(k)
        first = self._starts[k]
        state = first.state
        self._has_npc = bool(state.setup.npc.any())
        if self._has_npc:
            policy_state = self.npc_policy.initial_state(
                state.sim, [self.scenarios[k]], self._generator
            )
            state = dataclasses.replace(state, policy_state=policy_state)
        self._state = state
        self._names = first.names
        self._slot_of = {n: j for j, n in enumerate(first.names)}
        self.agents = list(first.names)
        # Every episode of scenario k starts from the same (immutable) state; the returned
        # arrays and dicts are copies.
        infos = {a: dict(info) for a, info in first.infos.items()}
        if self._lazy_obs:
            return _LazyObservations(list(first.names), self._observer(state, state.alive)), infos
        obs = {a: {key: v.copy() for key, v in o.items()} for a, o in first.obs.items()}
        return obs, infos

    def _start(self, k: int) -> _Start:
        """The first state, observations and infos of scenario ``k``'s episodes."""
        sc, query = self.scenarios[k], self.controlled_tracks[k]
        exact = bool(getattr(self.npc_policy, "exact_replay", False))
        # Lazy observations: the map context is built when an observation is first read.
        bank = ep.build_bank([sc], [query], exact, self._step_config, self.device)
        ks = torch.zeros(1, dtype=torch.int64, device=self.device)
        state, metrics = ep.start(bank, ks)
        names = [agent_name(sc.tracks.id[i]) for i in query]
        columns = self._info_columns(state, metrics, None)[0]
        infos = {a: {c: v[j] for c, v in columns.items()} for j, a in enumerate(names)}
        if self._lazy_obs:
            return _Start(state, names, {}, infos)
        obs = ep.observe_state(state, self._step_config)
        slot_of = {n: j for j, n in enumerate(names)}
        return _Start(state, names, self._per_agent(names, obs, slot_of), infos)

    # ------------------------------------------------------------------ step
    def _action_tensor(self, actions: dict[str, Any]) -> torch.Tensor:
        """[1, Q, 2] float32 actions of the controlled agents from the agent dict."""
        unknown = [a for a in actions if a not in self._slot_of or a not in self.agents]
        if unknown:
            raise ActionError(
                f"actions for agents that are not active: {unknown}; active agents: {self.agents}"
            )
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ActionError(f"no action for active agents {missing}")
        out = np.zeros((1, len(self._names), 2), np.float32)
        for name, act in actions.items():
            arr = np.asarray(act, dtype=np.float64)
            if arr.shape != (2,):
                raise ActionError(
                    f"action of {name!r} has shape {arr.shape}; expected (2,) = "
                    "(acceleration m/s^2, yaw rate rad/s)"
                )
            if not np.isfinite(arr).all():
                raise ActionError(f"action of {name!r} is not finite: {arr.tolist()}")
            out[0, self._slot_of[name]] = arr
        return torch.from_numpy(out).to(self.device)

    def step(self, actions: dict[str, Any]):
        """Advance one step (0.1 s). See the module docstring for the action format.

        Returns:
            (observations, rewards, terminations, truncations, infos), dicts by agent name
            of the agents alive before the step. An agent's info holds its metrics
            (``collision``, ``offroad``, ``offroad_distance``, ``progress``,
            ``goal_distance``, ``goal_reached``, ``log_divergence``, ``speed``), the
            ``scenario_id``, its ``track_id``, the ``step``, and ``reward_terms`` ({term:
            unweighted value} of every weighted reward term, ``env.rewards``).
        """
        with torch_threads(self.torch_threads), torch.inference_mode():
            return self._step(actions)

    def _step(self, actions: dict[str, Any]):
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        if not self.agents:
            raise RuntimeError("the episode is over: call reset()")
        act = self._action_tensor(actions)
        live_before = list(self.agents)
        state = self._state
        npc_action = None
        if self._has_npc:
            npc_action, policy_state = ep.npc_actions(self.npc_policy, state, self._generator)
            state = dataclasses.replace(state, policy_state=policy_state)
        state, out = self._step_fn(state, act, npc_action)
        self._state = state
        columns, reward_l, flags, values = self._info_columns(state, out.metrics, out)
        term_l, trunc_l = flags
        rewards, terms, truncs, infos = {}, {}, {}, {}
        names = list(out.terms)
        for name in live_before:
            j = self._slot_of[name]
            rewards[name] = reward_l[j]
            terms[name] = term_l[j]
            truncs[name] = trunc_l[j]
            infos[name] = {k: v[j] for k, v in columns.items()}
            infos[name]["reward_terms"] = {t: values[i][j] for i, t in enumerate(names)}
        if self._lazy_obs:
            obs = _LazyObservations(live_before, self._observer(state, out.active))
        else:
            obs = self._per_agent(live_before, out.obs, self._slot_of)
        self.agents = [a for a in live_before if not (terms[a] or truncs[a])]
        return obs, rewards, terms, truncs, infos

    # ------------------------------------------------------------------ helpers
    def _observer(
        self, state: EpisodeState, observers: torch.Tensor
    ) -> Callable[[list[str]], dict[str, dict[str, np.ndarray]]]:
        """A function observing ``state`` for the named agents (``lazy_observations``: the
        scenario's map context is built on the first call and kept)."""
        slot_of, k = dict(self._slot_of), self._scenario_index

        def observe(names: list[str]) -> dict[str, dict[str, np.ndarray]]:
            with torch_threads(self.torch_threads), torch.inference_mode():
                if k not in self._contexts:
                    scene, origin = [self.scenarios[k]], state.sim.origin
                    self._contexts[k] = build_map_context(scene, origin, self.obs_config)
                setup = dataclasses.replace(state.setup, ctx=self._contexts[k])
                seen = dataclasses.replace(state, setup=setup)
                rows = ep.observe_state(seen, self._step_config, observers)
            return self._per_agent(names, rows, slot_of)

        return observe

    def _per_agent(
        self, names: list[str], rows: torch.Tensor, slot_of: dict[str, int]
    ) -> dict[str, dict[str, np.ndarray]]:
        """Per-agent numpy views of the dense rows [1, Q, D] (``episode.StepConfig.dense``),
        for ``names``: one conversion of the batch, then numpy slicing."""
        flat = (rows if self.device.type == "cpu" else rows.cpu()).numpy()[0]
        cfg = self.obs_config
        sizes = (cfg.num_agents, cfg.num_map, cfg.num_traffic_lights)
        p = cfg.tokens.piece_segments
        return {n: dense_views(flat[slot_of[n]], sizes, p) for n in names}

    def _info_columns(
        self, state: EpisodeState, m: StepMetrics, out: StepOutput | None
    ) -> tuple[dict[str, list], list[float], tuple[list[bool], list[bool]], list[list[float]]]:
        """Per-agent info values as lists indexed like the controlled agents.

        Returns:
            (info columns, rewards, (terminations, truncations), reward terms) where the last
            three are those of ``out`` (empty without one). The values come from one
            concatenation and one ``tolist`` per dtype.
        """
        info = ep.agent_infos(state, m)
        float_keys = ("offroad_distance", "progress", "goal_distance", "log_divergence", "speed")
        flag_keys = ("collision", "offroad", "goal_reached")
        parts = [info[k] for k in float_keys + flag_keys]
        if out is not None:
            parts += [out.reward, out.terminated, out.truncated, *out.terms.values()]
        rows = _rows_by_dtype(parts)  # [part][agent]
        n_f, n_b, q = len(float_keys), len(flag_keys), info["speed"].shape[1]
        sc = self.scenario
        query = self.controlled_tracks[self._scenario_index]
        columns = {
            "scenario_id": [sc.scenario_id] * q,
            "track_id": [int(sc.tracks.id[i]) for i in query],
            "step": [int(state.sim.step)] * q,
            **dict(zip(flag_keys, rows[n_f : n_f + n_b])),
            **dict(zip(float_keys, rows[:n_f])),
        }
        if out is None:
            return columns, [], ([], []), []
        at = n_f + n_b
        terms = [[float(x) for x in row] for row in rows[at + 3 :]]
        return columns, rows[at], (rows[at + 1], rows[at + 2]), terms

    @torch.inference_mode()
    def expert_actions(self) -> dict[str, np.ndarray]:
        """Actions that steer each live agent from its current state back onto its log.

        One closed-loop inverse-dynamics step (``episode.expert_actions``) towards the logged
        state of the next step; zero where the log has no next state. Following them from the
        start reproduces the log within centimetres where the log is feasible.
        """
        act = ep.expert_actions(self.episode)[0].cpu().numpy().astype(np.float32)
        return {name: act[self._slot_of[name]] for name in self.agents}

    def render(self) -> np.ndarray | None:
        """Bird's-eye RGB frame of the current state (``render_mode="rgb_array"``)."""
        if self.render_mode is None:
            gym.logger.warn("render() called without render_mode; use render_mode='rgb_array'")
            return None
        from tbsim_env.rendering import AgentGroup, MapLayer, render_state, view_for

        if self._renderer is None or self._renderer[0] != self._scenario_index:
            layer = MapLayer.build(self.scenario, view_for(self.scenario, size=(600, 600)))
            self._renderer = (self._scenario_index, layer)
        state = self.episode
        groups = np.full(state.sim.num_agents, int(AgentGroup.LOG_REPLAY), np.int64)
        groups[state.setup.npc[0].cpu().numpy()] = int(AgentGroup.POLICY)
        groups[state.setup.external[0].cpu().numpy()] = int(AgentGroup.EXTERNAL)
        return render_state(self._renderer[1], state.sim, 0, groups)

    def close(self) -> None:
        self._renderer = None


def _rows_by_dtype(parts: list[torch.Tensor]) -> list[list]:
    """``[p[0].tolist() for p in parts]`` of [1, Q] tensors, with one concatenation and one
    ``tolist`` per dtype (a concatenation of mixed dtypes converts each input)."""
    groups: dict[torch.dtype, list[int]] = {}
    for i, p in enumerate(parts):
        groups.setdefault(p.dtype, []).append(i)
    rows: list[list] = [[] for _ in parts]
    for members in groups.values():
        for i, row in zip(members, torch.cat([parts[i] for i in members]).tolist()):
            rows[i] = row
    return rows


def episode_length(env: TrafficEnv) -> int:
    """Steps of a full episode of ``env`` (``TrafficEnv.episode_steps``)."""
    return int(math.floor(env.episode_steps))


__all__ = [
    "TrafficEnv",
    "agent_name",
    "controlled_indices",
    "episode_length",
    "resolve_scenarios",
]
