"""The environments: PettingZoo ``TrafficEnv`` and the tensor-batched ``BatchedTrafficEnv``."""

from tbsim_env.env.parallel_env import TrafficEnv, agent_name
from tbsim_env.env.vector_env import BatchedTrafficEnv

__all__ = ["BatchedTrafficEnv", "TrafficEnv", "agent_name"]
