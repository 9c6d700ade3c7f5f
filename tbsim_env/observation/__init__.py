"""Pairwise-relative observations: agent, map and traffic-light tokens of each observer in its
own frame (``tokens``), their keys, shapes and bounds (``spec``), the map-piece nearest
neighbours (``map_knn``) and the row helpers of the compact layout (``rows``).

The names below are the public ones; ``from tbsim_env.observation import ObsConfig, observe``
works as it always has.
"""

from tbsim_env.observation.spec import (
    ATTRIBUTE_FEATURES,
    HISTORY_FEATURES,
    NODE_FEATURES,
    NUM_TYPE_FEATURES,
    OBS_KEYS,
    ObsConfig,
    ObsKey,
    observation_shapes,
    observation_space,
    observation_table,
)
from tbsim_env.observation.tokens import (
    History,
    IndexedObservation,
    MapContext,
    build_map_context,
    dense_views,
    densify,
    densify_flat,
    init_history,
    observe,
    observe_indexed,
    push_history,
)

__all__ = [
    "ATTRIBUTE_FEATURES",
    "HISTORY_FEATURES",
    "NODE_FEATURES",
    "NUM_TYPE_FEATURES",
    "OBS_KEYS",
    "History",
    "IndexedObservation",
    "MapContext",
    "ObsConfig",
    "ObsKey",
    "build_map_context",
    "dense_views",
    "densify",
    "densify_flat",
    "init_history",
    "observation_shapes",
    "observation_space",
    "observation_table",
    "observe",
    "observe_indexed",
    "push_history",
]
