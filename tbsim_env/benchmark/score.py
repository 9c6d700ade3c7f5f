"""Per-episode results and the combined scores: nuPlan's closed-loop score (CLS) and NAVSIM's
PDM score, both on 0-100 (``docs/benchmark.md``).

CLS = 100 * NC * DAC * DDC * MP * (5 EP + 5 TTC + 4 SLC + 2 C) / 16, the speed-limit term
left out (weights renormalised) where the map gives no limits.
PDMS = 100 * NC * DAC * (5 EP + 5 TTC + 2 C) / 12.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

from tbsim_env.benchmark import metrics as M
from tbsim_env.benchmark.config import BenchmarkConfig
from tbsim_env.benchmark.episode import EpisodeRecord

MULTIPLIERS = (
    "no_at_fault_collisions",
    "drivable_area_compliance",
    "driving_direction_compliance",
    "making_progress",
)
"""The gates of the CLS (their product multiplies the weighted mean)."""
WEIGHTED = ("ego_progress", "time_to_collision", "speed_limit_compliance", "comfort")


@dataclass(frozen=True)
class ScenarioResult:
    """One controlled agent's benchmark result on one scene under one traffic mode.

    Attributes:
        scenario_id, traffic, agent: what ran.
        no_at_fault_collisions: 1, 0.5 or 0 (NC); drivable_area_compliance: 0 / 1 (DAC);
        driving_direction_compliance: 1, 0.5 or 0 (DDC); making_progress: 0 / 1 (MP).
        ego_progress: ego over expert progress in [0, 1] (EP); time_to_collision: 0 / 1
            (TTC within bound); speed_limit_compliance: [0, 1], None without map limits
            (SLC); comfort: 0 / 1 (C).
        score: the CLS, 0-100; pdm_score: the PDM score, 0-100.
        route_completion: share of the logged route covered; progress_m, expert_progress_m;
        min_ttc_s (inf: none); wrong_way_m; max_offroad_m; comfort_extremes: ``Comfort``
        fields; collisions: the contacts (``CollisionEvent`` fields).
        infractions: [(state index, what)] for the viewer.
        error: why the planner failed the episode (every score 0), or None.
    """

    scenario_id: str
    traffic: str
    agent: str
    no_at_fault_collisions: float = 0.0
    drivable_area_compliance: float = 0.0
    driving_direction_compliance: float = 0.0
    making_progress: float = 0.0
    ego_progress: float = 0.0
    time_to_collision: float = 0.0
    speed_limit_compliance: float | None = None
    comfort: float = 0.0
    score: float = 0.0
    pdm_score: float = 0.0
    route_completion: float = 0.0
    progress_m: float = 0.0
    expert_progress_m: float = 0.0
    min_ttc_s: float = math.inf
    wrong_way_m: float = 0.0
    max_offroad_m: float = 0.0
    comfort_extremes: dict = field(default_factory=dict)
    collisions: list = field(default_factory=list)
    infractions: list = field(default_factory=list)
    error: str | None = None

    def to_json(self) -> dict:
        """A JSON-safe dict (inf as None)."""
        out = dataclasses.asdict(self)
        out["min_ttc_s"] = None if math.isinf(self.min_ttc_s) else self.min_ttc_s
        return out

    @staticmethod
    def from_json(data: dict) -> ScenarioResult:
        data = dict(data)
        data["min_ttc_s"] = math.inf if data.get("min_ttc_s") is None else data["min_ttc_s"]
        return ScenarioResult(**data)


def combined_scores(r: ScenarioResult, cfg: BenchmarkConfig) -> tuple[float, float]:
    """(CLS, PDM score) of the metric fields of ``r``, 0-100."""
    gate = math.prod(getattr(r, name) for name in MULTIPLIERS)
    terms = [
        (cfg.weight_progress, r.ego_progress),
        (cfg.weight_ttc, r.time_to_collision),
        (cfg.weight_comfort, r.comfort),
    ]
    if r.speed_limit_compliance is not None:
        terms.append((cfg.weight_speed_limit, r.speed_limit_compliance))
    cls = 100.0 * gate * sum(w * v for w, v in terms) / sum(w for w, _ in terms)
    pdm = r.ego_progress * 5 + r.time_to_collision * 5 + r.comfort * 2
    pdms = 100.0 * r.no_at_fault_collisions * r.drivable_area_compliance * pdm / 12.0
    return cls, pdms


def _infractions(r: EpisodeRecord, events: list, lanes: M.LaneContext, cfg) -> list:
    """[(state index, what)] of the gates' failures, for the viewer."""
    out = [(e.step, f"at-fault collision ({e.kind.value}) with {e.other_id}") for e in events]
    out = [x for x, e in zip(out, events) if e.at_fault]
    off = [int(s) for s in (r.offroad_distance > cfg.drivable_violation).nonzero()[0] if s > 0]
    if off:
        out.append((off[0], f"off the drivable area by {r.offroad_distance.max():.2f} m"))
    over = (lanes.speed_limit > 0) & (abs(r.ego_speed) > lanes.speed_limit + cfg.max_overspeed)
    if over[1:].any():
        out.append((int(over[1:].nonzero()[0][0]) + 1, "over the speed limit"))
    return sorted(out)


def score_record(
    record: EpisodeRecord, lanes: M.LaneIndex, cfg: BenchmarkConfig | None = None
) -> ScenarioResult:
    """Every metric and both scores of one episode record."""
    cfg = cfg or BenchmarkConfig()
    base = ScenarioResult(record.scenario_id, record.traffic, record.agent)
    if record.error is not None:
        return dataclasses.replace(base, error=record.error)
    ctx = M.lane_context(record, lanes, cfg)
    events = M.collision_events(record, ctx, cfg)
    wrong = M.wrong_way_distance(record, ctx, cfg)
    ratio = M.progress_ratio(record, cfg)
    min_ttc = M.min_time_to_collision(record, cfg)
    comfort = M.comfort(record, cfg)
    r = dataclasses.replace(
        base,
        no_at_fault_collisions=M.no_at_fault_collisions(events),
        drivable_area_compliance=M.drivable_area_compliance(record, cfg),
        driving_direction_compliance=M.driving_direction_compliance(wrong, cfg),
        making_progress=float(ratio >= cfg.min_progress_ratio),
        ego_progress=ratio,
        time_to_collision=float(min_ttc >= cfg.ttc_bound),
        speed_limit_compliance=M.speed_limit_compliance(record, ctx, cfg),
        comfort=float(comfort.ok),
        route_completion=M.route_completion(record),
        progress_m=M.ego_progress(record),
        expert_progress_m=record.expert_progress,
        min_ttc_s=min_ttc,
        wrong_way_m=wrong,
        max_offroad_m=float(record.offroad_distance[1:].max(initial=-math.inf)),
        comfort_extremes={k: v for k, v in dataclasses.asdict(comfort).items() if k != "ok"},
        collisions=[{**dataclasses.asdict(e), "kind": e.kind.value} for e in events],
        infractions=_infractions(record, events, ctx, cfg),
    )
    cls, pdms = combined_scores(r, cfg)
    return dataclasses.replace(r, score=cls, pdm_score=pdms)
