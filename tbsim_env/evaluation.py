"""Realism evaluation of policies: WOSAC rollouts, submissions, scores and histogram plots.

The functions behind ``tbsim export-wosac``, ``tbsim wosac-score`` and ``tbsim evaluate``.
Every policy is rolled out by the same closed-loop simulator (``tbsim_env.metrics.wosac.simulate``),
except the official linear-extrapolation baseline, which is a formula, and exact log replay.

Every policy but log replay simulates the 80 WOSAC steps of any scene, history-only ones (the
WOSAC test split) included, so a folder mixing both exports in one run. Log replay and scoring
need the logged future: ``check_logged_future`` refuses such a scene before any rollout.
"""

from __future__ import annotations

import zlib
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from policies.registry import make_rollout_fn as registry_rollout_fn
from tbsim_env.data.scenario import Scenario
from tbsim_env.metrics.wosac import (
    Rollouts,
    ScenarioScores,
    SubmissionMetadata,
    build_submission,
    rollouts_to_proto,
    score_scenario,
    validate_scenario_rollouts,
    write_submission,
)
from tbsim_env.sim.horizon import wosac_end_step


def scenario_seed(seed: int, scenario_id: str) -> int:
    """Per-scenario seed: the same whatever the order or subset of scenarios evaluated."""
    return (int(seed) * 1_000_003 + zlib.crc32(scenario_id.encode())) % (2**31)


def check_logged_future(scenarios: Iterable[Scenario], task: str) -> None:
    """Refuse, before any work, a scenario whose log does not hold the 80 WOSAC steps.

    Args:
        scenarios: the scenarios the task will run on.
        task: what needs the logged future, for the message (e.g. "log replay").

    Raises:
        MissingFutureError: for the first such scenario, naming it and its source.
    """
    for sc in scenarios:
        sc.require_log_until(wosac_end_step(sc), task)


def make_rollout_fn(
    policy: str,
    *,
    checkpoint: str | None = None,
    device: str = "cpu",
    road_edge_weight: float | None = None,
) -> Callable[[Scenario, int, int], Rollouts]:
    """A function ``(scenario, num_rollouts, seed) -> Rollouts`` for a registered policy name
    (``policies.registry``: any policy a user registered works here too).

    ``road_edge_weight`` (TrafficBots only): weight of off-road agents, beside collided ones,
    when choosing which of the sampled rollouts to keep (docs/model.md §7.3's ``w_road_edge``, 0
    there); None for the policy's own (TrafficBots: its ``InferenceConfig``, shipped 1).
    """
    options = {} if road_edge_weight is None else {"road_edge_weight": road_edge_weight}
    return registry_rollout_fn(policy, checkpoint=checkpoint, device=device, **options)


@dataclass(frozen=True)
class RolloutSettings:
    """How the rollouts of an evaluation are made.

    Attributes:
        policy: a registered policy name (``policies.registry``).
        num_rollouts: joint futures per scenario (WOSAC: 32).
        seed: seed of the rollouts (each scenario's from it and its id: ``scenario_seed``).
        checkpoint: weights of the policy (for the policies that take one).
        device: torch device of the rollouts.
        road_edge_weight: TrafficBots only: weight of off-road agents, beside collided ones,
            when choosing which of the sampled rollouts to keep (docs/model.md §7.3's
            ``w_road_edge``); None for the model's own (shipped 1).
    """

    policy: str
    num_rollouts: int = 32
    seed: int = 0
    checkpoint: str | None = None
    device: str = "cpu"
    road_edge_weight: float | None = None


def rollout_settings(policy: str | RolloutSettings, **options: Any) -> RolloutSettings:
    """``policy`` as ``RolloutSettings``: given ones as they are (then no ``options``), or a
    policy name with the ``RolloutSettings`` fields in ``options``.

    Raises:
        TypeError: an option that is not a ``RolloutSettings`` field, or options beside
            given settings.
    """
    if isinstance(policy, RolloutSettings):
        if options:
            raise TypeError(f"options {sorted(options)} beside RolloutSettings: set them there")
        return policy
    return RolloutSettings(policy, **options)


def iter_rollouts(
    scenarios: Iterable[Scenario],
    settings: RolloutSettings,
    *,
    progress: bool = True,
    total: int | None = None,
):
    """Yield ``(scenario, rollouts)`` for every scenario, with a progress bar."""
    fn = make_rollout_fn(
        settings.policy,
        checkpoint=settings.checkpoint,
        device=settings.device,
        road_edge_weight=settings.road_edge_weight,
    )
    desc = f"rollouts {settings.policy}"
    for sc in tqdm(scenarios, desc=desc, unit="scenario", disable=not progress, total=total):
        yield sc, fn(sc, settings.num_rollouts, scenario_seed(settings.seed, sc.scenario_id))


def submission_metadata(policy: str) -> SubmissionMetadata:
    """The method description tbsim writes for a policy's submission."""
    return SubmissionMetadata(
        account_name="tbsim",
        unique_method_name=f"tbsim-{policy}",
        description=f"tbsim {policy} closed-loop rollouts",
        num_model_parameters="0",
        acknowledge_complies_with_closed_loop_requirement=True,
    )


