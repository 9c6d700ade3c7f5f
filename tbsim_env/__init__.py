"""tbsim: multi-agent traffic simulation on real Waymo scenarios."""

from tbsim_env.data.loader import load_scenarios
from tbsim_env.data.scenario import Scenario
from tbsim_env.env import TrafficEnv

__all__ = ["Scenario", "TrafficEnv", "load_scenarios"]
__version__ = "0.1.0"
