"""Run the benchmark: every scene under every traffic mode, scored (``docs/benchmark.md``)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from tqdm import tqdm

from tbsim_env.benchmark.config import BenchmarkConfig
from tbsim_env.benchmark.episode import EpisodeSpec, run_episode
from tbsim_env.benchmark.metrics import LaneIndex
from tbsim_env.benchmark.planner import load_planner
from tbsim_env.benchmark.score import ScenarioResult, score_record
from tbsim_env.data.scenario import Scenario
from tbsim_env.evaluation import check_logged_future, scenario_seed

TRAFFIC_MODES = ("log_replay", "idm", "trafficbots")
"""The traffic modes of the benchmark: non-reactive (CLS-NR), rule-based and learned."""


@dataclass(frozen=True)
class BenchmarkSettings:
    """What a benchmark run does (picklable: the Ray workers get it).

    Attributes:
        planner: ``load_planner`` spec (a built-in name or ``PACKAGE.MODULE:NAME``).
        traffic: NPC policies, one run of every scene each.
        controlled: ``"sdc"`` or ``"tracks_to_predict"`` (the SDC and the tracks to predict).
        seed: base seed (each scene gets ``scenario_seed(seed, id)``).
        npc_checkpoint: TrafficBots weights of ``trafficbots`` traffic (None: shipped).
        config: thresholds and weights.
    """

    planner: str
    traffic: tuple[str, ...] = TRAFFIC_MODES
    controlled: str = "sdc"
    seed: int = 0
    npc_checkpoint: str | None = None
    config: BenchmarkConfig = field(default_factory=BenchmarkConfig)

    def __post_init__(self) -> None:
        if not self.traffic:
            raise ValueError("BenchmarkSettings.traffic names no traffic mode")
        if self.controlled not in ("sdc", "tracks_to_predict"):
            raise ValueError(
                f"controlled must be 'sdc' or 'tracks_to_predict', not {self.controlled!r}"
            )


def benchmark_scenario(
    scenario: Scenario, settings: BenchmarkSettings, make_planner: Callable[[], Any] | None = None
) -> list[ScenarioResult]:
    """The results of one scene: a result per traffic mode and controlled agent.

    Args:
        make_planner: a factory of planners (one per controlled agent and episode); by
            default ``load_planner(settings.planner)``.
    """
    make = make_planner or (lambda: load_planner(settings.planner))
    lanes = LaneIndex.of(scenario)
    seed = scenario_seed(settings.seed, scenario.scenario_id)
    out = []
    for traffic in settings.traffic:
        spec = EpisodeSpec(scenario, traffic, settings.controlled, seed, settings.npc_checkpoint)
        out += [score_record(r, lanes, settings.config) for r in run_episode(spec, make)]
    return out


def run_benchmark(
    scenarios: Iterable[Scenario],
    settings: BenchmarkSettings,
    make_planner: Callable[[], Any] | None = None,
    progress: bool = True,
) -> list[ScenarioResult]:
    """Every scene's results, in scene order (a tqdm bar over the scenes).

    Raises:
        MissingFutureError: a scene without its logged future (the expert's route and
            progress come from the log).
    """
    scenarios = list(scenarios)
    check_logged_future(scenarios, "the planner benchmark")
    out: list[ScenarioResult] = []
    for sc in tqdm(scenarios, desc=f"benchmark {settings.planner}", disable=not progress):
        out += benchmark_scenario(sc, settings, make_planner)
    return out


def by_traffic(results: Sequence[ScenarioResult]) -> dict[str, list[ScenarioResult]]:
    """The results grouped by traffic mode, in first-seen order."""
    groups: dict[str, list[ScenarioResult]] = {}
    for r in results:
        groups.setdefault(r.traffic, []).append(r)
    return groups
