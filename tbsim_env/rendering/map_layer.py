"""Static map layer: the road map rasterised once per scenario and reused by every frame.

Rasterising a WOMD map (hundreds of polylines, ~20k points) takes tens of milliseconds, so it is
done once, supersampled for anti-aliasing, into a canvas that may be larger than the view (for a
camera that follows an agent). Each frame then only copies a crop of the canvas and draws agents.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from PIL import Image, ImageDraw

from tbsim_env.core.constants import LaneType, MapFeatureType, RoadEdgeType, RoadLineType
from tbsim_env.data.scenario import RoadMap, Scenario
from tbsim_env.rendering import palette as P
from tbsim_env.rendering.view import View

DEFAULT_SUPERSAMPLE = 2
"""Map canvases are drawn at this many times the output resolution, then box-filtered."""
MAX_CANVAS_PX = 8192
"""Largest canvas side in output pixels (memory guard: 8192^2 x 3 B = 200 MB)."""

# (colour, strokes): one stroke per painted line, (side, dashed); side -1/+1 offsets a double
# line to the right/left of the polyline, 0 keeps it on the polyline.
_Stroke = tuple[int, bool]
_ROAD_LINE_STYLE: dict[int, tuple[P.RGB, tuple[_Stroke, ...]]] = {
    RoadLineType.UNKNOWN: (P.ROAD_LINE_UNKNOWN, ((0, False),)),
    RoadLineType.BROKEN_SINGLE_WHITE: (P.ROAD_LINE_WHITE, ((0, True),)),
    RoadLineType.SOLID_SINGLE_WHITE: (P.ROAD_LINE_WHITE, ((0, False),)),
    RoadLineType.SOLID_DOUBLE_WHITE: (P.ROAD_LINE_WHITE, ((-1, False), (1, False))),
    RoadLineType.BROKEN_SINGLE_YELLOW: (P.ROAD_LINE_YELLOW, ((0, True),)),
    RoadLineType.BROKEN_DOUBLE_YELLOW: (P.ROAD_LINE_YELLOW, ((-1, True), (1, True))),
    RoadLineType.SOLID_SINGLE_YELLOW: (P.ROAD_LINE_YELLOW, ((0, False),)),
    RoadLineType.SOLID_DOUBLE_YELLOW: (P.ROAD_LINE_YELLOW, ((-1, False), (1, False))),
    RoadLineType.PASSING_DOUBLE_YELLOW: (P.ROAD_LINE_YELLOW, ((-1, False), (1, True))),
}


def road_line_style(subtype: int) -> tuple[P.RGB, tuple[tuple[int, bool], ...]]:
    """Colour and strokes ``((side, dashed), ...)`` of a WOMD road-line subtype."""
    return _ROAD_LINE_STYLE.get(int(subtype), _ROAD_LINE_STYLE[RoadLineType.UNKNOWN])


def dash_runs(xy: np.ndarray, dash: float, gap: float) -> list[np.ndarray]:
    """Cut a polyline into dashes along its arc length.

    Args:
        xy: [n, 2] polyline points (any length unit).
        dash: painted length per period.
        gap: unpainted length per period.

    Returns:
        A list of [m_i, 2] polylines (m_i >= 2), the painted pieces in order. The pattern starts
        with a dash at the first point.
    """
    if xy.shape[0] < 2:
        return []
    seg = np.linalg.norm(np.diff(xy, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    total = s[-1]
    if total <= 0:
        return []
    period = dash + gap
    starts = np.arange(0.0, total, period)
    cuts = np.concatenate([starts, starts + dash])
    s_all = np.unique(np.concatenate([s, cuts[(cuts > 0) & (cuts < total)]]))
    pts = np.stack([np.interp(s_all, s, xy[:, 0]), np.interp(s_all, s, xy[:, 1])], axis=1)
    mids = 0.5 * (s_all[:-1] + s_all[1:])
    on = np.mod(mids, period) < dash
    edges = np.diff(np.concatenate([[0], on.astype(np.int8), [0]]))
    run_starts = np.flatnonzero(edges == 1)
    run_ends = np.flatnonzero(edges == -1)  # exclusive segment index
    return [pts[a : b + 1] for a, b in zip(run_starts, run_ends)]


def offset_polyline(xy: np.ndarray, distance: float) -> np.ndarray:
    """Shift a polyline sideways, to the LEFT of its direction for positive ``distance``.

    Args:
        xy: [n, 2] points, n >= 2.
        distance: offset in the units of ``xy``.

    Returns:
        [n, 2] shifted points (per-vertex normal = mean of the adjacent segment normals).
    """
    d = np.diff(xy, axis=0)
    length = np.linalg.norm(d, axis=1, keepdims=True)
    d = d / np.maximum(length, 1e-9)
    seg_n = np.stack([-d[:, 1], d[:, 0]], axis=1)
    n = np.empty_like(xy)
    n[0], n[-1] = seg_n[0], seg_n[-1]
    if xy.shape[0] > 2:
        mid = seg_n[:-1] + seg_n[1:]
        n[1:-1] = mid / np.maximum(np.linalg.norm(mid, axis=1, keepdims=True), 1e-9)
    return xy + distance * n


@dataclass(frozen=True, eq=False)
class MapLayer:
    """A rasterised road map plus the camera it was made for.

    Attributes:
        view: the default camera of frames drawn on this layer.
        canvas: [Hc, Wc, 3] uint8 raster of ``canvas_view`` (contains ``view``).
        canvas_view: the camera of ``canvas`` (same centre and resolution as ``view``).
        scenario_id: id of the scenario the map came from (for titles).
    """

    view: View
    canvas: np.ndarray
    canvas_view: View
    scenario_id: str

    @staticmethod
    def build(
        scenario: Scenario,
        view: View,
        *,
        pad_m: float = 0.0,
        supersample: int = DEFAULT_SUPERSAMPLE,
    ) -> MapLayer:
        """Rasterise the map of ``scenario`` for ``view``.

        Args:
            scenario: the scenario whose ``road_map`` is drawn.
            view: default camera.
            pad_m: extra metres rasterised on every side, so that cameras made with
                ``follow(view, xy)`` that stay within the pad need no new rasterisation.
            supersample: integer anti-aliasing factor (1 = none).

        Returns:
            The layer; ``layer.image`` is the [H, W, 3] uint8 map for ``view``.
        """
        if supersample < 1:
            raise ValueError(f"supersample must be >= 1, got {supersample}")
        canvas_view = view.padded(pad_m)
        if max(canvas_view.size) > MAX_CANVAS_PX:
            raise ValueError(
                f"map canvas {canvas_view.size} px exceeds {MAX_CANVAS_PX} px per side; "
                "use a smaller pad_m or a coarser view"
            )
        canvas = rasterize_map(scenario, canvas_view, supersample=supersample)
        return MapLayer(view, canvas, canvas_view, scenario.scenario_id)

    @property
    def image(self) -> np.ndarray:
        """[H, W, 3] uint8 map for the default view (a fresh copy)."""
        return self.background(self.view)

    def background(self, view: View | None = None) -> np.ndarray:
        """The map seen by ``view`` (default: ``self.view``), as a fresh [H, W, 3] uint8 array.

        ``view`` must have the layer's resolution; the part of it outside the canvas is filled
        with the background colour. Sub-pixel offsets are rounded to whole pixels.
        """
        view = self.view if view is None else view
        cv = self.canvas_view
        if abs(view.meters_per_pixel / cv.meters_per_pixel - 1.0) > 1e-6:
            raise ValueError(
                f"view resolution {view.meters_per_pixel:.4g} m/px differs from the map layer's "
                f"{cv.meters_per_pixel:.4g} m/px; build a MapLayer for this view"
            )
        u0, v0 = np.rint(cv.to_pixels(view.to_world(np.zeros(2)))).astype(np.int64)
        h, w = view.size
        hc, wc = cv.size
        if u0 == 0 and v0 == 0 and (h, w) == (hc, wc):
            return self.canvas.copy()
        out = np.empty((h, w, 3), np.uint8)
        out[:] = P.BACKGROUND
        r0, r1 = max(v0, 0), min(v0 + h, hc)
        c0, c1 = max(u0, 0), min(u0 + w, wc)
        if r0 < r1 and c0 < c1:
            out[r0 - v0 : r1 - v0, c0 - u0 : c1 - u0] = self.canvas[r0:r1, c0:c1]
        return out


def render_map(
    scenario: Scenario, view: View, *, supersample: int = DEFAULT_SUPERSAMPLE
) -> np.ndarray:
    """Rasterise the road map of ``scenario`` as seen by ``view``.

    Args:
        scenario: the scenario.
        view: camera.
        supersample: integer anti-aliasing factor (1 = none).

    Returns:
        [H, W, 3] uint8 RGB image, north up.
    """
    return rasterize_map(scenario, view, supersample=supersample)


def _width_px(width_m: float, mpp: float, min_px: int, ss: int) -> int:
    return max(min_px * ss, int(round(width_m / mpp)))


@dataclass(frozen=True)
class _Canvas:
    """What every map-drawing step shares: the drawing, the supersampled view, the map."""

    draw: ImageDraw.ImageDraw
    view: View  # supersampled
    ss: int
    road_map: RoadMap
    visible: np.ndarray  # [F] bool, the feature may touch the view

    def features(self, kind: MapFeatureType) -> np.ndarray:
        """Indices of the visible features of one type."""
        return np.flatnonzero((self.road_map.feature_type == int(kind)) & self.visible)

    def pixels(self, k: int) -> np.ndarray:
        """[P, 2] pixel coordinates of feature ``k``'s polyline."""
        # PIL puts integer coordinates on pixel centres; ours put them on pixel corners.
        return self.view.to_pixels(self.road_map.polylines[k][:, :2]) - 0.5

    def width(self, width_m: float, min_px: int) -> int:
        return _width_px(width_m, self.view.meters_per_pixel, min_px, self.ss)


