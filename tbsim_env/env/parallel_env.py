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
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.utils import EzPickle
from pettingzoo import ParallelEnv

from policies import make_policy
from policies.base import Policy
from tbsim_env import constants as C
from tbsim_env.config import EnvConfig
from tbsim_env.data.scenario import Scenario
from tbsim_env.env.agent_metrics import Route, StepMetrics, build_route, goal_mask, step_metrics
from tbsim_env.env.fused import StepFunction
from tbsim_env.env.rewards import RewardOutcome
from tbsim_env.env.transition import Controllers, npc_actions
from tbsim_env.errors import ActionError, UnusableScenarioError
from tbsim_env.observation import (
    History,
    MapContext,
    ObsConfig,
    agent_static_features,
    build_map_context,
    init_history,
    observation_space,
    observe,
)
from tbsim_env.sim.build import build_sim_state
from tbsim_env.sim.dynamics import action_limits, inverse_step
from tbsim_env.sim.horizon import episode_scenario
from tbsim_env.sim.state import SimState
from tbsim_env.torch_utils import torch_threads

ControlledSpec = str | Sequence[int]


def agent_name(track_id: int) -> str:
    """PettingZoo name of the agent with WOMD track id ``track_id``."""
    return f"track_{int(track_id)}"


def resolve_scenarios(scenarios: Any) -> list[Scenario]:
    """Scenarios from None (embedded default), a path / glob / folder, or a list of either.

    ``Scenario`` objects given directly are validated like the ones a reader returns
    (``Scenario.validate``: shapes, references, plausibility bounds).

    Raises:
        ScenarioFormatError: a file or a given ``Scenario`` is malformed or implausible.
    """
    if scenarios is None:
        from tbsim_env.data.generator import default_scenarios

        return list(default_scenarios())
    if isinstance(scenarios, Scenario):
        return [scenarios.validate()]
    from tbsim_env.data import load_scenarios

    if isinstance(scenarios, (str, os.PathLike)):
        out = load_scenarios(scenarios)
    else:
        items = list(scenarios)
        if all(isinstance(s, Scenario) for s in items):
            out = [s.validate() for s in items]
        else:
            out = load_scenarios(items)
    if not out:
        raise ValueError(f"no scenarios found in {scenarios!r}")
    return out


