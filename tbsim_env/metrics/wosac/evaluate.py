"""Score a whole submission file against the logged scenarios (the CLI's entry point)."""

from __future__ import annotations

import os
from collections.abc import Iterable

import torch

from tbsim_env.data.scenario import Scenario
from tbsim_env.metrics.wosac.config import DEFAULT_VERSION, MetricVersion, parse_version
from tbsim_env.metrics.wosac.scoring import ScenarioScores, score_scenario
from tbsim_env.metrics.wosac.submission import (
    SubmissionError,
    read_submission,
    rollouts_from_proto,
    validate_scenario_rollouts,
)


def score_submission_file(
    scenarios: Iterable[Scenario],
    path: str | os.PathLike[str],
    version: MetricVersion | str = DEFAULT_VERSION,
    device: torch.device | str = "cpu",
) -> list[ScenarioScores]:
    """Validate and score every scenario of a submission file, in submission order.

    Args:
        scenarios: the logged scenarios (extra ones are ignored).
        path: raw serialized ``SimAgentsChallengeSubmission``.
        version: "wosac2025" (default) or "wosac2024".
        device: where to compute.

    Raises:
        SubmissionError: unreadable file, a scenario of the submission not among
            ``scenarios``, or rollouts that fail the server's checks.
    """
    version = parse_version(version)
    by_id = {s.scenario_id: s for s in scenarios}
    submission = read_submission(path)
    if not submission.scenario_rollouts:
        raise SubmissionError(f"{os.fspath(path)}: the submission holds no scenario rollouts")
    out = []
    for rollouts in submission.scenario_rollouts:
        scenario = by_id.get(rollouts.scenario_id)
        if scenario is None:
            raise SubmissionError(
                f"{os.fspath(path)}: scenario {rollouts.scenario_id!r} of the submission is not "
                f"among the {len(by_id)} given scenarios"
            )
        validate_scenario_rollouts(rollouts, scenario)
        out.append(score_scenario(scenario, rollouts_from_proto(rollouts, device), version))
    return out
