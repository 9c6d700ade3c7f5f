"""Embedded procedural scenario generator: WOMD-like scenes without any download.

Layouts (``LAYOUTS``) are built in ``roads``, vehicles and cyclists are driven by the
rule-based driver in ``driver``, pedestrians cross on the crosswalks as planned in
``crossings`` (the driver yields to them) and ``scenes`` packs the result into the same
``Scenario`` type the WOMD reader produces. Layouts: "intersection" (signalised, split
phasing), "merge" (freeway on-ramp), "stop_intersection" (all-way stop, first come first
served), "t_junction" (minor road with a stop sign yielding to the major road) and
"permissive_intersection" (signalised, two phases: left turns wait on the green for gaps in
oncoming traffic, with the queue behind them). ``training_mix(seed)`` cycles through them.
Speeds, acceleration, headways and walking are set by a ``behaviour.Behaviour``, calibrated
against the real training scenes (``calibration``, ``scripts/calibrate_generator.py``); a
``recording.Recording`` (``RECORDED``, fitted the same way) adds parked vehicles and the real
tracker's jitter to a scene's log.
"""

from __future__ import annotations

from tbsim_env.data.generator.scenes import (
    LAYOUTS,
    default_scenarios,
    frame_offset,
    generate_scenario,
    training_mix,
)

__all__ = ["LAYOUTS", "default_scenarios", "frame_offset", "generate_scenario", "training_mix"]
