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
            ``scenarios`` or listed twice, or rollouts that fail the server's checks (each
            naming the file, and the scenario, joint scene, object, step and field at fault).
    """
    version = parse_version(version)
    by_id = {s.scenario_id: s for s in scenarios}
    name = os.fspath(path)
    submission = read_submission(path)
    if not submission.scenario_rollouts:
        raise SubmissionError(f"{name}: the submission holds no scenario rollouts")
    first: dict[str, int] = {}
    for k, rollouts in enumerate(submission.scenario_rollouts):
        sid = rollouts.scenario_id
        if sid in first:
            raise SubmissionError(
                f"{name}: scenario {sid!r} is listed twice (entries {first[sid]} and {k} of "
                "scenario_rollouts); each scenario may be submitted once"
            )
        first[sid] = k
        if sid not in by_id:
            raise SubmissionError(
                f"{name}: scenario {sid!r} of the submission is not among the "
                f"{len(by_id)} given scenarios"
            )
        try:
            validate_scenario_rollouts(rollouts, by_id[sid])
        except SubmissionError as err:
            raise SubmissionError(f"{name}: {err}") from err
    return [
        score_scenario(by_id[r.scenario_id], rollouts_from_proto(r, device), version)
        for r in submission.scenario_rollouts
    ]
