"""Wrappers of ``TrafficEnv`` for RL libraries.

* ``SingleAgentTrafficEnv``: a Gymnasium ``Env`` where the SDC is the learner and every other
  agent is an NPC (flattened ``Box`` observation by default, as Stable-Baselines3 wants, or
  the ``Dict`` observation). It passes ``gymnasium.utils.env_checker.check_env``.
* ``SlotAgentsParallelEnv``: a PettingZoo ``ParallelEnv`` with a fixed agent set
  ``agent_0 .. agent_{Q-1}`` (Q = most controlled agents of any scenario) and flattened
  ``Box`` observations, for libraries that need the same agents in every step and episode
  (SuperSuit's ``pettingzoo_env_to_vec_env_v1``, parameter sharing in RLlib). Slots without
  an agent, or whose agent is done, get zero observations and zero reward and their actions
  are ignored ("black death") until every agent of the episode is done; then all slots end
  together.
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.utils import EzPickle
from pettingzoo import ParallelEnv

from tbsim_env.env.parallel_env import TrafficEnv


def action_box(env: TrafficEnv) -> gym.spaces.Box:
    """One ``Box`` covering the action spaces of every possible agent (loosest limits).

    Actions beyond an agent's own type limits are clipped by the simulator.
    """
    highs = np.stack([env.action_space(a).high for a in env.possible_agents])
    high = highs.max(axis=0).astype(np.float32)
    return gym.spaces.Box(-high, high, dtype=np.float32)


class SingleAgentTrafficEnv(gym.Env, EzPickle):
    """Gymnasium single-agent env: the SDC learns, everything else is an NPC.

    Args:
        scenarios: as ``TrafficEnv`` (None: embedded generated scenes).
        npc_policy: policy of all other agents (``"log_replay"``, ``"constant_velocity"``, a
            registered name or a ``Policy``).
        flatten: flattened ``Box`` observation (default) or the ``Dict`` of ``TrafficEnv``.
        normalize_actions: the action space is [-1, 1]^2, scaled by the SDC type's limits
            (what SB3 recommends); otherwise physical units.
        render_mode: None or ``"rgb_array"``.
        env_kwargs: further ``TrafficEnv`` keyword arguments (config, obs_config,
            scenario_order, device, torch_threads, compile).

    The action is ``np.float32[2]`` (acceleration m/s^2, yaw rate rad/s); the info dict is the
    SDC's ``TrafficEnv`` info (collision, offroad, progress, goal_reached, ...).
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 10}

    def __init__(
        self,
        scenarios: Any = None,
        npc_policy: Any = "log_replay",
        flatten: bool = True,
        normalize_actions: bool = False,
        render_mode: str | None = None,
        **env_kwargs: Any,
    ) -> None:
        EzPickle.__init__(
            self, scenarios, npc_policy, flatten, normalize_actions, render_mode, **env_kwargs
        )
        self.env = TrafficEnv(
            scenarios,
            controlled="sdc",
            npc_policy=npc_policy,
            render_mode=render_mode,
            **env_kwargs,
        )
        self.render_mode = render_mode
        self.flatten = flatten
        self._dict_space = self.env.observation_space(self.env.possible_agents[0])
        self.observation_space = (
            gym.spaces.flatten_space(self._dict_space) if flatten else self._dict_space
        )
        self._physical = action_box(self.env)
        self.normalize_actions = normalize_actions
        self.action_space = (
            gym.spaces.Box(-1.0, 1.0, (2,), np.float32) if normalize_actions else self._physical
        )
        self._agent: str | None = None
        self._last_obs: Any = None

    def _convert(self, obs: dict[str, np.ndarray]) -> Any:
        if self.flatten:
            return gym.spaces.flatten(self._dict_space, obs).astype(np.float32)
        return obs

    def reset(
        self, *, seed: int | None = None, options: dict | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Start an episode on the next scenario (``options`` as ``TrafficEnv.reset``)."""
        super().reset(seed=seed)
        obs, infos = self.env.reset(seed=seed, options=options)
        (self._agent,) = self.env.agents
        self._last_obs = self._convert(obs[self._agent])
        return self._last_obs, dict(infos[self._agent])

    def step(self, action: np.ndarray) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        """One 0.1 s step of the SDC with ``action`` = (acceleration, yaw rate)."""
        if self._agent is None:
            raise RuntimeError("call reset() before step()")
        if self._agent not in self.env.agents:
            raise RuntimeError("the episode is over: call reset()")
        act = np.asarray(action, dtype=np.float32)
        if self.normalize_actions and act.shape == (2,):
            act = np.clip(act, -1.0, 1.0) * self._physical.high
        obs, rew, term, trunc, infos = self.env.step({self._agent: act})
        a = self._agent
        self._last_obs = self._convert(obs[a])
        return self._last_obs, float(rew[a]), bool(term[a]), bool(trunc[a]), dict(infos[a])

    def expert_action(self) -> np.ndarray:
        """The SDC's inverse-dynamics action that follows its log, in this env's action units."""
        act = self.env.expert_actions()[self._agent]
        if self.normalize_actions:
            act = (act / self._physical.high).astype(np.float32)
        return act

    def render(self) -> np.ndarray | None:
        return self.env.render()

    def close(self) -> None:
        self.env.close()


class SlotAgentsParallelEnv(ParallelEnv, EzPickle):
    """``TrafficEnv`` with fixed slot agents ``agent_i`` and black death, for vector wrappers.

    Args:
        scenarios: as ``TrafficEnv``.
        flatten: flattened ``Box`` observations (default) or the ``Dict``.
        env_kwargs: further ``TrafficEnv`` keyword arguments (controlled, npc_policy,
            config, obs_config, scenario_order, render_mode, device, torch_threads).

    Per step every slot is present. ``infos[slot]["active"]`` tells whether the slot drove a
    real agent this step (``infos[slot]["agent"]`` is its ``track_<id>`` name). A real agent
    that terminates gets its reward that step and zero afterwards; the terminations and
    truncations of all slots are reported together at the step where the last real agent
    is done (``terminated`` for slots whose agent terminated, ``truncated`` otherwise).
    """

    metadata = {
        "render_modes": ["rgb_array"],
        "name": "tbsim_traffic_slots_v0",
        "is_parallelizable": True,
        "render_fps": 10,
    }

    def __init__(self, scenarios: Any = None, flatten: bool = True, **env_kwargs: Any) -> None:
        EzPickle.__init__(self, scenarios, flatten, **env_kwargs)
        self.env = TrafficEnv(scenarios, **env_kwargs)
        self.render_mode = self.env.render_mode
        self.flatten = flatten
        q = max(len(c) for c in self.env.controlled_tracks)
        self.possible_agents = [f"agent_{i}" for i in range(q)]
        self.agents: list[str] = []
        self._dict_space = self.env.observation_space(self.env.possible_agents[0])
        self._obs_space = (
            gym.spaces.flatten_space(self._dict_space) if flatten else self._dict_space
        )
        self._act_space = action_box(self.env)
        self._zero = self._convert(
            {k: np.zeros(s.shape, np.float32) for k, s in self._dict_space.spaces.items()}
        )
        self._slot_agent: dict[str, str] = {}
        self._terminated: dict[str, bool] = {}

    def observation_space(self, agent: str) -> gym.spaces.Space:
        return self._obs_space

    def action_space(self, agent: str) -> gym.spaces.Box:
        return self._act_space

    def _convert(self, obs: dict[str, np.ndarray]) -> Any:
        if self.flatten:
            return gym.spaces.flatten(self._dict_space, obs).astype(np.float32)
        return obs

    def _zero_obs(self) -> Any:
        if self.flatten:
            return self._zero.copy()
        return {k: v.copy() for k, v in self._zero.items()}

    def reset(
        self, seed: int | None = None, options: dict | None = None
    ) -> tuple[dict[str, Any], dict[str, dict]]:
        obs, infos = self.env.reset(seed=seed, options=options)
        self._slot_agent = dict(zip(self.possible_agents, self.env.agents))
        self._terminated = {s: False for s in self.possible_agents}
        self.agents = list(self.possible_agents)
        out_obs, out_info = {}, {}
        for s in self.agents:
            a = self._slot_agent.get(s)
            out_obs[s] = self._convert(obs[a]) if a else self._zero_obs()
            out_info[s] = {**(infos[a] if a else {}), "agent": a, "active": a is not None}
        return out_obs, out_info

    def step(self, actions: dict[str, Any]):
        if not self.agents:
            raise RuntimeError("the episode is over: call reset()")
        live = set(self.env.agents)
        inner = {}
        for s, a in self._slot_agent.items():
            if a in live:
                if s not in actions:
                    raise ValueError(f"no action for {s}")
                inner[a] = np.asarray(actions[s], dtype=np.float32)
        obs, rew, term, trunc, infos = self.env.step(inner)
        over = not self.env.agents
        out = ({}, {}, {}, {}, {})
        for s in self.possible_agents:
            a = self._slot_agent.get(s)
            acted = a in inner
            if acted and term[a]:
                self._terminated[s] = True
            out[0][s] = self._convert(obs[a]) if acted else self._zero_obs()
            out[1][s] = float(rew[a]) if acted else 0.0
            out[2][s] = over and self._terminated[s]
            out[3][s] = over and not self._terminated[s]
            out[4][s] = {**(infos[a] if acted else {}), "agent": a, "active": acted}
        if over:
            self.agents = []
        return out

    def render(self) -> np.ndarray | None:
        return self.env.render()

    def close(self) -> None:
        self.env.close()

    @property
    def unwrapped(self) -> SlotAgentsParallelEnv:
        return self


__all__ = ["SingleAgentTrafficEnv", "SlotAgentsParallelEnv", "action_box"]
