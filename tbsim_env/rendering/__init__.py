"""Fast headless bird's-eye rendering: a map raster built once, agents drawn per frame, videos.

Typical use::

    view = view_for(scenario, size=(600, 600))
    layer = MapLayer.build(scenario, view)
    frame = render_frame(layer, AgentLayer(xy=..., yaw=..., size=..., valid=..., group=...))
    # np.uint8 [600, 600, 3], north up
    write_video(frames, "out.mp4", fps=10)
"""

from tbsim_env.rendering.frame import (
    AgentLayer,
    SignalLayer,
    default_groups,
    log_groups,
    render_frame,
    render_log_frame,
    render_state,
)
from tbsim_env.rendering.map_layer import MapLayer, render_map
from tbsim_env.rendering.palette import GROUP_COLORS, GROUP_LABELS, TL_COLORS, AgentGroup
from tbsim_env.rendering.video import render_log_video, write_video
from tbsim_env.rendering.view import View, follow, view_for

__all__ = [
    "AgentLayer",
    "SignalLayer",
    "GROUP_COLORS",
    "GROUP_LABELS",
    "TL_COLORS",
    "AgentGroup",
    "MapLayer",
    "View",
    "default_groups",
    "follow",
    "log_groups",
    "render_frame",
    "render_log_frame",
    "render_log_video",
    "render_map",
    "render_state",
    "view_for",
    "write_video",
]
