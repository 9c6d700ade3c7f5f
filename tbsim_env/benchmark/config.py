"""Thresholds and weights of the closed-loop planner benchmark, with their sources.

Every number the benchmark's metrics and scores use lives here; ``docs/benchmark.md`` states
the definitions. Sources: nuPlan's closed-loop score (its devkit's metric configurations and
its documentation of the CLS), NAVSIM's PDM score (its ``docs/metrics.md``), and, where WOMD
data differ from nuPlan's (no lane polygons, no static-object class), the adaptation stated
beside the field.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ComfortBounds:
    """Bounds of nuPlan's ``ego_is_comfortable`` (all must hold at every step).

    Attributes:
        min_lon_accel: m/s^2, lowest longitudinal acceleration (-4.05).
        max_lon_accel: m/s^2, highest longitudinal acceleration (2.40).
        max_abs_lat_accel: m/s^2, |lateral acceleration| (4.89).
        max_abs_yaw_rate: rad/s, |yaw rate| (0.95).
        max_abs_yaw_accel: rad/s^2, |yaw acceleration| (1.93).
        max_abs_lon_jerk: m/s^3, |longitudinal jerk| (4.13).
        max_abs_jerk: m/s^3, magnitude of the jerk vector (8.37).
        accel_window: samples of the Savitzky-Golay filter (polynomial order 2) that
            differentiates the speed into accelerations and those into jerks (nuPlan: 15).
        yaw_window: samples of the filter that differentiates the heading into yaw rate and
            yaw acceleration (nuPlan's ``approximate_derivatives`` default: 5).
    """

    min_lon_accel: float = -4.05
    max_lon_accel: float = 2.40
    max_abs_lat_accel: float = 4.89
    max_abs_yaw_rate: float = 0.95
    max_abs_yaw_accel: float = 1.93
    max_abs_lon_jerk: float = 4.13
    max_abs_jerk: float = 8.37
    accel_window: int = 15
    yaw_window: int = 5


@dataclass(frozen=True)
class BenchmarkConfig:
    """The benchmark's rules (nuPlan's values unless said otherwise).

    Attributes:
        stopped_speed: m/s below which an agent counts as stopped in collision
            classification (nuPlan: 5e-2).
        drivable_violation: m an ego box corner may lie beyond a road edge before drivable-
            area compliance fails (nuPlan: 0.3).
        direction_window_s: s of the window over which progress against the lane direction
            is summed (nuPlan: 1).
        direction_ok: m of such progress that still scores 1 (nuPlan: 2).
        direction_bad: m from which it scores 0; between the two, 0.5 (nuPlan: 6).
        min_progress_ratio: ego progress over expert progress below which the ego is not
            making progress (nuPlan: 0.2).
        min_expert_progress: m of expert progress below which both progress metrics score 1
            (an expert that stands still cannot be out-progressed).
        ttc_bound: s, the least time to collision allowed (nuPlan: 0.95).
        ttc_horizon: s the constant-velocity projection looks ahead (nuPlan: 1).
        ttc_step: s between projected instants (the WOMD step, 0.1).
        max_overspeed: m/s of over-speed that, held over the whole episode, scores speed-limit
            compliance 0 (nuPlan: 2.23).
        lane_radius: m from the ego's centre within which a lane centre line counts as a lane
            the ego is on (WOMD has centre lines, not nuPlan's lane polygons: half a lane).
        lane_straddle: m between the ego's centre and its lane's centre line from which the
            ego straddles two lanes; a lateral collision is then the ego's fault (nuPlan: the
            ego in several lanes).
        comfort: the comfort bounds.
        weight_progress: CLS weight of ego progress (5); weight_ttc (5); weight_speed_limit
            (4); weight_comfort (2). The PDM score weighs progress 5, TTC 5, comfort 2.
    """

    stopped_speed: float = 0.05
    drivable_violation: float = 0.3
    direction_window_s: float = 1.0
    direction_ok: float = 2.0
    direction_bad: float = 6.0
    min_progress_ratio: float = 0.2
    min_expert_progress: float = 2.0
    ttc_bound: float = 0.95
    ttc_horizon: float = 1.0
    ttc_step: float = 0.1
    max_overspeed: float = 2.23
    lane_radius: float = 1.8
    lane_straddle: float = 1.0
    comfort: ComfortBounds = ComfortBounds()
    weight_progress: float = 5.0
    weight_ttc: float = 5.0
    weight_speed_limit: float = 4.0
    weight_comfort: float = 2.0

    def __post_init__(self) -> None:
        positive = ("drivable_violation", "direction_window_s", "ttc_horizon", "ttc_step")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"BenchmarkConfig.{name} must be > 0, got {getattr(self, name)}")
        if not self.direction_ok <= self.direction_bad:
            raise ValueError("BenchmarkConfig.direction_ok must not exceed direction_bad")
