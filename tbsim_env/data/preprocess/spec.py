"""Thresholds of the TrafficBots V1.5 preprocessing (docs/model.md §1.6 and §1.7), in one place.

These are the numbers of the reference implementation, not tunable limits: the token *limits*
(how many pieces, traffic lights and agents are kept) are configuration and live in
``tbsim_env.core.config.TokenConfig``. Units: metres, seconds, radians.
"""

from __future__ import annotations

# --------------------------------------------------------------------------- map (1.6)
BOX_MIN_EXTENT_XY = 500.0
"""Bounding-box filter: minimum margin in x and y around the relevant positions (m)."""
BOX_MIN_EXTENT_Z = 6.0
"""Bounding-box filter: minimum margin in z (m)."""
BOX_MIN_SURVIVORS = 10
"""If fewer pieces survive the box filter, the filter is undone."""
MIN_VALID_NODES = 4
"""Pieces with fewer valid nodes (i.e. <= 3) are dropped."""
MAP_PRUNE_START_RADIUS = 500.0
"""First radius of the map distance pruning; halved after every pass (m)."""
PRUNE_MIN_RADIUS = 1e-3
"""Below this radius a pruning pass uses r = 0, which makes every candidate droppable (m).

Not in the spec: it only guarantees termination when more pieces/agents than the limit sit
exactly on a relevant position."""

# --------------------------------------------------------------------------- agents (1.6)
MIN_VALID_STEPS_TRAINING = 20
"""Filter b: non-relevant agents with fewer valid steps are dropped (training only)."""
STILL_DISPLACEMENT_TRAINING = 2.0
"""Filter c/d: a displacement proxy (sum of speed * DT) below this is "still" (training, m)."""
STILL_DISPLACEMENT_EVAL = 0.5
"""Filter c/d: the same threshold for validation/test (m)."""
STILL_FAR_DISTANCE = 20.0
"""Filter c: a still agent must be farther than this from relevant agents and map nodes (m)."""
PARKED_LANE_DISTANCE = 3.0
"""Filter d: a vehicle within this xy distance of an aligned vehicle-lane node is not parked (m)."""
PARKED_FAR_DISTANCE = 10.0
"""Filter d: a parked vehicle must be farther than this from relevant agents (m)."""
YAW_JUMP_MAX = 1.5
"""Filter e: a per-step |delta yaw| above this is a heading glitch (rad)."""
YAW_JUMP_SLOW = 0.5
"""Filter e: a per-step |delta yaw| above this is a glitch for a slow agent (rad)."""
YAW_JUMP_SLOW_DISPLACEMENT_VEHICLE = 6.0
"""Filter e: "slow" threshold of the displacement proxy for vehicles (m)."""
YAW_JUMP_SLOW_DISPLACEMENT_OTHER = 1.0
"""Filter e: "slow" threshold for pedestrians and cyclists (m)."""
AGENT_PRUNE_START_RADIUS = 120.0
"""First radius of the agent distance pruning (filter f); halved after every pass (m)."""

# --------------------------------------------------------------------------- destination (1.7)
DEST_LANE_DISTANCE = 3.0
"""A lane node within this xy distance of the goal (with aligned direction) matches it (m)."""
DEST_EXTEND_SECONDS = 5.0
"""The extended goal is goal + this * speed * heading (s)."""
DEST_MAX_HOPS = 4
"""The lane-graph walk stops after this many hops."""
DEST_BRANCH_MIN_HOPS = 2
"""The walk stops at a branching lane once this many hops are done."""
