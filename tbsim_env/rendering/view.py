"""Camera of a bird's-eye image: which scenario-frame rectangle lands on which pixels.

Image convention: north up. Column ``u`` grows with +x (east), row ``v`` grows with -y, so the
scenario's +y axis points UP in the image. Continuous pixel coordinates put pixel ``(v, u)`` on
the square ``[u, u + 1) x [v, v + 1)``; the view centre lands on ``(W / 2, H / 2)``.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from tbsim_env.data.scenario import Scenario

DEFAULT_MARGIN_M = 10.0
"""Metres of context around the relevant agents in ``view_for``."""
MIN_VIEW_WIDTH_M = 60.0
"""``view_for`` never zooms in further than this (metres across the shorter image side)."""
MAX_VIEW_WIDTH_M = 400.0
"""``view_for`` never zooms out further than this unless the whole map is shown."""
SMALL_MAP_M = 160.0
"""A map whose bounding box fits within this many metres is shown whole by ``view_for``."""


@dataclass(frozen=True)
class View:
    """An axis-aligned, north-up camera.

    Attributes:
        center: (x, y) metres in the scenario frame, shown at the image centre.
        meters_per_pixel: ground sampling distance, metres per pixel (> 0).
        height: image height H in pixels.
        width: image width W in pixels.
    """

    center: tuple[float, float]
    meters_per_pixel: float
    height: int
    width: int

    def __post_init__(self) -> None:
        if not (np.isfinite(self.meters_per_pixel) and self.meters_per_pixel > 0):
            raise ValueError(f"meters_per_pixel must be > 0, got {self.meters_per_pixel}")
        if self.height < 1 or self.width < 1:
            raise ValueError(f"image size must be positive, got {(self.height, self.width)}")
        if len(self.center) != 2 or not np.isfinite(self.center).all():
            raise ValueError(f"center must be two finite numbers, got {self.center}")
        object.__setattr__(self, "center", (float(self.center[0]), float(self.center[1])))
        object.__setattr__(self, "meters_per_pixel", float(self.meters_per_pixel))
        object.__setattr__(self, "height", int(self.height))
        object.__setattr__(self, "width", int(self.width))

    @staticmethod
    def from_width(
        center: tuple[float, float] | np.ndarray, width_m: float, size: tuple[int, int]
    ) -> View:
        """A view ``width_m`` metres across the image width.

        Args:
            center: (x, y) metres, scenario frame.
            width_m: metres spanned by the W pixels of a row.
            size: (H, W) pixels.
        """
        h, w = size
        return View((float(center[0]), float(center[1])), width_m / w, h, w)

    @property
    def size(self) -> tuple[int, int]:
        """(H, W) pixels."""
        return (self.height, self.width)

    @property
    def width_m(self) -> float:
        """Metres across the image width."""
        return self.width * self.meters_per_pixel

    @property
    def height_m(self) -> float:
        """Metres across the image height."""
        return self.height * self.meters_per_pixel

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) metres covered by the image."""
        cx, cy = self.center
        hw, hh = 0.5 * self.width_m, 0.5 * self.height_m
        return (cx - hw, cx + hw, cy - hh, cy + hh)

    def to_pixels(self, xy: np.ndarray) -> np.ndarray:
        """Scenario-frame points to continuous pixel coordinates.

        Args:
            xy: [..., 2] metres (x, y), scenario frame.

        Returns:
            [..., 2] float64 (u column, v row); pixel (v, u) covers [u, u+1) x [v, v+1).
        """
        xy = np.asarray(xy, dtype=np.float64)
        u = (xy[..., 0] - self.center[0]) / self.meters_per_pixel + 0.5 * self.width
        v = 0.5 * self.height - (xy[..., 1] - self.center[1]) / self.meters_per_pixel
        return np.stack([u, v], axis=-1)

    def to_world(self, uv: np.ndarray) -> np.ndarray:
        """Inverse of ``to_pixels``: [..., 2] (u, v) pixels -> [..., 2] (x, y) metres."""
        uv = np.asarray(uv, dtype=np.float64)
        x = (uv[..., 0] - 0.5 * self.width) * self.meters_per_pixel + self.center[0]
        y = (0.5 * self.height - uv[..., 1]) * self.meters_per_pixel + self.center[1]
        return np.stack([x, y], axis=-1)

    def scaled(self, factor: int) -> View:
        """The same ground rectangle at ``factor`` times the resolution (for supersampling)."""
        return View(
            self.center, self.meters_per_pixel / factor, self.height * factor, self.width * factor
        )

    def padded(self, pad_m: float) -> View:
        """The same centre and resolution, grown by ``pad_m`` metres on every side."""
        pad_px = int(np.ceil(max(pad_m, 0.0) / self.meters_per_pixel))
        return View(
            self.center, self.meters_per_pixel, self.height + 2 * pad_px, self.width + 2 * pad_px
        )


