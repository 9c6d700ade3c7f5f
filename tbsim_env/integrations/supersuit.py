"""SuperSuit: ``TrafficEnv`` agents as a (Stable-Baselines3 or Gymnasium) vector env.

Every agent slot of every env copy becomes one row of the vector env with shared parameters
(CleanRL's ``ppo_pettingzoo_ma_atari`` recipe): ``SlotAgentsParallelEnv`` gives fixed agent
slots and flattened ``Box`` observations, ``pettingzoo_env_to_vec_env_v1`` turns the slots
into rows and ``concat_vec_envs_v1`` stacks ``num_envs`` copies.
"""

from __future__ import annotations

from typing import Any

from tbsim_env.env.wrappers import SlotAgentsParallelEnv


def make_vec_env(
    num_envs: int = 2,
    base_class: str = "gymnasium",
    num_cpus: int = 0,
    **env_kwargs: Any,
):
    """A SuperSuit vector env of ``num_envs`` x Q agent rows.

    Args:
        num_envs: copies of the parallel env.
        base_class: ``"gymnasium"`` or ``"stable_baselines3"`` (an SB3 ``VecEnv``).
        num_cpus: worker processes (0: all in this process).
        env_kwargs: ``SlotAgentsParallelEnv`` / ``TrafficEnv`` keyword arguments.
    """
    import supersuit as ss

    env = ss.pettingzoo_env_to_vec_env_v1(SlotAgentsParallelEnv(**env_kwargs))
    return ss.concat_vec_envs_v1(env, num_envs, num_cpus=num_cpus, base_class=base_class)


__all__ = ["make_vec_env"]
