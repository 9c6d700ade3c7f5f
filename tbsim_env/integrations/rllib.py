"""RLlib: ``TrafficEnv`` as a multi-agent env through RLlib's ``ParallelPettingZooEnv``.

RLlib needs a fixed set of agent ids and an ``"__all__"`` flag that turns True when the
episode is over. ``TrafficEnv`` names agents by track id (different per scenario), so the env
is wrapped in ``SlotAgentsParallelEnv`` (``agent_0 .. agent_{Q-1}``). RLlib's wrapper sets
``terminateds["__all__"] = all(terminated)`` and ``truncateds["__all__"] = all(truncated)``,
which stays False when the episode ends with some agents terminated and the others truncated;
``TbsimRLlibEnv`` sets ``"__all__"`` from ``terminated or truncated`` instead.

    from ray.tune.registry import register_env
    from tbsim_env.integrations.rllib import ENV_NAME, make_rllib_env
    register_env(ENV_NAME, make_rllib_env)
    config = PPOConfig().environment(ENV_NAME, env_config={"controlled": "tracks_to_predict"})
"""

from __future__ import annotations

from typing import Any

from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv

from tbsim_env.env.wrappers import SlotAgentsParallelEnv

ENV_NAME = "tbsim_traffic_slots"
"""Name to register ``make_rllib_env`` under."""


class TbsimRLlibEnv(ParallelPettingZooEnv):
    """RLlib's PettingZoo wrapper with ``"__all__"`` = every agent terminated or truncated."""

    def step(self, action_dict: dict[str, Any]):
        obs, rew, term, trunc, infos = self.par_env.step(action_dict)
        over = all(term[a] or trunc[a] for a in term)
        every_term = all(term.values())
        term["__all__"] = over and every_term
        trunc["__all__"] = over and not every_term
        return obs, rew, term, trunc, infos


def make_rllib_env(env_config: dict[str, Any] | None = None) -> TbsimRLlibEnv:
    """Env creator for ``register_env``.

    Args:
        env_config: ``SlotAgentsParallelEnv`` / ``TrafficEnv`` keyword arguments, plus
            ``num_default_scenes`` (embedded generated scenes, when ``scenarios`` is absent).
            Defaults: 2 generated scenes, ``controlled="tracks_to_predict"``,
            ``npc_policy="constant_velocity"``.
    """
    cfg = dict(env_config or {})
    if "scenarios" not in cfg:
        from tbsim_env.data.generator import default_scenarios

        cfg["scenarios"] = default_scenarios(int(cfg.pop("num_default_scenes", 2)))
    cfg.pop("num_default_scenes", None)
    cfg.setdefault("controlled", "tracks_to_predict")
    cfg.setdefault("npc_policy", "constant_velocity")
    return TbsimRLlibEnv(SlotAgentsParallelEnv(**cfg))


__all__ = ["ENV_NAME", "TbsimRLlibEnv", "make_rllib_env"]
