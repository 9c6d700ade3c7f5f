"""TorchRL: ``BatchedTrafficEnv`` as a multi-agent TorchRL ``EnvBase`` (the ``torchrl`` extra).

One TorchRL env of batch size ``[B]`` (B scenario slots); the Q controlled-agent slots of a
scenario form one agent group (``"agents"`` by default), as TorchRL's VMAS and PettingZoo
wrappers group agents. Keys (shapes with the batch; units as ``BatchedTrafficEnv``):

* ``("agents", "observation", key)`` [B, Q, *shape] float32: the dense observation keys
  (``single_observation_space``: ``ego_history``, ``agents``, ``map``, ...; ``route`` when
  ``route_points`` > 0); zero for agents that are not active. With
  ``obs_layout="indexed"`` the per-observer keys of ``OBS_INDEXED_KEYS`` instead (``ego``,
  ``index`` int64; ``pose``, ``mask``, ``observer_mask`` float32; ``route``), and the tokens
  they index: ``("tokens", "agent_tokens")`` [B, R, D] (``OBS_INDEXED_KEYS``) and
  ``("tokens", "light_tokens")`` [B, L, 5] (map pieces: ``env.env.map_token_bank`` rows of
  ``"scenario_index"``; ``env.env.densify`` gives the dense layout).
* ``("agents", "mask")`` [B, Q] bool: agents active now (they need an action; padding agent
  slots and agents that ended are False). Use it to mask losses and statistics.
* ``("agents", "info", name)`` [B, Q] float32: metrics of the step that led here
  (``collision``, ``offroad``, ``goal_reached``, ``progress`` m, ``log_divergence`` m);
  0 right after a reset (no step yet).
* ``"scenario_index"`` [B] int64: the slot's scenario (index into ``env.scenarios``).
* ``("agents", "action")`` [B, Q, 2]: (acceleration m/s^2, yaw rate rad/s), bounded by the
  loosest type limits (actions are clipped per type; those of inactive agents are ignored).
* ``("agents", "reward")`` [B, Q, 1] float32, 0 for agents that did not act.
* ``("agents", "done" | "terminated" | "truncated")`` [B, Q, 1] bool: the agent's episode
  ended in this step (``BatchedTrafficEnv``'s ``terminated`` / ``truncated``; ``done`` is
  either). They are events, not states: an agent that ended earlier, or a padding slot, is
  not done again (its ``mask`` is False), so a collector's trajectory ids change only when
  an agent or a slot ends.
* ``"done" | "terminated" | "truncated"`` [B, 1] bool: the slot's episode is over (every
  agent ended); ``truncated`` when it ended at the end step, ``terminated`` otherwise.

**Resets, the TorchRL way.** ``("next", ...)`` holds the true last observation of a finished
episode (``BatchedTrafficEnv``'s ``infos["final_obs"]``), so truncated episodes can be
bootstrapped. TorchRL then calls ``reset`` with a ``"_reset"`` mask of the finished slots
(``step_and_maybe_reset``, ``rollout``, collectors); that partial reset returns the first
observation of their next episode, which ``BatchedTrafficEnv`` already started in the same
step (same-step autoreset), so stepping through TorchRL gives exactly the episodes and values
of ``BatchedTrafficEnv`` for the same seed. A reset without ``"_reset"`` (or with every slot)
starts every slot anew. Only slots whose episode just ended can be reset partially (the
batched env has no other partial reset): asking for another slot raises ``RuntimeError``.

    from tbsim_env.integrations.torchrl import TorchRLTrafficEnv
    env = TorchRLTrafficEnv(batch_size=8, controlled="all", npc_policy="constant_velocity")
    data = env.rollout(100, break_when_any_done=False)  # [8, 100] TensorDict
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from tbsim_env.env import episode as ep
from tbsim_env.env.vector_env import ROUTE_KEY, BatchedTrafficEnv

GROUP = "agents"
"""Default name of the agent group."""

INFO_KEYS = ("collision", "offroad", "goal_reached", "progress", "log_divergence")
"""Per-agent step metrics copied to ``(group, "info", name)`` as float32."""


# ---------------------------------------------------------------------- specs
def box_spec(space: gym.spaces.Box, lead: tuple[int, ...], device: torch.device) -> Any:
    """TorchRL spec of a Gymnasium ``Box`` batched over ``lead`` (e.g. (B, Q)).

    ``Unbounded`` where any bound is infinite, else ``Bounded`` with the element-wise bounds.
    """
    shape = (*lead, *space.shape)
    dtype = torch.float32
    if not (np.isfinite(space.low).all() and np.isfinite(space.high).all()):
        return Unbounded(shape=shape, dtype=dtype, device=device)
    low = torch.as_tensor(space.low, dtype=dtype).expand(shape).clone()
    high = torch.as_tensor(space.high, dtype=dtype).expand(shape).clone()
    return Bounded(low=low, high=high, shape=shape, dtype=dtype, device=device)


def _flags(shape: tuple[int, ...], device: torch.device) -> Categorical:
    """A bool spec of ``shape``."""
    return Categorical(2, shape=shape, dtype=torch.bool, device=device)


def _done_spec(shape: tuple[int, ...], device: torch.device) -> dict[str, Categorical]:
    """``done``, ``terminated`` and ``truncated`` bool specs of ``shape``."""
    return {k: _flags(shape, device) for k in ("done", "terminated", "truncated")}


def observation_specs(env: BatchedTrafficEnv, device: torch.device) -> tuple[dict, dict]:
    """(per-agent specs [B, Q, ...], per-slot token specs [B, ...]) of ``env``'s layout.

    Dense: the Gymnasium space of one agent, no tokens. Indexed: the token counts come from
    one episode start of the bank (``episode.start``, the env's state is not touched).
    """
    b, q = env.batch_size, env.num_agents
    if env.obs_layout == "dense":
        spaces = env.single_observation_space().spaces
        return {k: box_spec(s, (b, q), device) for k, s in spaces.items()}, {}
    cfg = ep.StepConfig(env.config, env.obs_config, dense=False)
    with torch.no_grad():
        state, _ = ep.start(env.bank, torch.zeros(1, dtype=torch.int64, device=env.device))
        probe = ep.observe_state(state, cfg)
    k = probe.index.shape[-1]
    unit = gym.spaces.Box(0.0, 1.0, (), np.float32)

    def floats(*shape: int) -> Unbounded:
        return Unbounded(shape=(b, *shape), dtype=torch.float32, device=device)

    agent = {
        "ego": Unbounded(shape=(b, q), dtype=torch.int64, device=device),
        "index": Unbounded(shape=(b, q, k), dtype=torch.int64, device=device),
        "pose": floats(q, k, 3),
        "mask": box_spec(gym.spaces.Box(0.0, 1.0, (k,), np.float32), (b, q), device),
        "observer_mask": box_spec(unit, (b, q), device),
    }
    if env.route_points:
        agent[ROUTE_KEY] = floats(q, env.route_points, 2)
    tokens = {
        "agent_tokens": floats(*probe.agent_tokens.shape[1:]),
        "light_tokens": box_spec(
            gym.spaces.Box(0.0, 1.0, probe.light_tokens.shape[2:], np.float32),
            (b, probe.light_tokens.shape[1]),
            device,
        ),
    }
    return agent, tokens


# ---------------------------------------------------------------------- the env
class TorchRLTrafficEnv(EnvBase):
    """``BatchedTrafficEnv`` as a TorchRL env of batch size [B] with one agent group.

    Args:
        env: a ``BatchedTrafficEnv`` to wrap (either ``obs_layout``); when None, one is built
            from ``env_kwargs``.
        group: name of the agent group in the keys.
        info_keys: per-agent metrics copied to ``(group, "info", name)``.
        env_kwargs: ``BatchedTrafficEnv`` keyword arguments (``scenarios``, ``batch_size``,
            ``controlled``, ``npc_policy``, ``seed``, ``route_points``, ...) when ``env`` is
            None.

    Attributes:
        env: the wrapped ``BatchedTrafficEnv``.
        num_agents: Q, agent slots per scenario slot.
        last_info: the ``infos`` dict of the latest ``BatchedTrafficEnv`` step or reset
            (``episode_return``, ``reward_terms``, ...).
    """

    def __init__(
        self,
        env: BatchedTrafficEnv | None = None,
        *,
        group: str = GROUP,
        info_keys: tuple[str, ...] = INFO_KEYS,
        **env_kwargs: Any,
    ) -> None:
        if env is None:
            env = BatchedTrafficEnv(**env_kwargs)
        elif env_kwargs:
            raise ValueError("give either a BatchedTrafficEnv or its keyword arguments")
        super().__init__(device=env.device, batch_size=torch.Size([env.batch_size]))
        self.env = env
        self.group = group
        self.info_keys = tuple(info_keys)
        self.num_agents = env.num_agents
        self.last_info: dict[str, Any] = {}
        agent_obs, slot_obs = observation_specs(env, self.device)
        self._obs_keys, self._token_keys = list(agent_obs), list(slot_obs)
        self._pending_seed: int | None = None
        self._reset_data: TensorDict | None = None  # first observation of restarted slots
        self._restarted = torch.zeros(env.batch_size, dtype=torch.bool, device=env.device)
        self._make_specs()

    def _make_specs(self) -> None:
        """Observation, action, reward and done specs from the env's Gymnasium spaces."""
        b, q, dev, g = self.env.batch_size, self.num_agents, self.device, self.group
        obs, tokens = observation_specs(self.env, dev)
        info = {k: Unbounded(shape=(b, q), dtype=torch.float32, device=dev) for k in self.info_keys}
        group_obs = Composite(
            observation=Composite(obs, shape=(b, q), device=dev),
            mask=_flags((b, q), dev),
            info=Composite(info, shape=(b, q), device=dev),
            shape=(b, q),
            device=dev,
        )
        n_scenarios = len(self.env.scenarios)
        self.observation_spec = Composite(
            {
                g: group_obs,
                "scenario_index": Categorical(n_scenarios, (b,), dtype=torch.int64, device=dev),
                **({"tokens": Composite(tokens, shape=(b,), device=dev)} if tokens else {}),
            },
            shape=(b,),
            device=dev,
        )
        action = box_spec(self.env.single_action_space(), (b, q), dev)
        self.full_action_spec = Composite(
            {g: Composite(action=action, shape=(b, q), device=dev)}, shape=(b,), device=dev
        )
        reward = Unbounded(shape=(b, q, 1), dtype=torch.float32, device=dev)
        self.full_reward_spec = Composite(
            {g: Composite(reward=reward, shape=(b, q), device=dev)}, shape=(b,), device=dev
        )
        agent_done = Composite(_done_spec((b, q, 1), dev), shape=(b, q), device=dev)
        self.full_done_spec = Composite(
            {**_done_spec((b, 1), dev), g: agent_done}, shape=(b,), device=dev
        )

    # ------------------------------------------------------------------ packaging
    def _group_td(
        self, obs: dict[str, torch.Tensor], mask: torch.Tensor, info: dict[str, Any] | None
    ) -> TensorDict:
        """The group's observation entries: obs [B, Q, ...], mask [B, Q], info [B, Q] (zero
        when ``info`` is None)."""
        b, q = mask.shape
        if info is None:
            zeros = torch.zeros(b, q, dtype=torch.float32, device=self.device)
            metrics = {k: zeros.clone() for k in self.info_keys}
        else:
            metrics = {k: info[k].to(torch.float32) for k in self.info_keys}
        return TensorDict(
            {
                "observation": {k: obs[k] for k in self._obs_keys},
                "mask": mask.clone(),
                "info": metrics,
            },
            batch_size=mask.shape,
            device=self.device,
        )

    def _tokens(self, obs: dict[str, torch.Tensor]) -> dict[str, Any]:
        """The per-slot token entries of an indexed observation (none when dense)."""
        if not self._token_keys:
            return {}
        return {"tokens": {k: obs[k] for k in self._token_keys}}

    def _reset_td(
        self, obs: dict[str, torch.Tensor], mask: torch.Tensor, scenario: torch.Tensor
    ) -> TensorDict:
        """A reset output: first observations, no step metrics, nothing done."""
        b = self.env.batch_size
        group = self._group_td(obs, mask, None)
        agent_false = torch.zeros_like(mask[..., None])
        group.update(
            done=agent_false, terminated=agent_false.clone(), truncated=agent_false.clone()
        )
        root_false = torch.zeros(b, 1, dtype=torch.bool, device=self.device)
        return TensorDict(
            {
                self.group: group,
                **self._tokens(obs),
                "scenario_index": scenario.clone(),
                "done": root_false,
                "terminated": root_false.clone(),
                "truncated": root_false.clone(),
            },
            batch_size=self.batch_size,
            device=self.device,
        )

    # ------------------------------------------------------------------ EnvBase API
    def _set_seed(self, seed: int | None) -> None:
        """The next full reset reseeds the scenario draws and the policy generator."""
        self._pending_seed = None if seed is None else int(seed)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs: Any) -> TensorDictBase:
        """Full reset, or the partial reset of the slots that finished in the last step.

        Args:
            tensordict: may hold ``"_reset"`` [B, 1] bool, the slots to reset.

        Returns:
            TensorDict [B] of first observations (every slot; TorchRL keeps the others).
        """
        rows = None if tensordict is None else tensordict.get("_reset", None)
        if rows is not None and self._reset_data is not None:
            rows = rows.reshape(self.env.batch_size).to(self.device)
            if not bool((rows & ~self._restarted).any()):
                self._restarted = self._restarted & ~rows
                return self._reset_data.clone()
            if not bool(rows.all()):
                raise RuntimeError(
                    "TorchRLTrafficEnv can reset only the slots whose episode ended in the last "
                    "step (BatchedTrafficEnv restarts those itself); reset every slot instead"
                )
        obs, info = self.env.reset(seed=self._pending_seed)
        self._pending_seed = None
        self.last_info = info
        mask = info["agent_mask"]
        self._reset_data = self._reset_td(obs, mask, info["scenario_index"])
        self._restarted = torch.zeros_like(self._restarted)
        return self._reset_data.clone()

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        """One ``BatchedTrafficEnv`` step of every slot (0.1 s).

        Returns:
            The ``"next"`` TensorDict [B]: last observations (of the finished episode where a
            slot ended), rewards, done flags and step metrics.
        """
        action = tensordict.get((self.group, "action"))
        obs, rew, term, trunc, info = self.env.step(action)
        self.last_info = info
        active = info["active"]
        alive = active & ~term & ~trunc  # before any restart
        ended = info["done"]
        group = self._group_td(info["final_obs"], alive, info)
        group.update(
            reward=rew[..., None],
            done=(term | trunc)[..., None],
            terminated=term[..., None].clone(),
            truncated=trunc[..., None].clone(),
        )
        slot_trunc = ended & trunc.any(-1)
        out = TensorDict(
            {
                self.group: group,
                **self._tokens(info["final_obs"]),
                "scenario_index": info["scenario_index"],
                "done": ended[:, None].clone(),
                "terminated": (ended & ~slot_trunc)[:, None],
                "truncated": slot_trunc[:, None],
            },
            batch_size=self.batch_size,
            device=self.device,
        )
        self._restarted = ended.clone()
        self._reset_data = self._reset_td(obs, info["agent_mask"], self.env.scenario_index)
        return out


def make_torchrl_env(**kwargs: Any) -> TorchRLTrafficEnv:
    """``TorchRLTrafficEnv`` with the integrations' defaults: the embedded generated scenes,
    ``controlled="all"``, ``npc_policy="constant_velocity"``, B = 4 (``batch_size``)."""
    kwargs.setdefault("controlled", "all")
    kwargs.setdefault("npc_policy", "constant_velocity")
    kwargs.setdefault("batch_size", 4)
    return TorchRLTrafficEnv(**kwargs)


__all__ = ["GROUP", "INFO_KEYS", "TorchRLTrafficEnv", "box_spec", "make_torchrl_env"]
