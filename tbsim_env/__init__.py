"""tbsim: multi-agent traffic simulation on real Waymo scenarios."""

from tbsim_env.data.scenario import Scenario

__all__ = ["Scenario"]
__version__ = "0.1.0"
