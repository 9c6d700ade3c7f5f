"""Per-scenario WOSAC scores and dataset means (docs/metrics.md, "Estimators" and "Scores").

``score_scenario`` turns a logged ``Scenario`` and its simulated ``Rollouts`` into a frozen
``ScenarioScores``: the ten likelihoods, the realism meta-metric, the kinematic / interactive /
map-based buckets, ADE, minADE and the simulated collision / off-road / red-light rates.
``aggregate`` averages every field over scenarios and recomputes the buckets.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from tbsim_env.core.constants import ObjectType
from tbsim_env.core.errors import TbsimError
from tbsim_env.data.scenario import Scenario
from tbsim_env.metrics.wosac.config import (
    BUCKETS,
    DEFAULT_VERSION,
    MetricVersion,
    WosacConfig,
    get_config,
)
from tbsim_env.metrics.wosac.estimators import (
    bernoulli_log_likelihood,
    histogram_log_likelihood,
    masked_likelihood,
)
from tbsim_env.metrics.wosac.features import (
    MetricFeatures,
    compute_metric_features,
    slice_steps,
)
from tbsim_env.metrics.wosac.features_kinematic import acceleration_validity, speed_validity
from tbsim_env.metrics.wosac.features_map import (
    distance_to_road_edge,
    road_edge_segments,
    traffic_light_map,
)
from tbsim_env.metrics.wosac.rollouts import Rollouts
from tbsim_env.metrics.wosac.trajectories import (
    MetricObjects,
    ObjectTrajectories,
    concat_rollouts,
    log_trajectories,
    select_objects,
    simulated_trajectories,
)


class ScoringError(TbsimError, ValueError):
    """Rollouts cannot be scored against a scenario (wrong scenario, missing agents, ...)."""


LIKELIHOOD_NAMES = (
    "linear_speed",
    "linear_acceleration",
    "angular_speed",
    "angular_acceleration",
    "distance_to_nearest_object",
    "collision_indication",
    "time_to_collision",
    "distance_to_road_edge",
    "offroad_indication",
    "traffic_light_violation",
)
"""Likelihood fields of ``ScenarioScores`` are these names + ``_likelihood``."""


@dataclass(frozen=True)
class Scores:
    """WOSAC metrics of one scenario or means over a dataset.

    Every ``*_likelihood`` is exp(mean log-likelihood) in [0, 1] (NaN if no step was scored).

    Attributes:
        version: metric version value ("wosac2024" / "wosac2025").
        realism_meta_metric: weighted sum of the likelihoods.
        kinematic_metrics, interactive_metrics, map_based_metrics: bucket scores.
        average_displacement_error: ADE (m), over log-valid steps including history.
        min_average_displacement_error: minADE (m), min over rollouts of the object mean.
        simulated_collision_rate: fraction of (rollout, object) pairs.
        simulated_offroad_rate: fraction of (rollout, object) pairs.
        simulated_traffic_light_violation_rate: fraction of (rollout, object) pairs.
    """

    version: str
    realism_meta_metric: float
    kinematic_metrics: float
    interactive_metrics: float
    map_based_metrics: float
    average_displacement_error: float
    min_average_displacement_error: float
    linear_speed_likelihood: float
    linear_acceleration_likelihood: float
    angular_speed_likelihood: float
    angular_acceleration_likelihood: float
    distance_to_nearest_object_likelihood: float
    collision_indication_likelihood: float
    time_to_collision_likelihood: float
    distance_to_road_edge_likelihood: float
    offroad_indication_likelihood: float
    traffic_light_violation_likelihood: float
    simulated_collision_rate: float
    simulated_offroad_rate: float
    simulated_traffic_light_violation_rate: float

    def likelihoods(self) -> dict[str, float]:
        """Likelihood of every feature, keyed by feature name."""
        return {n: getattr(self, f"{n}_likelihood") for n in LIKELIHOOD_NAMES}


@dataclass(frozen=True)
class ScenarioScores(Scores):
    """``Scores`` of one scenario.

    Attributes:
        scenario_id: the scored scenario.
        num_sim_agents: objects simulated (valid at the current step).
        num_evaluated: objects scored (SDC + tracks to predict).
    """

    scenario_id: str = ""
    num_sim_agents: int = 0
    num_evaluated: int = 0


@dataclass(frozen=True)
class DatasetScores(Scores):
    """Plain means of ``Scores`` over scenarios (buckets recomputed from the mean likelihoods).

    Attributes:
        num_scenarios: scenarios averaged.
    """

    num_scenarios: int = 0


def _weighted(config: WosacConfig, likelihoods: dict[str, float]) -> dict[str, float]:
    """Meta-metric and buckets from the likelihoods."""
    w = config.weights.as_dict()
    out = {"realism_meta_metric": math.fsum(w[n] * likelihoods[n] for n in LIKELIHOOD_NAMES)}
    for bucket, names in BUCKETS.items():
        total = config.bucket_weight(bucket)
        out[f"{bucket}_metrics"] = math.fsum(w[n] * likelihoods[n] for n in names) / total
    return out


def _split_first_rollout(features: MetricFeatures) -> tuple[MetricFeatures, MetricFeatures]:
    """(features of rollout 0, features of the others), every field [R, E, F]."""
    fields = {f.name: getattr(features, f.name) for f in dataclasses.fields(MetricFeatures)}
    head = MetricFeatures(**{k: v[:1] for k, v in fields.items()})
    tail = MetricFeatures(**{k: v[1:] for k, v in fields.items()})
    return head, tail


def _indication(per_step: torch.Tensor, log_valid: torch.Tensor) -> torch.Tensor:
    """[R, E] any over the steps where the log is valid ([R, E, F] and [E, F])."""
    return (per_step & log_valid.unsqueeze(0)).any(-1)


def _likelihoods(
    config: WosacConfig,
    log: MetricFeatures,
    sim: MetricFeatures,
    log_valid: torch.Tensor,
    is_vehicle: torch.Tensor,
) -> dict[str, float]:
    """All ten likelihoods from the log [1, E, F] and simulated [R, E, F] features."""
    h = config.histograms
    c = config.histogram_pseudocount
    speed_mask = speed_validity(log_valid)
    accel_mask = acceleration_validity(log_valid)
    ttc_mask = log_valid & is_vehicle[:, None] if config.ttc_vehicles_only else log_valid
    hist = {
        "linear_speed": (h.linear_speed, speed_mask),
        "linear_acceleration": (h.linear_acceleration, accel_mask),
        "angular_speed": (h.angular_speed, speed_mask),
        "angular_acceleration": (h.angular_acceleration, accel_mask),
        "distance_to_nearest_object": (h.distance_to_nearest_object, log_valid),
        "time_to_collision": (h.time_to_collision, ttc_mask),
        "distance_to_road_edge": (h.distance_to_road_edge, log_valid),
    }
    out = {}
    for name, (spec, mask) in hist.items():
        ll = histogram_log_likelihood(getattr(log, name)[0], getattr(sim, name), spec, c)
        out[name] = masked_likelihood(ll, mask)
    vehicle_valid = log_valid & is_vehicle[:, None]
    flags = {
        "collision_indication": ("collision_per_step", log_valid),
        "offroad_indication": ("offroad_per_step", log_valid),
        "traffic_light_violation": ("traffic_light_violation_per_step", vehicle_valid),
    }
    everyone = torch.ones_like(log_valid[:, 0])
    for name, (field, mask) in flags.items():
        ll = bernoulli_log_likelihood(
            _indication(getattr(log, field), mask)[0],
            _indication(getattr(sim, field), mask),
            config.bernoulli_pseudocount,
        )
        out[name] = masked_likelihood(ll, everyone)
    return out


def _displacement(log: ObjectTrajectories, sim: ObjectTrajectories) -> tuple[float, float]:
    """(ADE, minADE) of the evaluated objects over log-valid steps of the whole trajectory."""
    e = log.num_eval
    err = torch.sqrt(
        (sim.x[:, :e] - log.x[:, :e]) ** 2
        + (sim.y[:, :e] - log.y[:, :e]) ** 2
        + (sim.z[:, :e] - log.z[:, :e]) ** 2
    )  # [R, E, T]
    valid = log.valid[:, :e]
    per_object = torch.where(valid, err, 0.0).sum(-1) / valid.sum(-1)  # [R, E]
    return float(per_object.mean()), float(per_object.mean(1).min())


@dataclass(frozen=True)
class ScenarioFeatures:
    """The inputs of a scenario's scores: who is scored and every per-step feature.

    Attributes:
        objects: the sim agents (evaluated first).
        log: [1, N, T] logged trajectories.
        sim: [R, N, T] simulated trajectories (history from the log).
        log_features: [1, E, F] features of the log over the future steps.
        sim_features: [R, E, F] features of the rollouts over the future steps.
        log_valid: [E, F] bool, log validity of the evaluated objects at the future steps.
    """

    objects: MetricObjects
    log: ObjectTrajectories
    sim: ObjectTrajectories
    log_features: MetricFeatures
    sim_features: MetricFeatures
    log_valid: torch.Tensor


def _trajectories(
    scenario: Scenario,
    rollouts: Rollouts,
    device: torch.device | str | None,
    require_future: bool = True,
) -> tuple[MetricObjects, ObjectTrajectories, ObjectTrajectories]:
    """Check the rollouts against the scenario; (objects, log [1, N, T], sim [R, N, T]).
    Without ``require_future`` the log may end at the current step (its future invalid)."""
    device = rollouts.x.device if device is None else torch.device(device)
    same_scene = rollouts.scenario_id == scenario.scenario_id
    if require_future and same_scene:
        scenario.require_log_until(scenario.current_index + rollouts.num_steps, "WOSAC scoring")
    mismatch = rollouts.mismatch(scenario, scenario.num_steps - scenario.current_index - 1)
    if mismatch:
        raise ScoringError(mismatch)
    impossible = rollouts.impossible_value()
    if impossible:
        raise ScoringError(f"scenario {scenario.scenario_id} ({scenario.source}): {impossible}")
    objects = select_objects(scenario)
    if objects.num_eval == 0:
        raise ScoringError(f"scenario {scenario.scenario_id}: no evaluated object is a sim agent")
    log = log_trajectories(scenario, objects, device)
    sim = simulated_trajectories(log, objects, rollouts.to(device), scenario.current_index)
    return objects, log, sim


def scenario_features(
    scenario: Scenario, rollouts: Rollouts, device: torch.device | str | None = None
) -> ScenarioFeatures:
    """Check the rollouts against the scenario and compute every WOSAC feature of both.

    Raises:
        ScoringError: wrong scenario id, missing sim agents, or a step count that does not fit.
        MissingFutureError: the log does not cover the rollouts' steps (a history-only scene).
        MapFeatureError: the scenario has no road edge.
    """
    scenario = scenario.motion_window()
    objects, log, sim = _trajectories(scenario, rollouts, device)
    first = scenario.current_index + 1
    edges = road_edge_segments(scenario, log.x.device)
    lights = traffic_light_map(scenario, log.x.device)
    both = compute_metric_features(concat_rollouts(log, sim), edges, lights, first)
    log_feat, sim_feat = _split_first_rollout(both)
    return ScenarioFeatures(
        objects=objects,
        log=log,
        sim=sim,
        log_features=log_feat,
        sim_features=sim_feat,
        log_valid=log.valid[0, : objects.num_eval, first:],
    )


def offroad_indication(
    scenario: Scenario, rollouts: Rollouts, device: torch.device | str | None = None
) -> torch.Tensor:
    """Which evaluated objects leave the road in each rollout: the WOSAC off-road indication.

    The same flag as behind ``simulated_offroad_rate`` (a box corner past the road edge at a
    future step where the log is valid), without the other features: cheap enough to rank many
    candidate rollouts by.

    Returns:
        [R, E] bool, E = the evaluated objects (SDC and tracks to predict that are sim agents).

    Raises:
        ScoringError, MissingFutureError, MapFeatureError: as ``score_scenario``.
    """
    offroad, log_valid = _offroad_per_step(scenario, rollouts, device, require_future=True)
    return _indication(offroad[..., 1:], log_valid)


def simulated_offroad(
    scenario: Scenario, rollouts: Rollouts, device: torch.device | str | None = None
) -> torch.Tensor:
    """Which evaluated objects leave the road in each rollout, at any simulated step.

    ``offroad_indication`` counts only the steps where the log is valid (as WOSAC scores);
    this flag counts every simulated step, so it reads nothing of the log's future: a
    history-only scene on WOSAC's time grid (``sim.horizon.wosac_scenario``, the test split)
    works too. What a submission may rank its own samples by.

    Returns:
        [R, E] bool, E = the evaluated objects (SDC and tracks to predict that are sim agents).

    Raises:
        ScoringError, MapFeatureError: as ``score_scenario``.
    """
    return _offroad_per_step(scenario, rollouts, device, require_future=False)[0][..., 1:].any(-1)


def simulated_road_departure(
    scenario: Scenario, rollouts: Rollouts, device: torch.device | str | None = None
) -> torch.Tensor:
    """Which evaluated objects on the road at the current step leave it in each rollout.

    ``simulated_offroad`` of the objects whose box is inside the road edges at the current
    step (the last logged one): an object already off the road then (a pedestrian on the
    sidewalk, a car in a lot) counts in neither direction. Reads nothing of the log's future.

    Returns:
        [R, E] bool, E = the evaluated objects.

    Raises:
        ScoringError, MapFeatureError: as ``score_scenario``.
    """
    off = _offroad_per_step(scenario, rollouts, device, require_future=False)[0]
    return off[..., 1:].any(-1) & ~off[..., 0]


def _offroad_per_step(
    scenario: Scenario,
    rollouts: Rollouts,
    device: torch.device | str | None,
    require_future: bool,
) -> tuple[torch.Tensor, torch.Tensor]:
    """(evaluated objects with a box corner past the road edge [R, E, 1 + F] bool at the
    current step and the F future steps, the log's validity at the future steps [E, F] bool)
    of the scenario in WOSAC's motion window."""
    scenario = scenario.motion_window()
    objects, log, sim = _trajectories(scenario, rollouts, device, require_future)
    now = scenario.current_index
    dist = distance_to_road_edge(
        slice_steps(sim, slice(now, None)), road_edge_segments(scenario, log.x.device)
    )
    return dist > 0.0, log.valid[0, : objects.num_eval, now + 1 :]


def score_scenario(
    scenario: Scenario,
    rollouts: Rollouts,
    version: MetricVersion | str = DEFAULT_VERSION,
    device: torch.device | str | None = None,
) -> ScenarioScores:
    """WOSAC scores of simulated rollouts against the logged scenario.

    Args:
        scenario: the logged scenario (WOMD: 91 steps, current index 10; a longer log is
            scored over the rollouts' steps only).
        rollouts: R simulated futures of every sim agent (extra objects are ignored; validate
            a submission first with ``validate_scenario_rollouts`` for the server's checks).
        version: "wosac2025" (default) or "wosac2024".
        device: where to compute (default: the rollouts' device).

    Raises:
        ScoringError: wrong scenario id, missing sim agents, a step count that does not fit,
            or a non-finite or out-of-bound rollout value (``Rollouts.impossible_value``).
        MissingFutureError: the log does not cover the rollouts' steps (a history-only scene).
        MapFeatureError: the scenario has no road edge.
    """
    config = get_config(version)
    f = scenario_features(scenario, rollouts, device)
    objects, log, sim, log_feat, sim_feat = f.objects, f.log, f.sim, f.log_features, f.sim_features
    log_valid = f.log_valid
    is_vehicle = log.evaluated(log.object_type) == int(ObjectType.VEHICLE)
    lik = _likelihoods(config, log_feat, sim_feat, log_valid, is_vehicle)
    ade, min_ade = _displacement(log, sim)
    rates = {
        "simulated_collision_rate": _indication(sim_feat.collision_per_step, log_valid),
        "simulated_offroad_rate": _indication(sim_feat.offroad_per_step, log_valid),
        "simulated_traffic_light_violation_rate": _indication(
            sim_feat.traffic_light_violation_per_step, log_valid
        ),
    }
    return ScenarioScores(
        version=config.version.value,
        **_weighted(config, lik),
        average_displacement_error=ade,
        min_average_displacement_error=min_ade,
        **{f"{n}_likelihood": v for n, v in lik.items()},
        **{k: float(v.float().mean()) for k, v in rates.items()},
        scenario_id=scenario.scenario_id,
        num_sim_agents=objects.num_objects,
        num_evaluated=objects.num_eval,
    )


def aggregate(scores: Sequence[ScenarioScores]) -> DatasetScores:
    """Dataset scores: the plain mean of every field over scenarios, buckets recomputed.

    Raises:
        ScoringError: if ``scores`` is empty or mixes metric versions.
    """
    if not scores:
        raise ScoringError("cannot aggregate an empty list of scenario scores")
    versions = {s.version for s in scores}
    if len(versions) != 1:
        raise ScoringError(f"cannot aggregate scores of different metric versions {versions}")
    config = get_config(versions.pop())
    numeric = [f.name for f in dataclasses.fields(Scores) if f.name != "version"]
    mean = {n: math.fsum(getattr(s, n) for s in scores) / len(scores) for n in numeric}
    lik = {n: mean[f"{n}_likelihood"] for n in LIKELIHOOD_NAMES}
    mean.update(_weighted(config, lik))
    return DatasetScores(version=config.version.value, **mean, num_scenarios=len(scores))