def _flat(uv: np.ndarray) -> list[float]:
    return uv.reshape(-1).tolist()


def _visible_features(road_map: RoadMap, view: View) -> np.ndarray:
    """[F] bool: the feature's bounding box, grown by the widest stroke, touches ``view``."""
    x0, x1, y0, y1 = view.extent
    slack = 2.0 * P.ROAD_EDGE_WIDTH_M + 2.0 * P.STOP_SIGN_RADIUS_M + 4 * view.meters_per_pixel
    polys = road_map.polylines
    bb = np.array(
        [(p[:, 0].min(), p[:, 0].max(), p[:, 1].min(), p[:, 1].max()) for p in polys]
    ).reshape(-1, 4)
    return (
        (bb[:, 1] >= x0 - slack)
        & (bb[:, 0] <= x1 + slack)
        & (bb[:, 3] >= y0 - slack)
        & (bb[:, 2] <= y1 + slack)
    )


def _draw_areas(c: _Canvas) -> None:
    """Driveways, crosswalks and speed bumps as translucent polygons."""
    for kind, color in (
        (MapFeatureType.DRIVEWAY, P.DRIVEWAY),
        (MapFeatureType.CROSSWALK, P.CROSSWALK),
        (MapFeatureType.SPEED_BUMP, P.SPEED_BUMP),
    ):
        for k in c.features(kind):
            uv = c.pixels(k)
            if uv.shape[0] >= 3:
                c.draw.polygon(_flat(uv), fill=color)
            elif uv.shape[0] == 2:
                c.draw.line(_flat(uv), fill=color, width=c.width(1.0, 1))


