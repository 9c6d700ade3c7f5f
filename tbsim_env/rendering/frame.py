"""Dynamic layer: agents, traffic signals, trails and text drawn over a ``MapLayer``.

Everything here takes numpy arrays in the scenario frame (metres, radians CCW from +x). Callers
holding a ``SimState`` use ``render_state``, which adds the state's ``origin`` back.
"""

from __future__ import annotations

import functools
from collections.abc import Sequence

import numpy as np
import torch
from PIL import Image, ImageDraw, ImageFont

from tbsim_env.constants import DT, NUM_TL_STATES, SIGNAL_TO_TL_STATE, ObjectType, TLState
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


def agent_corners(xy: np.ndarray, yaw: np.ndarray, size: np.ndarray) -> np.ndarray:
    """Box corners of oriented rectangles.

    Args:
        xy: [N, 2] box centres, metres.
        yaw: [N] headings, radians CCW from +x.
        size: [N, 2] (length, width), metres.

    Returns:
        [N, 4, 2] corners (front-left, front-right, rear-right, rear-left), metres.
    """
    c, s = np.cos(yaw), np.sin(yaw)
    hl, hw = 0.5 * size[:, 0], 0.5 * size[:, 1]
    lon = np.array([1.0, 1.0, -1.0, -1.0])
    lat = np.array([1.0, -1.0, -1.0, 1.0])
    dx = lon[None] * hl[:, None]
    dy = lat[None] * hw[:, None]
    x = xy[:, None, 0] + c[:, None] * dx - s[:, None] * dy
    y = xy[:, None, 1] + s[:, None] * dx + c[:, None] * dy
    return np.stack([x, y], axis=-1)


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