def export_submission(
    scenarios: Sequence[Scenario],
    policy: str | RolloutSettings,
    out: str | Path,
    *,
    metadata: SubmissionMetadata | None = None,
    **options: Any,
) -> int:
    """Write a ``SimAgentsChallengeSubmission`` of the scenarios' rollouts; returns their count.

    Every scenario's rollouts pass ``validate_scenario_rollouts`` (with ``num_rollouts`` joint
    scenes) before anything is written: a failing check raises and leaves no file.

    Args:
        scenarios: the scenarios.
        policy: a policy name (with the other ``RolloutSettings`` fields as ``options``:
            ``num_rollouts``, ``seed``, ``checkpoint``, ``device``, ``road_edge_weight``), or
            ``RolloutSettings``.
        out: the submission file.
        metadata: the method description (default: ``submission_metadata``).

    Raises:
        MissingFutureError: ``policy="log_replay"`` on a scene without its logged future.
        SubmissionError: rollouts that break the challenge format (wrong step count, missing
            agent, non-finite or impossible coordinate).
    """
    settings = rollout_settings(policy, **options)
    if settings.policy == "log_replay":
        check_logged_future(scenarios, "log replay")
    metadata = metadata or submission_metadata(settings.policy)
    protos = []
    for sc, r in iter_rollouts(scenarios, settings, total=len(scenarios)):
        protos.append(rollouts_to_proto(r))
        validate_scenario_rollouts(protos[-1], sc, num_rollouts=settings.num_rollouts)
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    write_submission(out, build_submission(protos, metadata))
    return len(protos)


def evaluate_policy(
    scenarios: Sequence[Scenario],
    policy: str | RolloutSettings,
    *,
    version: str = "wosac2025",
    keep_rollouts: bool = False,
    **options: Any,
) -> tuple[list[ScenarioScores], list[Rollouts]]:
    """Roll out and score every scenario (no proto written).

    Args:
        scenarios: the scenarios (with their logged future).
        policy: a policy name (with the other ``RolloutSettings`` fields as ``options``), or
            ``RolloutSettings``.
        version: the metric configuration (``"wosac2024"`` or ``"wosac2025"``).
        keep_rollouts: also return the rollouts (else an empty list).

    Raises:
        MissingFutureError: a scenario without its logged future (scoring compares with it),
            before any rollout.
    """
    settings = rollout_settings(policy, **options)
    check_logged_future(scenarios, "WOSAC scoring")
    scores, kept = [], []
    for sc, r in iter_rollouts(scenarios, settings, total=len(scenarios)):
        scores.append(score_scenario(sc, r, version))
        if keep_rollouts:
            kept.append(r)
    return scores, kept


# ----------------------------------------------------------------------------- histograms
HISTOGRAM_FEATURES = (
    ("linear_speed", "linear speed (m/s)"),
    ("linear_acceleration", "linear acceleration (m/s^2)"),
    ("angular_speed", "angular speed (rad/s)"),
    ("angular_acceleration", "angular acceleration (rad/s^2)"),
    ("distance_to_nearest_object", "distance to nearest object (m)"),
    ("time_to_collision", "time to collision (s)"),
    ("distance_to_road_edge", "distance to road edge (m)"),
)


def feature_samples(scenario: Scenario, rollouts: Rollouts) -> dict[str, tuple[np.ndarray, ...]]:
    """Log and simulated values of every histogram feature over the log-valid future steps.

    Returns:
        {feature: (log values [k], simulated values [R * k])}, NaNs removed.
    """
    from tbsim_env.metrics.wosac.features import compute_metric_features
    from tbsim_env.metrics.wosac.features_map import road_edge_segments, traffic_light_map
    from tbsim_env.metrics.wosac.trajectories import (
        concat_rollouts,
        log_trajectories,
        select_objects,
        simulated_trajectories,
    )

    scenario = scenario.motion_window()  # the steps WOSAC scores
    first = scenario.current_index + 1
    objects = select_objects(scenario)
    log = log_trajectories(scenario, objects, "cpu")
    sim = simulated_trajectories(log, objects, rollouts, scenario.current_index)
    feats = compute_metric_features(
        concat_rollouts(log, sim), road_edge_segments(scenario), traffic_light_map(scenario), first
    )
    valid = log.valid[0, : objects.num_eval, first:]
    out = {}
    for name, _ in HISTOGRAM_FEATURES:
        values = getattr(feats, name)  # [1 + R, E, S]
        lv = values[0][valid].numpy()
        sv = values[1:][valid.expand(values.shape[0] - 1, -1, -1)].numpy()
        out[name] = (lv[np.isfinite(lv)], sv[np.isfinite(sv)])
    return out


def plot_histograms(
    samples: dict[str, list[tuple[np.ndarray, np.ndarray]]], path: str | Path, title: str = ""
) -> None:
    """One panel per feature: log (filled) vs simulation (outline) density, to a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(2, 4, figsize=(16, 7))
    for ax, (name, label) in zip(axes.flat, HISTOGRAM_FEATURES):
        logs = np.concatenate([s[0] for s in samples[name]]) if samples[name] else np.zeros(0)
        sims = np.concatenate([s[1] for s in samples[name]]) if samples[name] else np.zeros(0)
        both = np.concatenate([logs, sims])
        both = both[np.abs(both) < 1e9]
        if both.size == 0:
            ax.set_title(f"{label}\n(no samples)")
            continue
        lo, hi = np.percentile(both, [1, 99])
        bins = np.linspace(lo, hi if hi > lo else lo + 1.0, 40)
        ax.hist(logs, bins=bins, density=True, alpha=0.5, label="log", color="tab:blue")
        ax.hist(
            sims, bins=bins, density=True, histtype="step", lw=2, label="sim", color="tab:orange"
        )
        ax.set_title(label)
    axes.flat[-1].axis("off")
    axes.flat[0].legend()
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


__all__ = [
    "HISTOGRAM_FEATURES",
    "RolloutSettings",
    "check_logged_future",
    "evaluate_policy",
    "export_submission",
    "feature_samples",
    "iter_rollouts",
    "make_rollout_fn",
    "plot_histograms",
    "rollout_settings",
    "scenario_seed",
    "submission_metadata",
]