def _draw_lanes(c: _Canvas) -> None:
    """Lane centre lines (bike lanes in their own colour)."""
    width = c.width(P.LANE_CENTER_WIDTH_M, P.LANE_CENTER_MIN_PX)
    for k in c.features(MapFeatureType.LANE):
        uv = c.pixels(k)
        if uv.shape[0] >= 2:
            bike = c.road_map.subtype[k] == LaneType.BIKE_LANE
            c.draw.line(_flat(uv), fill=P.BIKE_LANE_CENTER if bike else P.LANE_CENTER, width=width)


def _draw_road_lines(c: _Canvas) -> None:
    """Road lines, dashed / doubled by subtype."""
    mpp = c.view.meters_per_pixel
    w_line = c.width(P.ROAD_LINE_WIDTH_M, P.ROAD_LINE_MIN_PX)
    gap_px = P.DOUBLE_LINE_GAP_M / mpp
    for k in c.features(MapFeatureType.ROAD_LINE):
        uv = c.pixels(k)
        if uv.shape[0] < 2:
            continue
        color, strokes = road_line_style(c.road_map.subtype[k])
        width = w_line
        if len(strokes) == 2 and gap_px < w_line:
            # Too small to separate the two strokes: one wider stroke, solid if either is.
            strokes, width = ((0, strokes[0][1] and strokes[1][1]),), 2 * w_line
        for side, dashed in strokes:
            # Image rows grow downwards, so the image-space left normal is the world right.
            line = offset_polyline(uv, -side * gap_px) if side else uv
            pieces = dash_runs(line, P.DASH_M / mpp, P.GAP_M / mpp) if dashed else [line]
            for piece in pieces:
                c.draw.line(_flat(piece), fill=color, width=width)