def follow(view: View, xy: np.ndarray | tuple[float, float]) -> View:
    """A camera with the same zoom and size, centred on ``xy`` (e.g. an agent's position).

    Args:
        view: the camera to move.
        xy: [2] metres, scenario frame.
    """
    xy = np.asarray(xy, dtype=np.float64).reshape(-1)
    return dataclasses.replace(view, center=(float(xy[0]), float(xy[1])))


def map_bounds(scenario: Scenario) -> tuple[float, float, float, float] | None:
    """(x_min, x_max, y_min, y_max) metres of all map points, or None for an empty map."""
    pls = scenario.road_map.polylines
    if not pls:
        return None
    pts = np.concatenate([p[:, :2] for p in pls], axis=0)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    return (float(lo[0]), float(hi[0]), float(lo[1]), float(hi[1]))


def view_for(
    scenario: Scenario,
    size: tuple[int, int] = (600, 600),
    margin: float = DEFAULT_MARGIN_M,
    *,
    min_width_m: float = MIN_VIEW_WIDTH_M,
    max_width_m: float = MAX_VIEW_WIDTH_M,
    small_map_m: float = SMALL_MAP_M,
) -> View:
    """A north-up view centred on the SDC that fits the relevant agents over the whole log.

    Relevant agents are the SDC, ``tracks_to_predict`` and ``objects_of_interest``; all their
    valid positions over every step must fit, plus ``margin`` metres. When the whole map fits
    within ``small_map_m`` metres it is shown instead (centred on its bounding box).

    Args:
        scenario: the scenario to frame.
        size: (H, W) image size in pixels.
        margin: metres of context added on every side.
        min_width_m: lower bound on the metres spanned by the shorter image side.
        max_width_m: upper bound on that span (the SDC stays centred; far agents may fall out).
        small_map_m: a map whose bounding box is at most this wide and high is shown whole.

    Returns:
        The view; ``meters_per_pixel`` is the same along both axes.
    """
    h, w = size
    bounds = map_bounds(scenario)
    if bounds is not None:
        x0, x1, y0, y1 = bounds
        if max(x1 - x0, y1 - y0) <= small_map_m:
            cx, cy = 0.5 * (x0 + x1), 0.5 * (y0 + y1)
            half_x = 0.5 * (x1 - x0) + margin
            half_y = 0.5 * (y1 - y0) + margin
            mpp = max(2 * half_x / w, 2 * half_y / h, min_width_m / min(h, w))
            return View((cx, cy), mpp, h, w)

    t = scenario.tracks
    sdc = scenario.sdc_index
    cur = scenario.current_index
    if t.valid[sdc, cur]:
        center = t.xyz[sdc, cur, :2]
    elif t.valid[sdc].any():
        center = t.xyz[sdc, int(np.flatnonzero(t.valid[sdc])[0]), :2]
    else:
        center = t.xyz[..., :2][t.valid].mean(axis=0) if t.valid.any() else np.zeros(2)
    relevant = scenario.role_mask().any(axis=1)
    pts = t.xyz[relevant][..., :2][t.valid[relevant]]
    if pts.size:
        half = np.abs(pts - center).max(axis=0) + margin
    else:
        half = np.array([margin, margin])
    mpp = max(2 * half[0] / w, 2 * half[1] / h)
    mpp = min(max(mpp, min_width_m / min(h, w)), max_width_m / min(h, w))
    return View((float(center[0]), float(center[1])), mpp, h, w)