def controlled_indices(scenario: Scenario, controlled: ControlledSpec, start: int) -> list[int]:
    """Track indices of the externally controlled agents (all must be valid at ``start``).

    Args:
        scenario: the scenario.
        controlled: ``"sdc"``, ``"tracks_to_predict"``, ``"all"``, ``"none"``, or track ids.
        start: the first simulated step.
    """
    valid = scenario.tracks.valid[:, start]
    if isinstance(controlled, str):
        if controlled == "sdc":
            idx = [scenario.sdc_index]
        elif controlled == "tracks_to_predict":
            idx = sorted(set(int(i) for i in scenario.tracks_to_predict) | {scenario.sdc_index})
        elif controlled == "all":
            idx = [int(i) for i in np.flatnonzero(valid)]
        elif controlled == "none":
            idx = []
        else:
            raise ValueError(
                f"controlled={controlled!r}; use 'sdc', 'tracks_to_predict', 'all', 'none' "
                "or a list of track ids"
            )
        return [i for i in idx if valid[i]]
    ids = {int(t): k for k, t in enumerate(scenario.tracks.id)}
    out = []
    for tid in controlled:
        if int(tid) not in ids:
            raise UnusableScenarioError(
                f"no track with id {tid} (controlled={list(controlled)!r})",
                scenario.scenario_id,
                scenario.source,
            )
        if not valid[ids[int(tid)]]:
            raise UnusableScenarioError(
                f"track {tid} is not valid at step {start}, so it cannot be controlled from "
                "the start",
                scenario.scenario_id,
                scenario.source,
            )
        out.append(ids[int(tid)])
    return out


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
        compile: run the step (all but the NPC policy) as one ``torch.compile`` graph: about
            twice the steps/s on the CPU after ~15 s of compiling on the first step; results
            equal the eager ones up to float rounding (``tbsim_env.env.fused``).
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
        )
        if render_mode not in (None, "rgb_array"):
            raise ValueError(f"render_mode={render_mode!r}; supported: None, 'rgb_array'")
        if scenario_order not in ("cycle", "random"):
            raise ValueError("scenario_order must be 'cycle' or 'random'")
        self.config = config or EnvConfig()
        self.obs_config = obs_config or ObsConfig()
        self.render_mode = render_mode
        self.device = torch.device(device)
        self.scenario_order = scenario_order
        self.torch_threads = torch_threads
        self._step_fn = StepFunction(compile)
        self.controlled_spec = controlled
        kwargs = {"checkpoint": npc_checkpoint} if npc_checkpoint else {}
        if npc_policy == "trafficbots":
            # Every reset starts the whole batch, so the policy may run on the used tokens.
            kwargs.update(device=str(self.device), trim=True)
        self.npc_policy = make_policy(npc_policy, **kwargs)
        replays = bool(getattr(self.npc_policy, "exact_replay", False))
        self.scenarios = [
            episode_scenario(sc, self.config, replays_log=replays)
            for sc in resolve_scenarios(scenarios)
        ]
        start = self.config.start_step
        self._controlled: list[list[int]] = []
        names: dict[str, None] = {}
        for sc in self.scenarios:
            idx = controlled_indices(sc, controlled, start)
            if not idx and controlled != "none":
                raise UnusableScenarioError(
                    f"controlled={controlled!r} selects no agent valid at the start step {start}",
                    sc.scenario_id,
                    sc.source,
                )
            self._controlled.append(idx)
            for i in idx:
                names[agent_name(sc.tracks.id[i])] = None
        self.possible_agents = list(names)
        self._obs_space = observation_space(self.obs_config)
        self._act_spaces: dict[str, gym.spaces.Box] = {}
        for sc, idx in zip(self.scenarios, self._controlled):
            for i in idx:
                name = agent_name(sc.tracks.id[i])
                if name not in self._act_spaces:
                    t = int(sc.tracks.object_type[i])
                    hi = np.array([C.MAX_ACCEL[t], C.MAX_YAW_RATE[t]], np.float32)
                    self._act_spaces[name] = gym.spaces.Box(-hi, hi, dtype=np.float32)
        self.agents: list[str] = []
        self._cache: dict[int, tuple[SimState, MapContext]] = {}
        self._route_cache: dict[int, Route] = {}
        self._start_cache: dict[int, tuple] = {}
        self._episode = -1
        self.np_random, _ = gym.utils.seeding.np_random(None)
        self._generator = torch.Generator(device="cpu")
        self._scenario_index = 0
        self.state_: SimState | None = None
        self._renderer = None

    # ------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> gym.spaces.Dict:
        return self._obs_space

    def action_space(self, agent: str) -> gym.spaces.Box:
        if agent not in self._act_spaces:
            raise ActionError(f"unknown agent {agent!r}; possible agents: {self.possible_agents}")
        return self._act_spaces[agent]

    # ------------------------------------------------------------------ reset
    @property
    def scenario(self) -> Scenario:
        """The scenario of the current episode."""
        return self.scenarios[self._scenario_index]

    @property
    def sim_state(self) -> SimState:
        """The current batched simulator state (batch of one)."""
        if self.state_ is None:
            raise RuntimeError("call reset() first")
        return self.state_

    def _initial(self, k: int) -> tuple[SimState, MapContext]:
        if k not in self._cache:
            sc = self.scenarios[k]
            state = build_sim_state([sc], start_step=self.config.start_step, device=self.device)
            ctx = build_map_context([sc], state.origin, self.obs_config)
            self._cache[k] = (state, ctx)
        return self._cache[k]

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

    def _reset(
        self, seed: int | None, options: dict | None
    ) -> tuple[dict[str, dict[str, np.ndarray]], dict[str, dict]]:
        if seed is not None:
            self.np_random, _ = gym.utils.seeding.np_random(seed)
            self._generator.manual_seed(int(seed))
            self._episode = -1
        self._episode += 1
        options = options or {}
        if "scenario_index" in options:
            k = int(options["scenario_index"])
            if not 0 <= k < len(self.scenarios):
                raise ValueError(f"scenario_index {k} outside [0, {len(self.scenarios)})")
        elif "scenario_id" in options:
            ids = [s.scenario_id for s in self.scenarios]
            if options["scenario_id"] not in ids:
                raise ValueError(f"unknown scenario_id {options['scenario_id']!r}")
            k = ids.index(options["scenario_id"])
        elif self.scenario_order == "random":
            k = int(self.np_random.integers(len(self.scenarios)))
        else:
            k = self._episode % len(self.scenarios)
        self._scenario_index = k
        sc = self.scenarios[k]
        state, self._ctx = self._initial(k)
        ext = self._controlled[k]
        self._ext_slots = torch.tensor([ext], dtype=torch.int64, device=self.device)
        self._ext_index = self._ext_slots[0]
        self._ext_names = [agent_name(sc.tracks.id[i]) for i in ext]
        self._slot_of = {n: j for j, n in enumerate(self._ext_names)}
        external = torch.zeros_like(state.controlled)
        external[0, ext] = True
        exact = getattr(self.npc_policy, "exact_replay", False)
        npc = torch.zeros_like(external) if exact else state.agents.mask & ~external
        self.state_ = state.replace(controlled=external | npc)
        self._ctrl = Controllers(
            external=external, npc=npc, policy=self.npc_policy, has_npc=bool(npc.any())
        )
        self._policy_state = (
            self.npc_policy.initial_state(self.state_, [sc], self._generator)
            if self._ctrl.has_npc
            else None
        )
        if k not in self._route_cache:
            self._route_cache[k] = build_route(self.state_, self._ext_slots)
        self._route = self._route_cache[k]
        self._end = self.config.last_step
        self.agents = list(self._ext_names)
        self._action_rows = {n: int(ext[j]) for n, j in self._slot_of.items()}
        self._track_ids = [int(sc.tracks.id[i]) for i in ext]
        # [1, Q] like the metrics (the batch of one is kept until the per-agent dicts).
        self._goal_reached = torch.zeros_like(self._ext_slots, dtype=torch.bool)
        # Agents whose log ends at the start or whose logged route is shorter than the goal
        # radius have no goal to reach.
        self._has_goal = goal_mask(
            self._route, self.config.start_step, self.config.reward.goal_radius
        )
        # Every episode of scenario k starts from the same state, so what follows from it
        # alone is computed once (the returned arrays and dicts are copies).
        if k not in self._start_cache:
            self._start_cache[k] = self._start(k)
        history, static, progress, obs, infos = self._start_cache[k]
        self._history: History = history
        self._agent_static = static
        self._progress = progress.clone()
        obs = {a: {key: v.copy() for key, v in o.items()} for a, o in obs.items()}
        return obs, {a: dict(info) for a, info in infos.items()}

    def _start(self, k: int) -> tuple:
        """History, static features, progress, observations and infos of the
        first state of scenario ``k`` (set up by ``_reset``)."""
        self._history = init_history(self.state_, self.obs_config.history)
        self._agent_static = agent_static_features(self.state_)
        metrics = step_metrics(self.state_, self._ext_slots, self._route)
        obs = self._observations(self.agents, metrics.agent_distance)
        columns, _, _ = self._info_columns(metrics)
        infos = {a: {c: v[self._slot_of[a]] for c, v in columns.items()} for a in self.agents}
        return self._history, self._agent_static, metrics.progress, obs, infos

    # ------------------------------------------------------------------ step
    def _action_tensor(self, actions: dict[str, Any]) -> torch.Tensor:
        unknown = [a for a in actions if a not in self._slot_of or a not in self.agents]
        if unknown:
            raise ActionError(
                f"actions for agents that are not active: {unknown}; active agents: {self.agents}"
            )
        missing = [a for a in self.agents if a not in actions]
        if missing:
            raise ActionError(f"no action for active agents {missing}")
        out = np.zeros((1, self.state_.num_agents, 2), np.float32)
        for name, act in actions.items():
            arr = np.asarray(act, dtype=np.float64)
            if arr.shape != (2,):
                raise ActionError(
                    f"action of {name!r} has shape {arr.shape}; expected (2,) = "
                    "(acceleration m/s^2, yaw rate rad/s)"
                )
            if not np.isfinite(arr).all():
                raise ActionError(f"action of {name!r} is not finite: {arr.tolist()}")
            out[0, self._action_rows[name]] = arr
        return torch.from_numpy(out).to(self.device)

    def step(self, actions: dict[str, Any]):
        """Advance one step (0.1 s). See the module docstring for the action format."""
        with torch_threads(self.torch_threads), torch.inference_mode():
            return self._step(actions)

    def _step(self, actions: dict[str, Any]):
        if self.state_ is None:
            raise RuntimeError("call reset() before step()")
        if not self.agents:
            raise RuntimeError("the episode is over: call reset()")
        ext_action = self._action_tensor(actions)
        live_before = list(self.agents)
        action, self._policy_state = npc_actions(
            self.state_, ext_action, self._ctrl, self._policy_state, self._generator
        )
        fused = self._step_fn(
            self.state_,
            action,
            self._ext_slots,
            self._route,
            self._progress,
            self._goal_reached,
            self._has_goal,
            self.config,
            self._history,
            self._ctx,
            self.obs_config,
            self._agent_static,
        )
        tr = fused.transition
        metrics, outcome = tr.metrics, tr.outcome
        self._progress = outcome.progress_best
        self._goal_reached = tr.goal_reached
        self.state_ = tr.state
        columns, reward_l, term_l = self._info_columns(metrics, outcome)
        truncated_all = columns["step"][0] >= self._end
        rewards, terms, truncs, infos = {}, {}, {}, {}
        for name in live_before:
            j = self._slot_of[name]
            rewards[name] = reward_l[j]
            terms[name] = term_l[j]
            truncs[name] = truncated_all and not term_l[j]
            infos[name] = {k: v[j] for k, v in columns.items()}
        self._history = fused.history
        obs = self._per_agent(live_before, fused.obs)
        self.agents = [a for a in live_before if not (terms[a] or truncs[a])]
        return obs, rewards, terms, truncs, infos

    # ------------------------------------------------------------------ helpers
    def _observations(
        self, names: list[str], agent_distance: torch.Tensor | None = None
    ) -> dict[str, dict[str, np.ndarray]]:
        if not names:
            return {}
        o = observe(
            self.state_,
            self._history,
            self._ctx,
            self._ext_slots,
            self.obs_config,
            agent_static=self._agent_static,
            agent_distance=agent_distance,
        )
        return self._per_agent(names, o)

    def _per_agent(
        self, names: list[str], o: dict[str, torch.Tensor]
    ) -> dict[str, dict[str, np.ndarray]]:
        """Per-agent numpy views of ``observe``'s [1, Q, ...] tensors, for ``names``."""
        if self.device.type == "cpu":
            o = {k: v.numpy()[0] for k, v in o.items()}
        else:
            o = {k: v.cpu().numpy()[0] for k, v in o.items()}
        return {n: {k: v[self._slot_of[n]] for k, v in o.items()} for n in names}

    def _info_columns(
        self, m: StepMetrics, outcome: RewardOutcome | None = None
    ) -> tuple[dict[str, list], list[float], list[bool]]:
        """Per-agent info values as lists indexed like ``self._ext_slots``.

        Returns:
            (info columns, rewards, terminations) where the last two are those of ``outcome``
            (empty without one). All values come from two ``tolist`` calls.
        """
        q = self._ext_slots.shape[1]
        floats = [
            m.offroad_distance,
            m.progress,
            m.goal_distance,
            m.log_divergence,
            self.state_.speed.index_select(1, self._ext_index),
        ]
        flags = [m.collision, m.offroad, self._goal_reached]
        if outcome is not None:
            floats.append(outcome.reward)
            flags.append(outcome.terminated)
        # [field][batch of one][agent] lists.
        dist, progress, goal_d, log_d, speed, *reward = (x[0] for x in torch.stack(floats).tolist())
        coll, off, reached, *term = (x[0] for x in torch.stack(flags).tolist())
        columns = {
            "scenario_id": [self.scenario.scenario_id] * q,
            "track_id": list(self._track_ids),
            "step": [int(self.state_.step.item())] * q,
            "collision": coll,
            "offroad": off,
            "offroad_distance": dist,
            "progress": progress,
            "goal_distance": goal_d,
            "goal_reached": reached,
            "log_divergence": log_d,
            "speed": speed,
        }
        return columns, (reward or [[]])[0], (term or [[]])[0]

    @torch.inference_mode()
    def expert_actions(self) -> dict[str, np.ndarray]:
        """Actions that steer each live agent from its current state back onto its log.

        One closed-loop inverse-dynamics step (``inverse_step``) towards the logged state of
        the next step; zero where the log has no next state. Following them from the start
        reproduces the log within centimetres where the log is feasible.
        """
        s = self.sim_state
        n_t = s.log.valid.shape[-1]
        t1 = min(int(s.step[0]) + 1, n_t - 1)
        slots = self._ext_slots[0]
        max_acc, max_yaw = action_limits(s.agents.object_type[0, slots])
        act = inverse_step(
            s.pose[0, slots],
            s.speed[0, slots],
            s.log.pose[0, slots, t1],
            s.log.speed[0, slots, t1],
            max_acc,
            max_yaw,
        )
        act = act * s.log.valid[0, slots, t1, None]
        act = act.cpu().numpy().astype(np.float32)
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
        state = self.sim_state
        groups = np.full(state.num_agents, int(AgentGroup.LOG_REPLAY), np.int64)
        groups[self._ctrl.npc[0].cpu().numpy()] = int(AgentGroup.POLICY)
        groups[self._ctrl.external[0].cpu().numpy()] = int(AgentGroup.EXTERNAL)
        return render_state(self._renderer[1], state, 0, groups)

    def close(self) -> None:
        self._renderer = None


def episode_length(env: TrafficEnv) -> int:
    """Steps of a full episode of the current scenario."""
    return int(math.floor(env._end - env.config.start_step))


__all__ = ["TrafficEnv", "agent_name", "controlled_indices", "resolve_scenarios"]
