"""Dynamic layer: agents, traffic signals, trails and text drawn over a ``MapLayer``.

Everything here takes numpy arrays in the scenario frame (metres, radians CCW from +x). Callers
holding a ``SimState`` use ``render_state``, which adds the state's ``origin`` back.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from tbsim_env.core.boxes import box_corners_numpy
from tbsim_env.core.constants import DT, NUM_TL_STATES, SIGNAL_TO_TL_STATE, ObjectType, TLState
from tbsim_env.data.scenario import Scenario
from tbsim_env.rendering import palette as P
from tbsim_env.rendering.map_layer import MapLayer
from tbsim_env.rendering.palette import AgentGroup
from tbsim_env.rendering.view import View
from tbsim_env.sim.state import SimState

_NUM_GROUPS = len(AgentGroup)
_GROUP_RGB = np.array([P.GROUP_COLORS[g] for g in AgentGroup], np.uint8)
_TRAIL_RGB = np.rint(
    P.TRAIL_MIX * _GROUP_RGB + (1.0 - P.TRAIL_MIX) * np.asarray(P.BACKGROUND)
).astype(np.uint8)
_TL_RGB = np.array([P.TL_COLORS[TLState(s)] for s in range(NUM_TL_STATES)], np.uint8)
_SIGNAL_TO_TL = np.asarray(SIGNAL_TO_TL_STATE, np.int64)


@functools.lru_cache(maxsize=8)
def _font(size: int) -> ImageFont.ImageFont | ImageFont.FreeTypeFont:
    try:
        return ImageFont.load_default(size=size)
    except (TypeError, OSError, ImportError):  # Pillow without FreeType
        return ImageFont.load_default()


def _as(name: str, value: np.ndarray, shape: tuple[int, ...], dtype: type) -> np.ndarray:
    arr = np.asarray(value)
    if arr.shape != shape:
        raise ValueError(f"{name} has shape {arr.shape}, expected {shape}")
    return arr.astype(dtype, copy=False)


def _draw_text_box(
    draw: ImageDraw.ImageDraw, xy: tuple[float, float], text: str, *, anchor_bottom: bool = False
) -> None:
    font = _font(P.FONT_PX)
    pad = 4
    left, top, right, bottom = draw.multiline_textbbox((0, 0), text, font=font, spacing=2)
    x, y = xy
    if anchor_bottom:
        y = y - (bottom - top) - 2 * pad
    draw.rectangle((x, y, x + right - left + 2 * pad, y + bottom - top + 2 * pad), fill=P.TEXT_BOX)
    draw.multiline_text((x + pad - left, y + pad - top), text, fill=P.TEXT, font=font, spacing=2)


def _draw_legend(draw: ImageDraw.ImageDraw, groups: Sequence[AgentGroup], height: int) -> None:
    if not groups:
        return
    font = _font(P.FONT_PX)
    pad, sw, row = 4, 10, P.FONT_PX + 4
    labels = [P.GROUP_LABELS[g] for g in groups]
    text_w = max(draw.textbbox((0, 0), s, font=font)[2] for s in labels)
    box_h = row * len(groups) + 2 * pad
    x0, y0 = 4, height - 4 - box_h
    draw.rectangle((x0, y0, x0 + 3 * pad + sw + text_w, y0 + box_h), fill=P.TEXT_BOX)
    for i, (g, label) in enumerate(zip(groups, labels)):
        y = y0 + pad + i * row
        draw.rectangle(
            (x0 + pad, y + 2, x0 + pad + sw, y + 2 + sw),
            fill=P.GROUP_COLORS[g],
            outline=P.AGENT_OUTLINE,
        )
        draw.text((x0 + 2 * pad + sw, y), label, fill=P.TEXT, font=font)


def _valid_runs(valid: np.ndarray) -> list[tuple[int, int]]:
    """(start, stop) index pairs of runs of True in a 1-D bool array."""
    edges = np.diff(np.concatenate([[0], valid.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)))


@dataclass(frozen=True)
class AgentLayer:
    """The agents of one frame (numpy, scenario frame).

    Attributes:
        xy: [N, 2] box centres, metres.
        yaw: [N] headings, radians CCW from +x.
        size: [N, 2] (length, width) metres.
        valid: [N] bool; invalid agents (and their trails) are not drawn.
        group: [N] int ``AgentGroup`` values.
        type: [N] int ``ObjectType`` values (optional; pedestrians are drawn as discs).
        trails: [N, K, 2] past positions, metres, oldest first (non-finite points skipped).
        trail_valid: [N, K] bool mask for ``trails`` (default: all finite points).
    """

    xy: np.ndarray
    yaw: np.ndarray
    size: np.ndarray
    valid: np.ndarray
    group: np.ndarray
    type: np.ndarray | None = None
    trails: np.ndarray | None = None
    trail_valid: np.ndarray | None = None

    def checked(self) -> AgentLayer:
        """The same layer as arrays of checked shapes and dtypes; ``valid`` also False where
        a value is not finite.

        Raises:
            ValueError: a wrong shape, or a group outside ``AgentGroup``.
        """
        n = np.asarray(self.xy).shape[0]
        xy = _as("agent_xy", self.xy, (n, 2), np.float64)
        yaw = _as("agent_yaw", self.yaw, (n,), np.float64)
        size = _as("agent_size", self.size, (n, 2), np.float64)
        group = _as("agent_group", self.group, (n,), np.int64)
        if ((group < 0) | (group >= _NUM_GROUPS)).any():
            raise ValueError(f"agent_group values must be AgentGroup 0..{_NUM_GROUPS - 1}")
        otype = np.zeros(n, np.int64) if self.type is None else self.type
        valid = _as("agent_valid", self.valid, (n,), bool)
        valid = valid & np.isfinite(xy).all(1) & np.isfinite(yaw) & np.isfinite(size).all(1)
        trails, trail_valid = None, None
        if self.trails is not None:
            k = np.asarray(self.trails).shape[1] if np.ndim(self.trails) == 3 else -1
            trails = _as("trails", self.trails, (n, k, 2), np.float64)
            trail_valid = np.isfinite(trails).all(axis=-1)
            if self.trail_valid is not None:
                trail_valid &= _as("trail_valid", self.trail_valid, (n, k), bool)
        otype = _as("agent_type", otype, (n,), np.int64)
        return AgentLayer(xy, yaw, size, valid, group, otype, trails, trail_valid)


@dataclass(frozen=True)
class SignalLayer:
    """The traffic signals of one frame, drawn at their stop points.

    Attributes:
        xy: [S, 2] stop points, metres, scenario frame.
        state: [S] int ``TLState`` values 0..4.
        valid: [S] bool (default: all valid).
    """

    xy: np.ndarray
    state: np.ndarray
    valid: np.ndarray | None = None


def render_frame(
    map_layer: MapLayer,
    agents: AgentLayer,
    signals: SignalLayer | None = None,
    *,
    title: str | None = None,
    legend: bool | Sequence[AgentGroup] = True,
    view: View | None = None,
) -> np.ndarray:
    """Draw one bird's-eye frame over a pre-rasterised map.

    Agents are oriented rectangles (pedestrians: discs) filled with their group colour, with a
    dark outline and a heading tick from the centre to the middle of the front edge; highlighted
    groups are drawn last (on top). Signals are discs at their stop points coloured by state.

    Args:
        map_layer: the scenario's map raster.
        agents: the agents (and their trails).
        signals: the traffic signals (optional).
        title: text drawn at the top left (may hold newlines).
        legend: True for a legend of the groups of the drawn agents, a sequence of groups for a
            fixed legend, False for none.
        view: camera (default ``map_layer.view``); it must have the layer's resolution, e.g.
            ``follow(map_layer.view, xy)``.

    Returns:
        [H, W, 3] uint8 RGB image, north up.

    Raises:
        ValueError: arrays of the wrong shape, or group / signal state values out of range.
    """
    view = map_layer.view if view is None else view
    agents = agents.checked()
    img = Image.fromarray(map_layer.background(view))
    draw = ImageDraw.Draw(img, "RGBA")
    if agents.trails is not None:  # under everything else dynamic
        _draw_trails(draw, view, agents)
    if signals is not None:
        _draw_signals(draw, view, signals)
    _draw_agents(draw, view, agents)
    if title:
        _draw_text_box(draw, (4, 4), title)
    if legend is True:
        present = sorted({int(g) for g in agents.group[agents.valid]})
        _draw_legend(draw, [AgentGroup(g) for g in present], view.size[0])
    elif legend:
        _draw_legend(draw, [AgentGroup(g) for g in legend], view.size[0])
    return np.asarray(img).copy()


def _draw_trails(draw: ImageDraw.ImageDraw, view: View, agents: AgentLayer) -> None:
    """Each valid agent's trail as lines of its group's trail colour (runs of valid points)."""
    tv, k = agents.trail_valid, agents.trails.shape[1]
    tuv = view.to_pixels(np.where(tv[..., None], agents.trails, 0.0)) - 0.5
    width = max(P.TRAIL_MIN_PX, int(round(P.TRAIL_WIDTH_M / view.meters_per_pixel)))
    whole = tv.all(axis=1)  # the common case: one run over the whole trail
    for i in np.flatnonzero(agents.valid & tv.any(axis=1)):
        color = tuple(_TRAIL_RGB[agents.group[i]].tolist())
        for a, b in [(0, k)] if whole[i] else _valid_runs(tv[i]):
            if b - a >= 2:
                draw.line(tuv[i, a:b].reshape(-1).tolist(), fill=color, width=width)


def _draw_signals(draw: ImageDraw.ImageDraw, view: View, signals: SignalLayer) -> None:
    """Discs at the valid signals' stop points, coloured by state."""
    s = np.asarray(signals.xy).shape[0]
    sxy = _as("signal_xy", signals.xy, (s, 2), np.float64)
    sst = _as("signal_state", signals.state, (s,), np.int64)
    valid = np.ones(s, bool) if signals.valid is None else signals.valid
    valid = _as("signal_valid", valid, (s,), bool)
    if ((sst[valid] < 0) | (sst[valid] >= NUM_TL_STATES)).any():
        raise ValueError(f"signal_state values must be TLState 0..{NUM_TL_STATES - 1}")
    r = max(P.SIGNAL_MIN_PX, P.SIGNAL_RADIUS_M / view.meters_per_pixel)
    suv = view.to_pixels(sxy) - 0.5
    for j in np.flatnonzero(valid & np.isfinite(sxy).all(axis=1)):
        u, v = suv[j]
        fill = tuple(_TL_RGB[sst[j]].tolist())
        draw.ellipse((u - r, v - r, u + r, v + r), fill=fill, outline=P.SIGNAL_OUTLINE)


