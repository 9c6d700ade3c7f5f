"""WOSAC realism metrics (2024 and 2025 sim-agents challenges), vectorised in torch.

Typical use::

    from tbsim_env.metrics.wosac import score_submission_file, scores_table
    scores = score_submission_file(scenarios, "submission.binproto", "wosac2025")
    print(scores_table(scores))
"""

from tbsim_env.metrics.wosac.config import (
    DEFAULT_VERSION,
    MetricVersion,
    WosacConfig,
    WosacConfigError,
    get_config,
    parse_version,
)
from tbsim_env.metrics.wosac.evaluate import score_submission_file
from tbsim_env.metrics.wosac.features_map import MapFeatureError
from tbsim_env.metrics.wosac.report import scores_table, scores_to_json
from tbsim_env.metrics.wosac.rollouts import Rollouts, RolloutsError, log_replay_rollouts
from tbsim_env.metrics.wosac.scoring import (
    DatasetScores,
    ScenarioScores,
    ScoringError,
    aggregate,
    offroad_indication,
    scenario_features,
    score_scenario,
    simulated_offroad,
    simulated_road_departure,
)
from tbsim_env.metrics.wosac.submission import (
    SubmissionError,
    SubmissionMetadata,
    build_submission,
    read_submission,
    rollouts_from_proto,
    rollouts_to_proto,
    validate_scenario_rollouts,
    write_submission,
)

__all__ = [
    "DEFAULT_VERSION",
    "DatasetScores",
    "MapFeatureError",
    "MetricVersion",
    "Rollouts",
    "RolloutsError",
    "ScenarioScores",
    "ScoringError",
    "SubmissionError",
    "SubmissionMetadata",
    "WosacConfig",
    "WosacConfigError",
    "aggregate",
    "build_submission",
    "get_config",
    "log_replay_rollouts",
    "offroad_indication",
    "parse_version",
    "read_submission",
    "rollouts_from_proto",
    "rollouts_to_proto",
    "scenario_features",
    "score_scenario",
    "simulated_offroad",
    "simulated_road_departure",
    "score_submission_file",
    "scores_table",
    "scores_to_json",
    "validate_scenario_rollouts",
    "write_submission",
]
