"""Plain-text and JSON views of WOSAC scores, for the command line and result files."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

from tbsim_env.metrics.wosac.scoring import (
    LIKELIHOOD_NAMES,
    DatasetScores,
    ScenarioScores,
    aggregate,
)

_SHORT = {
    "linear_speed": "lin_spd",
    "linear_acceleration": "lin_acc",
    "angular_speed": "ang_spd",
    "angular_acceleration": "ang_acc",
    "distance_to_nearest_object": "d_obj",
    "collision_indication": "coll",
    "time_to_collision": "ttc",
    "distance_to_road_edge": "d_edge",
    "offroad_indication": "offroad",
    "traffic_light_violation": "tl",
}
_COLUMNS = (
    ("meta", "realism_meta_metric"),
    ("kinem", "kinematic_metrics"),
    ("inter", "interactive_metrics"),
    ("map", "map_based_metrics"),
    ("minADE", "min_average_displacement_error"),
    ("ADE", "average_displacement_error"),
    ("coll_rate", "simulated_collision_rate"),
    ("off_rate", "simulated_offroad_rate"),
    ("tl_rate", "simulated_traffic_light_violation_rate"),
) + tuple((_SHORT[n], f"{n}_likelihood") for n in LIKELIHOOD_NAMES)


def scores_table(scores: Sequence[ScenarioScores]) -> str:
    """A per-scenario table (one row per scenario) followed by the dataset means.

    Args:
        scores: scores of one metric version (at least one).

    Returns:
        Plain text, columns separated by spaces, values with 4 decimals.
    """
    mean = aggregate(scores)
    width = max(16, *(len(s.scenario_id) for s in scores))
    head = ["scenario".ljust(width)] + [name.rjust(9) for name, _ in _COLUMNS]
    lines = [f"WOSAC {mean.version} ({len(scores)} scenarios)", " ".join(head)]

    def row(label: str, s: ScenarioScores | DatasetScores) -> str:
        cells = [f"{getattr(s, field):9.4f}" for _, field in _COLUMNS]
        return " ".join([label.ljust(width)] + cells)

    lines += [row(s.scenario_id, s) for s in scores]
    lines.append(row("MEAN", mean))
    return "\n".join(lines)


def scores_to_json(scores: Sequence[ScenarioScores]) -> dict:
    """Every per-scenario field plus the dataset means, as JSON-ready builtins.

    Returns:
        {"version": str, "num_scenarios": int, "mean": {...}, "scenarios": [{...}, ...]}.
    """
    mean = aggregate(scores)
    return {
        "version": mean.version,
        "num_scenarios": mean.num_scenarios,
        "mean": dataclasses.asdict(mean),
        "scenarios": [dataclasses.asdict(s) for s in scores],
    }