def render_frame(
    map_layer: MapLayer,
    *,
    agent_xy: np.ndarray,
    agent_yaw: np.ndarray,
    agent_size: np.ndarray,
    agent_valid: np.ndarray,
    agent_group: np.ndarray,
    agent_type: np.ndarray | None = None,
    signal_xy: np.ndarray | None = None,
    signal_state: np.ndarray | None = None,
    signal_valid: np.ndarray | None = None,
    trails: np.ndarray | None = None,
    trail_valid: np.ndarray | None = None,
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
        agent_xy: [N, 2] box centres, metres, scenario frame.
        agent_yaw: [N] headings, radians CCW from +x.
        agent_size: [N, 2] (length, width) metres.
        agent_valid: [N] bool; invalid agents (and their trails) are not drawn.
        agent_group: [N] int ``AgentGroup`` values.
        agent_type: [N] int ``ObjectType`` values (optional; pedestrians are drawn as discs).
        signal_xy: [S, 2] stop points, metres, scenario frame.
        signal_state: [S] int ``TLState`` values 0..4.
        signal_valid: [S] bool (default: all valid).
        trails: [N, K, 2] past positions, metres, oldest first (non-finite points are skipped).
        trail_valid: [N, K] bool mask for ``trails`` (default: all finite points).
        title: text drawn at the top left (may hold newlines).
        legend: True for a legend of the groups of the drawn agents, a sequence of groups for a
            fixed legend, False for none.
        view: camera (default ``map_layer.view``); it must have the layer's resolution, e.g.
            ``follow(map_layer.view, xy)``.

    Returns:
        [H, W, 3] uint8 RGB image, north up.
    """
    view = map_layer.view if view is None else view
    n = np.asarray(agent_xy).shape[0]
    xy = _as("agent_xy", agent_xy, (n, 2), np.float64)
    yaw = _as("agent_yaw", agent_yaw, (n,), np.float64)
    size = _as("agent_size", agent_size, (n, 2), np.float64)
    valid = _as("agent_valid", agent_valid, (n,), bool)
    group = _as("agent_group", agent_group, (n,), np.int64)
    if ((group < 0) | (group >= _NUM_GROUPS)).any():
        raise ValueError(f"agent_group values must be AgentGroup 0..{_NUM_GROUPS - 1}")
    otype = (
        np.zeros(n, np.int64)
        if agent_type is None
        else _as("agent_type", agent_type, (n,), np.int64)
    )
    valid = valid & np.isfinite(xy).all(axis=1) & np.isfinite(yaw) & np.isfinite(size).all(axis=1)

    img = Image.fromarray(map_layer.background(view))
    draw = ImageDraw.Draw(img, "RGBA")
    mpp = view.meters_per_pixel
    h, w = view.size

    # Cull agents far outside the image.
    uv_c = view.to_pixels(np.where(valid[:, None], xy, 0.0))
    reach = 0.5 * np.hypot(size[:, 0], size[:, 1]) / mpp + P.AGENT_MIN_PX + 2
    on_img = (
        (uv_c[:, 0] > -reach) & (uv_c[:, 0] < w + reach)
        & (uv_c[:, 1] > -reach) & (uv_c[:, 1] < h + reach)
    )  # fmt: skip
    draw_mask = valid & on_img

    # Trails (under everything else dynamic).
    if trails is not None:
        k = np.asarray(trails).shape[1] if np.ndim(trails) == 3 else -1
        tr = _as("trails", trails, (n, k, 2), np.float64)
        tv = np.isfinite(tr).all(axis=-1)
        if trail_valid is not None:
            tv &= _as("trail_valid", trail_valid, (n, k), bool)
        tuv = view.to_pixels(np.where(tv[..., None], tr, 0.0)) - 0.5
        width = max(P.TRAIL_MIN_PX, int(round(P.TRAIL_WIDTH_M / mpp)))
        whole = tv.all(axis=1)  # the common case: one run over the whole trail
        for i in np.flatnonzero(valid & tv.any(axis=1)):
            color = tuple(_TRAIL_RGB[group[i]].tolist())
            runs = [(0, k)] if whole[i] else _valid_runs(tv[i])
            for a, b in runs:
                if b - a >= 2:
                    draw.line(tuv[i, a:b].reshape(-1).tolist(), fill=color, width=width)

    # Traffic signals at their stop points.
    if signal_xy is not None:
        s = np.asarray(signal_xy).shape[0]
        sxy = _as("signal_xy", signal_xy, (s, 2), np.float64)
        if signal_state is None:
            raise ValueError("signal_state is required with signal_xy")
        sst = _as("signal_state", signal_state, (s,), np.int64)
        svalid = (
            np.ones(s, bool)
            if signal_valid is None
            else _as("signal_valid", signal_valid, (s,), bool)
        )
        if ((sst[svalid] < 0) | (sst[svalid] >= NUM_TL_STATES)).any():
            raise ValueError(f"signal_state values must be TLState 0..{NUM_TL_STATES - 1}")
        r = max(P.SIGNAL_MIN_PX, P.SIGNAL_RADIUS_M / mpp)
        suv = view.to_pixels(sxy) - 0.5
        for j in np.flatnonzero(svalid & np.isfinite(sxy).all(axis=1)):
            u, v = suv[j]
            draw.ellipse(
                (u - r, v - r, u + r, v + r),
                fill=tuple(_TL_RGB[sst[j]].tolist()),
                outline=P.SIGNAL_OUTLINE,
            )

    # Agents, lowest group first so that highlighted ones end on top.
    min_m = P.AGENT_MIN_PX * mpp
    size_d = np.maximum(size, min_m)
    corners = view.to_pixels(agent_corners(xy, yaw, size_d)) - 0.5
    front = view.to_pixels(xy + 0.5 * size_d[:, :1] * np.stack([np.cos(yaw), np.sin(yaw)], 1))
    front -= 0.5
    centre = uv_c - 0.5
    tick_w = max(P.HEADING_TICK_MIN_PX, int(round(P.HEADING_TICK_WIDTH_M / mpp)))
    is_ped = otype == int(ObjectType.PEDESTRIAN)
    order = np.flatnonzero(draw_mask)
    order = order[np.argsort(group[order], kind="stable")]
    for i in order:
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

    if title:
        _draw_text_box(draw, (4, 4), title)
    if legend is True:
        present = sorted({int(g) for g in group[valid]})
        _draw_legend(draw, [AgentGroup(g) for g in present], h)
    elif legend:
        _draw_legend(draw, [AgentGroup(g) for g in legend], h)
    return np.asarray(img).copy()


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
    trails: np.ndarray | None = None,
    trail_valid: np.ndarray | None = None,
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
        trails: [N, K, 2] past positions, metres, in the SCENARIO frame (oldest first).
        trail_valid: [N, K] bool mask for ``trails``.
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
    return render_frame(
        map_layer,
        agent_xy=pose[:, :2] + origin,
        agent_yaw=pose[:, 2],
        agent_size=_np(state.agents.size[b, :, :2]),
        agent_valid=_np(state.valid[b] & state.agents.mask[b]),
        agent_group=groups,
        agent_type=_np(state.agents.object_type[b]),
        signal_xy=_np(sig.stop_point[b]).astype(np.float64) + origin,
        signal_state=_np(tl[b]),
        signal_valid=_np(tl_valid[b] & (sig.lane_id[b] >= 0)),
        trails=trails,
        trail_valid=trail_valid,
        title=title,
        legend=legend,
        view=view,
    )


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
    return render_frame(
        map_layer,
        agent_xy=t.xyz[:, step, :2],
        agent_yaw=t.heading[:, step],
        agent_size=t.size[:, step, :2],
        agent_valid=t.valid[:, step],
        agent_group=log_groups(scenario) if groups is None else groups,
        agent_type=t.object_type,
        signal_xy=sig.stop_point[:, :2],
        signal_state=_SIGNAL_TO_TL[sig.state[:, step].astype(np.int64)],
        signal_valid=sig.valid[:, step],
        trails=trails,
        trail_valid=trail_valid,
        title=title,
        legend=legend,
        view=view,
    )
