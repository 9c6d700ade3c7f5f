"""The policy interface (defined by the simulation layer: ``tbsim_env.sim.policy``)."""

from tbsim_env.sim.policy import Policy, PolicyState

__all__ = ["Policy", "PolicyState"]
