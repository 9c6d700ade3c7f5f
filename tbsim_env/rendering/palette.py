"""Colours and sizes of the bird's-eye renderer (the only home of rendering literals).

Colours are (R, G, B) uint8 tuples, or (R, G, B, A) where blended. Sizes in metres are drawn
with a minimum size in pixels so that zoomed-out images stay legible.
"""

from __future__ import annotations

import enum

from tbsim_env.core.constants import TLState

RGB = tuple[int, int, int]
RGBA = tuple[int, int, int, int]


class AgentGroup(enum.IntEnum):
    """Who drives an agent; selects its colour."""

    LOG_REPLAY = 0
    """Replayed from the log, or any other agent."""
    POLICY = 1
    """Driven by a policy NPC (e.g. TrafficBots)."""
    EXTERNAL = 2
    """Controlled from outside (the agent being trained or evaluated)."""
    SDC = 3
    """The self-driving car, or any agent to highlight."""


GROUP_COLORS: dict[AgentGroup, RGB] = {
    AgentGroup.LOG_REPLAY: (110, 150, 200),
    AgentGroup.POLICY: (255, 150, 40),
    AgentGroup.EXTERNAL: (60, 200, 90),
    AgentGroup.SDC: (230, 60, 220),
}
"""Fill colour of an agent per group."""

GROUP_LABELS: dict[AgentGroup, str] = {
    AgentGroup.LOG_REPLAY: "log replay",
    AgentGroup.POLICY: "policy NPC",
    AgentGroup.EXTERNAL: "external",
    AgentGroup.SDC: "SDC",
}
"""Legend text per group."""

TL_COLORS: dict[TLState, RGB] = {
    TLState.UNKNOWN: (150, 150, 150),
    TLState.STOP: (235, 40, 40),
    TLState.CAUTION: (250, 220, 40),
    TLState.GO: (40, 220, 70),
    TLState.FLASHING: (255, 140, 0),
}
"""Fill colour of a traffic-signal stop point per ``TLState``."""

# --------------------------------------------------------------------------- map
BACKGROUND: RGB = (92, 94, 100)
LANE_CENTER: RGB = (140, 142, 150)
BIKE_LANE_CENTER: RGB = (120, 170, 140)
ROAD_LINE_WHITE: RGB = (235, 235, 235)
ROAD_LINE_YELLOW: RGB = (240, 200, 40)
ROAD_LINE_UNKNOWN: RGB = (180, 180, 180)
ROAD_EDGE_BOUNDARY: RGB = (28, 28, 32)
ROAD_EDGE_MEDIAN: RGB = (45, 40, 60)
CROSSWALK: RGBA = (240, 240, 240, 90)
SPEED_BUMP: RGBA = (240, 170, 40, 110)
DRIVEWAY: RGBA = (70, 160, 200, 70)
STOP_SIGN: RGB = (210, 20, 20)
STOP_SIGN_OUTLINE: RGB = (255, 255, 255)

LANE_CENTER_WIDTH_M = 0.12
ROAD_LINE_WIDTH_M = 0.15
ROAD_EDGE_WIDTH_M = 0.5
DOUBLE_LINE_GAP_M = 0.2
"""Centre-to-centre half distance of the two strokes of a double road line."""
DASH_M = 3.0
GAP_M = 6.0
STOP_SIGN_RADIUS_M = 1.2

LANE_CENTER_MIN_PX = 1
ROAD_LINE_MIN_PX = 1
ROAD_EDGE_MIN_PX = 2
STOP_SIGN_MIN_PX = 5.0
STOP_SIGN_OUTLINE_PX = 1

# --------------------------------------------------------------------------- dynamic layer
AGENT_OUTLINE: RGB = (20, 20, 20)
HEADING_TICK: RGB = (15, 15, 15)
HEADING_TICK_WIDTH_M = 0.3
HEADING_TICK_MIN_PX = 2
AGENT_MIN_PX = 3.0
"""Smallest drawn length/width of an agent, pixels."""
PEDESTRIAN_MIN_RADIUS_M = 0.35
SIGNAL_RADIUS_M = 1.0
SIGNAL_MIN_PX = 3.0
SIGNAL_OUTLINE: RGB = (15, 15, 15)
TRAIL_MIX = 0.6
"""Trails are opaque: this fraction of the group colour, the rest background colour."""
TRAIL_WIDTH_M = 0.5
TRAIL_MIN_PX = 2
TEXT: RGB = (250, 250, 250)
TEXT_BOX: RGBA = (0, 0, 0, 140)
FONT_PX = 14
