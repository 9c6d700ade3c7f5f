"""Behaviour parameters of the generator shared by every layout, and their calibrated values.

A ``Behaviour`` sets how the generated agents move: the drivers' desired speeds (a factor on
each layout's range), acceleration, braking, headway, standstill gap and bend speeds, the
cyclists' speeds and acceleration, and the pedestrians' walking speeds, the share of sidewalk
pedestrians who stand still, and the walkers' speed fluctuation and sideways sway.

``UNCALIBRATED`` holds the values the generator had before its calibration (with it, scenes
are the same as then, bit for bit); ``CALIBRATED``, the default of ``generate_scenario``, holds
the values fitted by ``scripts/calibrate_generator.py`` so that the kinematic histograms of
generated scenes match those of the real training scenes (docs/model_card/
generator_calibration.md). Units: metres, seconds.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from tbsim_env.data.generator.driver import DriverConfig

Range = tuple[float, float]


@dataclass(frozen=True)
class Behaviour:
    """Agent behaviour of generated scenes, for every layout.

    Ranges are (timid end, aggressive end), low to high: a driver's value is placed in its
    range by its personality (see ``driver.draw_fleet``).

    Attributes:
        speed_scale: factor on every layout's desired speed range (``LayoutTraffic.driver``).
        max_accel: IDM maximum acceleration range of motor vehicles, m/s^2.
        comfort_decel: IDM comfortable deceleration range of motor vehicles, m/s^2.
        time_headway: IDM time headway range, s.
        min_gap: IDM standstill gap range, m.
        lateral_accel: lateral acceleration that caps speeds in bends, m/s^2.
        cyclist_speed: desired speed range of cyclists, m/s.
        cyclist_accel: maximum acceleration range of cyclists, m/s^2.
        cyclist_decel: comfortable deceleration range of cyclists, m/s^2.
        ped_speed: walking speed range of sidewalk pedestrians, m/s.
        crossing_speed: walking speed range of pedestrians who cross on crosswalks, m/s.
        ped_standing_share: share of sidewalk pedestrians who stand still, in [0, 1].
        ped_speed_sigma: standard deviation of a walker's speed around its walking speed, m/s
            (Ornstein-Uhlenbeck, time constant ``ped_wander_tau``).
        ped_sway_sigma: standard deviation of a walker's sideways offset from its line, m
            (Ornstein-Uhlenbeck, time constant ``ped_wander_tau``).
        ped_wander_tau: time constant of the speed fluctuation and sway, s.
    """

    speed_scale: float
    max_accel: Range
    comfort_decel: Range
    time_headway: Range
    min_gap: Range
    lateral_accel: float
    cyclist_speed: Range
    cyclist_accel: Range
    cyclist_decel: Range
    ped_speed: Range
    crossing_speed: Range
    ped_standing_share: float
    ped_speed_sigma: float
    ped_sway_sigma: float
    ped_wander_tau: float

    def driver(self, cfg: DriverConfig) -> DriverConfig:
        """``cfg`` (a layout's driver configuration) with this behaviour's parameters."""
        lo, hi = cfg.desired_speed
        return dataclasses.replace(
            cfg,
            desired_speed=(lo * self.speed_scale, hi * self.speed_scale),
            max_accel=self.max_accel,
            comfort_decel=self.comfort_decel,
            time_headway=self.time_headway,
            min_gap=self.min_gap,
            lateral_accel=self.lateral_accel,
            cyclist_speed=self.cyclist_speed,
            cyclist_accel=self.cyclist_accel,
            cyclist_decel=self.cyclist_decel,
        )

    @property
    def walkers_wander(self) -> bool:
        """Whether sidewalk walkers fluctuate in speed or sway (else they walk straight at
        constant speed)."""
        return self.ped_speed_sigma > 0.0 or self.ped_sway_sigma > 0.0


UNCALIBRATED = Behaviour(
    speed_scale=1.0,
    max_accel=(1.1, 2.4),
    comfort_decel=(1.5, 3.0),
    time_headway=(0.9, 2.2),
    min_gap=(1.8, 3.5),
    lateral_accel=2.0,
    cyclist_speed=(4.0, 7.0),
    cyclist_accel=(0.8, 1.5),
    cyclist_decel=(1.5, 2.5),
    ped_speed=(1.0, 1.6),
    crossing_speed=(1.2, 1.6),
    ped_standing_share=0.0,
    ped_speed_sigma=0.0,
    ped_sway_sigma=0.0,
    ped_wander_tau=1.0,
)
"""The behaviour before calibration (the hand-set values the generator had)."""

# Fitted by scripts/calibrate_generator.py on the real "train" scenes of
# docs/model_card/real_splits.json (see docs/model_card/generator_calibration.md); rerun the
# script to refit, it rewrites this block.
# BEGIN CALIBRATED
CALIBRATED = Behaviour(
    speed_scale=1.35,
    max_accel=(1.76, 3.84),
    comfort_decel=(1.95, 3.9),
    time_headway=(0.63, 1.54),
    min_gap=(2.7, 5.25),
    lateral_accel=3.0,
    cyclist_speed=(4.0, 7.0),
    cyclist_accel=(0.8, 1.5),
    cyclist_decel=(1.5, 2.5),
    ped_speed=(0.8, 1.28),
    crossing_speed=(0.96, 1.28),
    ped_standing_share=0.0,
    ped_speed_sigma=0.2,
    ped_sway_sigma=0.0,
    ped_wander_tau=0.3,
)
# END CALIBRATED
"""The calibrated behaviour, the default of ``generate_scenario``."""