def _on_image(view: View, agents: AgentLayer, uv: np.ndarray) -> np.ndarray:
    """[N] bool: the agent's box may reach into the image (centres ``uv`` in pixels)."""
    h, w = view.size
    reach = 0.5 * np.hypot(agents.size[:, 0], agents.size[:, 1]) / view.meters_per_pixel
    reach = reach + P.AGENT_MIN_PX + 2
    return (
        (uv[:, 0] > -reach) & (uv[:, 0] < w + reach)
        & (uv[:, 1] > -reach) & (uv[:, 1] < h + reach)
    )  # fmt: skip


def _draw_agents(draw: ImageDraw.ImageDraw, view: View, agents: AgentLayer) -> None:
    """Boxes (pedestrians: discs) and heading ticks, lowest group first (highlights on top)."""
    mpp = view.meters_per_pixel
    xy, yaw, size, group = agents.xy, agents.yaw, agents.size, agents.group
    uv = view.to_pixels(np.where(agents.valid[:, None], xy, 0.0))
    size_d = np.maximum(size, P.AGENT_MIN_PX * mpp)
    corners = view.to_pixels(box_corners_numpy(xy, yaw, size_d[:, 0], size_d[:, 1])) - 0.5
    front = view.to_pixels(xy + 0.5 * size_d[:, :1] * np.stack([np.cos(yaw), np.sin(yaw)], 1))
    front -= 0.5
    centre = uv - 0.5
    tick_w = max(P.HEADING_TICK_MIN_PX, int(round(P.HEADING_TICK_WIDTH_M / mpp)))
    is_ped = agents.type == int(ObjectType.PEDESTRIAN)
    order = np.flatnonzero(agents.valid & _on_image(view, agents, uv))
    for i in order[np.argsort(group[order], kind="stable")]:
        fill = tuple(_GROUP_RGB[group[i]].tolist())
        if is_ped[i]:
            r = max(P.PEDESTRIAN_MIN_RADIUS_M, 0.5 * max(size[i, 0], size[i, 1])) / mpp
            r = max(r, 0.5 * P.AGENT_MIN_PX)
            u, v = centre[i]
            draw.ellipse((u - r, v - r, u + r, v + r), fill=fill, outline=P.AGENT_OUTLINE)
        else:
            draw.polygon(corners[i].reshape(-1).tolist(), fill=fill, outline=P.AGENT_OUTLINE)
        draw.line(
            (centre[i, 0], centre[i, 1], front[i, 0], front[i, 1]),
            fill=P.HEADING_TICK,
            width=tick_w if size_d[i, 1] >= 3 * tick_w * mpp else 1,
        )


