"""Run the benchmark: every scene under every traffic mode, scored (``docs/benchmark.md``)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any

from tqdm import tqdm

from tbsim_env.benchmark.batch import batch_eligible, batchable, run_batch
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
        batch_size: scenes stepped together where that gives the same episodes
            (``batch.batchable``: the SDC, log-replayed traffic, a planner with
            ``act_batch``); 1 runs every scene alone.
    """

    planner: str
    traffic: tuple[str, ...] = TRAFFIC_MODES
    controlled: str = "sdc"
    seed: int = 0
    npc_checkpoint: str | None = None
    config: BenchmarkConfig = field(default_factory=BenchmarkConfig)
    batch_size: int = 16

    def __post_init__(self) -> None:
        if self.batch_size < 1:
            raise ValueError(f"BenchmarkSettings.batch_size must be >= 1, not {self.batch_size}")
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
    make = make_planner or (lambda: load_planner(settings.planner))
    lanes = [LaneIndex.of(sc) for sc in scenarios]
    seeds = [scenario_seed(settings.seed, sc.scenario_id) for sc in scenarios]
    done: dict[tuple[int, str], list[ScenarioResult]] = {}
    total, size = len(scenarios) * len(settings.traffic), settings.batch_size
    with tqdm(total=total, desc=f"benchmark {settings.planner}", disable=not progress) as bar:
        # A group of scenes under every traffic mode in turn, then the next group: what the
        # modes share (each scene's road-edge grid, ``scene_edge_grid``) is still kept.
        for lo in range(0, len(scenarios), size):
            ks = list(range(lo, min(lo + size, len(scenarios))))
            for traffic in settings.traffic:
                specs = [
                    EpisodeSpec(scenarios[k], traffic, settings.controlled, seeds[k],
                                settings.npc_checkpoint)
                    for k in ks
                ]  # fmt: skip
                for k, records in zip(ks, _episodes(specs, make, size)):
                    done[k, traffic] = [score_record(r, lanes[k], settings.config)
                                        for r in records]  # fmt: skip
                    bar.update()
    return [r for k in range(len(scenarios)) for t in settings.traffic for r in done[k, t]]


def _episodes(specs: Sequence[EpisodeSpec], make: Callable[[], Any], size: int) -> list[list]:
    """Each spec's episode records: together (``batch.run_batch``, a last group of one
    included) where batches are asked for (``size`` > 1) and ``batch.batchable`` allows it,
    else one scene at a time."""
    if size > 1 and batch_eligible(specs[0]):
        planner = make()
        if batchable(specs[0], planner):
            return [[r] for r in run_batch(specs, planner)]
    return [run_episode(spec, make) for spec in specs]


def by_traffic(results: Sequence[ScenarioResult]) -> dict[str, list[ScenarioResult]]:
    """The results grouped by traffic mode, in first-seen order."""
    groups: dict[str, list[ScenarioResult]] = {}
    for r in results:
        groups.setdefault(r.traffic, []).append(r)
    return groups