def _draw_road_edges(c: _Canvas) -> None:
    """Road edges (medians in their own colour)."""
    width = c.width(P.ROAD_EDGE_WIDTH_M, P.ROAD_EDGE_MIN_PX)
    for k in c.features(MapFeatureType.ROAD_EDGE):
        uv = c.pixels(k)
        if uv.shape[0] >= 2:
            median = c.road_map.subtype[k] == RoadEdgeType.MEDIAN
            color = P.ROAD_EDGE_MEDIAN if median else P.ROAD_EDGE_BOUNDARY
            c.draw.line(_flat(uv), fill=color, width=width, joint="curve")


def _draw_stop_signs(c: _Canvas) -> None:
    """Stop signs: red octagons."""
    r = max(P.STOP_SIGN_MIN_PX * c.ss, P.STOP_SIGN_RADIUS_M / c.view.meters_per_pixel)
    for k in c.features(MapFeatureType.STOP_SIGN):
        u, v = c.pixels(k)[0]
        c.draw.regular_polygon(
            (float(u), float(v), float(r)),
            8,
            rotation=22.5,
            fill=P.STOP_SIGN,
            outline=P.STOP_SIGN_OUTLINE,
            width=P.STOP_SIGN_OUTLINE_PX * c.ss,
        )


def rasterize_map(scenario: Scenario, view: View, *, supersample: int = 1) -> np.ndarray:
    """Draw every map feature of ``scenario`` that touches ``view``.

    Order (bottom to top): driveways, crosswalks, speed bumps (translucent polygons), lane centre
    lines, road lines, road edges, stop signs.

    Args:
        scenario: the scenario.
        view: camera.
        supersample: integer anti-aliasing factor; the image is drawn at ``supersample`` times
            the resolution and box-filtered down.

    Returns:
        [H, W, 3] uint8 RGB.
    """
    ss = int(supersample)
    sv = view.scaled(ss)
    img = Image.new("RGB", (sv.width, sv.height), P.BACKGROUND)
    rm = scenario.road_map
    if rm.num_features:
        visible = _visible_features(rm, view)
        canvas = _Canvas(ImageDraw.Draw(img, "RGBA"), sv, ss, rm, visible)
        for step in (_draw_areas, _draw_lanes, _draw_road_lines, _draw_road_edges):
            step(canvas)
        _draw_stop_signs(canvas)
    if ss > 1:
        img = img.reduce(ss)
    return np.asarray(img).copy()