def _np(t: torch.Tensor) -> np.ndarray:
    return t.detach().cpu().numpy()


def default_groups(state: SimState, batch_index: int) -> np.ndarray:
    """[N] AgentGroup per slot: controlled agents POLICY, the SDC SDC, the rest LOG_REPLAY."""
    b = batch_index
    groups = np.where(_np(state.controlled[b]), AgentGroup.POLICY, AgentGroup.LOG_REPLAY)
    groups[_np(state.agents.role[b, :, 0])] = AgentGroup.SDC
    return groups.astype(np.int64)


def render_state(
    map_layer: MapLayer,
    state: SimState,
    batch_index: int,
    groups: np.ndarray | None = None,
    *,
    trails: tuple[np.ndarray, np.ndarray] | None = None,
    title: str | None = None,
    legend: bool | Sequence[AgentGroup] = True,
    view: View | None = None,
) -> np.ndarray:
    """Draw scenario ``batch_index`` of a ``SimState`` (origin added back, scenario frame).

    Args:
        map_layer: map raster of that scenario.
        state: batched simulator state.
        batch_index: which scenario of the batch.
        groups: [N] ``AgentGroup`` per agent slot (default: ``default_groups``).
        trails: (positions [N, K, 2] metres in the SCENARIO frame, oldest first; valid
            [N, K] bool): past positions drawn behind the agents.
        title: text; default ``"<scenario id>  t = <step * DT> s"``.
        legend: as in ``render_frame``.
        view: camera (default ``map_layer.view``).

    Returns:
        [H, W, 3] uint8 RGB.
    """
    b = batch_index
    if not 0 <= b < state.batch_size:
        raise IndexError(f"batch_index {b} outside [0, {state.batch_size})")
    origin = _np(state.origin[b]).astype(np.float64)
    pose = _np(state.pose[b]).astype(np.float64)
    groups = default_groups(state, b) if groups is None else np.asarray(groups)
    tl, tl_valid = state.tl_state_now()
    sig = state.signals
    if title is None:
        title = f"{map_layer.scenario_id}  t = {int(state.step[b]) * DT:.1f} s"
    agents = AgentLayer(
        xy=pose[:, :2] + origin,
        yaw=pose[:, 2],
        size=_np(state.agents.size[b, :, :2]),
        valid=_np(state.valid[b] & state.agents.mask[b]),
        group=groups,
        type=_np(state.agents.object_type[b]),
        trails=None if trails is None else trails[0],
        trail_valid=None if trails is None else trails[1],
    )
    signals = SignalLayer(
        xy=_np(sig.stop_point[b]).astype(np.float64) + origin,
        state=_np(tl[b]),
        valid=_np(tl_valid[b] & (sig.lane_id[b] >= 0)),
    )
    return render_frame(map_layer, agents, signals, title=title, legend=legend, view=view)


