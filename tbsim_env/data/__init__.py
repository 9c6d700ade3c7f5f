"""Scenario data: the typed ``Scenario`` and its readers."""

from tbsim_env.data.scenario import RoadMap, Scenario, Tracks, TrafficSignals

__all__ = ["RoadMap", "Scenario", "Tracks", "TrafficSignals"]

from tbsim_env.data.loader import iter_scenarios, load_scenarios  # noqa: E402

__all__ += ["iter_scenarios", "load_scenarios"]
