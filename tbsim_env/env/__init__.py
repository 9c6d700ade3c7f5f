"""The environments: PettingZoo ``TrafficEnv``, the tensor-batched ``BatchedTrafficEnv`` and its
Gymnasium ``VectorEnv`` view ``TrafficVectorEnv``."""

from tbsim_env.env.gym_vector import TrafficVectorEnv
from tbsim_env.env.parallel_env import TrafficEnv, agent_name
from tbsim_env.env.vector_env import BatchedTrafficEnv

__all__ = ["BatchedTrafficEnv", "TrafficEnv", "TrafficVectorEnv", "agent_name"]