def log_groups(scenario: Scenario) -> np.ndarray:
    """[A] AgentGroup for a log replay: all LOG_REPLAY, the SDC highlighted as SDC."""
    groups = np.full(scenario.tracks.num_tracks, int(AgentGroup.LOG_REPLAY), np.int64)
    groups[scenario.sdc_index] = int(AgentGroup.SDC)
    return groups


def render_log_frame(
    map_layer: MapLayer,
    scenario: Scenario,
    step: int,
    *,
    groups: np.ndarray | None = None,
    trail_steps: int = 10,
    title: str | None = None,
    legend: bool | Sequence[AgentGroup] = True,
    view: View | None = None,
) -> np.ndarray:
    """Draw the logged scene of ``scenario`` at log step ``step``.

    Args:
        map_layer: map raster of ``scenario``.
        scenario: the scenario.
        step: log step index in [0, T).
        groups: [A] ``AgentGroup`` per track (default ``log_groups``).
        trail_steps: past steps drawn as a trail (0 for none).
        title: text; default ``"<scenario id>  t = <time since step 0> s"``.
        legend: as in ``render_frame``.
        view: camera (default ``map_layer.view``).

    Returns:
        [H, W, 3] uint8 RGB.
    """
    t = scenario.tracks
    if not 0 <= step < t.num_steps:
        raise IndexError(f"step {step} outside [0, {t.num_steps})")
    sig = scenario.signals
    trails = trail_valid = None
    if trail_steps > 0:
        lo = max(0, step - trail_steps)
        trails = t.xyz[:, lo : step + 1, :2]
        trail_valid = t.valid[:, lo : step + 1]
    if title is None:
        time_s = float(scenario.timestamps[step] - scenario.timestamps[0])
        title = f"{scenario.scenario_id}  t = {time_s:.1f} s"
    agents = AgentLayer(
        xy=t.xyz[:, step, :2],
        yaw=t.heading[:, step],
        size=t.size[:, step, :2],
        valid=t.valid[:, step],
        group=log_groups(scenario) if groups is None else groups,
        type=t.object_type,
        trails=trails,
        trail_valid=trail_valid,
    )
    signals = SignalLayer(
        xy=sig.stop_point[:, :2],
        state=_SIGNAL_TO_TL[sig.state[:, step].astype(np.int64)],
        valid=sig.valid[:, step],
    )
    return render_frame(map_layer, agents, signals, title=title, legend=legend, view=view)
