"""Preprocessing of a ``Scenario`` into ``SceneTokens`` (TrafficBots V1.5, docs/model.md §1).

Pure numpy functions, one job per module:

- ``map_pieces``: map features -> pieces of <= 20 segments with 11 classes (1.2).
- ``map_filter``: keep the pieces near the relevant agents, up to the limit (1.6).
- ``traffic_lights``: one TL token per kept piece of each controlled lane (1.3).
- ``agents``: signed speed, mean size, gap filling with acc and yaw rate (1.4).
- ``selection``: which tracks become simulated agents (1.6, filters a-f).
- ``destination``: the destination map piece of each agent (1.7).
- ``scene``: orchestration and padding -> ``SceneTokens``.
"""

from tbsim_env.data.preprocess.agents import (
    AgentAttributes,
    AgentStates,
    agent_attributes,
    fill_gaps,
    mean_size,
    signed_speed,
)
from tbsim_env.data.preprocess.destination import Goals, destination_labels, last_valid_goals
from tbsim_env.data.preprocess.map_filter import filter_map_pieces
from tbsim_env.data.preprocess.map_pieces import MapPieces, build_map_pieces, feature_classes
from tbsim_env.data.preprocess.scene import (
    preprocess_scenario,
    scenario_rng,
    scene_origin,
    scene_yaw,
)
from tbsim_env.data.preprocess.selection import select_agents
from tbsim_env.data.preprocess.traffic_lights import (
    TrafficLightTokens,
    attach_traffic_lights,
    map_signal_states,
)

__all__ = [
    "AgentAttributes",
    "AgentStates",
    "Goals",
    "MapPieces",
    "TrafficLightTokens",
    "agent_attributes",
    "attach_traffic_lights",
    "build_map_pieces",
    "destination_labels",
    "feature_classes",
    "fill_gaps",
    "filter_map_pieces",
    "last_valid_goals",
    "map_signal_states",
    "mean_size",
    "preprocess_scenario",
    "scenario_rng",
    "scene_origin",
    "scene_yaw",
    "select_agents",
    "signed_speed",
]
