"""Closed-loop planner benchmark: a planner drives the SDC (or the tracks to predict) on real
scenes under log-replayed, IDM and TrafficBots traffic, scored with nuPlan's closed-loop score
and a PDM score (``docs/benchmark.md``; ``tbsim benchmark``)."""

from tbsim_env.benchmark.config import BenchmarkConfig, ComfortBounds
from tbsim_env.benchmark.planner import (
    BatchInput,
    BatchPlanner,
    ConstantVelocityPlanner,
    ExpertPlanner,
    FunctionPlanner,
    Planner,
    PlannerInput,
    SB3Planner,
    TorchPlanner,
    load_planner,
)
from tbsim_env.benchmark.runner import BenchmarkSettings, benchmark_scenario, run_benchmark
from tbsim_env.benchmark.score import ScenarioResult

__all__ = [
    "BatchInput",
    "BatchPlanner",
    "BenchmarkConfig",
    "BenchmarkSettings",
    "ComfortBounds",
    "ConstantVelocityPlanner",
    "ExpertPlanner",
    "FunctionPlanner",
    "Planner",
    "PlannerInput",
    "SB3Planner",
    "ScenarioResult",
    "TorchPlanner",
    "benchmark_scenario",
    "load_planner",
    "run_benchmark",
]
