"""The PettingZoo environment and its per-agent metrics."""

from tbsim_env.env.parallel_env import TrafficEnv, agent_name

__all__ = ["TrafficEnv", "agent_name"]
