"""Scenario data: the typed ``Scenario`` and its readers."""

from tbsim_env.data.scenario import RoadMap, Scenario, Tracks, TrafficSignals

__all__ = ["RoadMap", "Scenario", "Tracks", "TrafficSignals"]
