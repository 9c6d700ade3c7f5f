"""``TrafficVectorEnv``: a Gymnasium ``VectorEnv`` view of ``BatchedTrafficEnv`` for one learner.

Each of the ``num_envs`` rows is one scenario slot whose SDC is the learner (every other agent
is an NPC of ``npc_policy``), so CleanRL-style code written for ``gymnasium.vector`` runs on
the batched simulator directly: one batched tensor step per call, no per-env Python loop and
no SuperSuit.

* Observations: the SDC's dense observation, flattened into one float32 vector per row
  (``flatten=True``, the keys in ``single_observation_space``'s order, as
  ``gymnasium.spaces.flatten`` orders them) or the ``Dict`` of arrays.
* Autoreset is same-step (``metadata["autoreset_mode"] = AutoresetMode.SAME_STEP``): a row
  whose episode ended returns the first observation of its next episode, and
  ``infos["final_obs"]`` / ``infos["_final_obs"]`` hold the last one, as Gymnasium 1.x
  declares it.
* ``backend="numpy"`` (default) returns numpy arrays; ``"torch"`` returns the simulator's
  tensors on its device (actions may then be tensors too).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from tbsim_env.env.vector_env import BatchedTrafficEnv

INFO_KEYS = ("collision", "offroad", "progress", "goal_reached", "log_divergence")
"""Per-row metrics copied into ``infos`` (the SDC's, as in ``BatchedTrafficEnv``)."""


class TrafficVectorEnv(VectorEnv):
    """``num_envs`` scenario slots stepped as one batch; the SDC of each is the learner.

    Args:
        scenarios: as ``BatchedTrafficEnv`` (None: the embedded generated scenes).
        num_envs: rows (scenario slots).
        flatten: one flat float32 observation per row (default) or the ``Dict``.
        backend: ``"numpy"`` or ``"torch"`` for what ``reset`` / ``step`` return.
        env_kwargs: further ``BatchedTrafficEnv`` keyword arguments (``npc_policy``,
            ``config``, ``obs_config``, ``seed``, ``device``, ``route_points``, ...);
            ``controlled`` is always ``"sdc"``.
    """

    metadata = {"autoreset_mode": AutoresetMode.SAME_STEP, "render_modes": []}

    def __init__(
        self,
        scenarios: Any = None,
        num_envs: int = 8,
        *,
        flatten: bool = True,
        backend: str = "numpy",
        **env_kwargs: Any,
    ) -> None:
        if backend not in ("numpy", "torch"):
            raise ValueError(f"backend must be 'numpy' or 'torch', got {backend!r}")
        if env_kwargs.pop("controlled", "sdc") != "sdc":
            raise ValueError("TrafficVectorEnv's learner is the SDC (controlled='sdc')")
        env_kwargs.pop("obs_layout", None)
        self.env = BatchedTrafficEnv(scenarios, num_envs, controlled="sdc", **env_kwargs)
        self.num_envs = int(num_envs)
        self.flatten = bool(flatten)
        self.backend = backend
        dict_space = self.env.single_observation_space()
        self._keys = list(dict_space.spaces)  # the order gymnasium.spaces.flatten uses
        self.single_observation_space = (
            gym.spaces.flatten_space(dict_space) if flatten else dict_space
        )
        self.single_action_space = self.env.single_action_space()
        self.observation_space = batch_space(self.single_observation_space, self.num_envs)
        self.action_space = batch_space(self.single_action_space, self.num_envs)

    # ------------------------------------------------------------------ conversion
    def _obs(self, obs: dict[str, torch.Tensor]) -> Any:
        """[B, 1, ...] per key -> [B, D] flat or a dict of [B, ...] (numpy or torch)."""
        rows = {k: obs[k][:, 0] for k in self._keys}
        if self.flatten:
            flat = torch.cat([rows[k].reshape(self.num_envs, -1) for k in self._keys], -1)
            return self._out(flat)
        return {k: self._out(v) for k, v in rows.items()}

    def _out(self, x: torch.Tensor) -> Any:
        return x if self.backend == "torch" else x.cpu().numpy()

    def _infos(self, info: dict[str, Any]) -> dict[str, Any]:
        out = {k: self._out(info[k][:, 0]) for k in INFO_KEYS}
        out["scenario_index"] = self._out(info["scenario_index"])
        return out

    # ------------------------------------------------------------------ API
    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[Any, dict[str, Any]]:
        """Start every row anew (``options["scenario_indices"]`` picks the scenarios)."""
        indices = (options or {}).get("scenario_indices")
        obs, info = self.env.reset(seed=seed, scenario_indices=indices)
        return self._obs(obs), self._infos(info)

    def step(self, actions: Any) -> tuple[Any, Any, Any, Any, dict[str, Any]]:
        """Advance every row by 0.1 s.

        Args:
            actions: [num_envs, 2] (acceleration m/s^2, yaw rate rad/s), numpy or torch.

        Returns:
            (obs, rewards [B] float32, terminations [B] bool, truncations [B] bool, infos):
            ``infos`` holds the per-row metrics, ``final_obs`` (the last observation of the
            rows that ended, ``_final_obs`` marks them) and ``episode`` (``r`` return, ``l``
            length, ``_r`` the rows that ended).
        """
        act = torch.as_tensor(np.asarray(actions) if not torch.is_tensor(actions) else actions)
        act = act.reshape(self.num_envs, 1, 2)
        obs, rew, term, trunc, info = self.env.step(act)
        infos = self._infos(info)
        done = info["done"]
        infos["final_obs"] = self._obs(info["final_obs"])
        infos["_final_obs"] = self._out(done)
        infos["episode"] = {
            "r": self._out(info["episode_return"][:, 0]),
            "l": self._out(info["episode_length"]),
            "_r": self._out(done),
        }
        return (
            self._obs(obs),
            self._out(rew[:, 0]),
            self._out(term[:, 0]),
            self._out(trunc[:, 0]),
            infos,
        )

    def close_extras(self, **kwargs: Any) -> None:
        """Nothing to release: the simulator lives in this process."""


__all__ = ["INFO_KEYS", "TrafficVectorEnv"]
