"""What a benchmark run shows: a table per traffic mode, the JSON of every field, a plot of the
score distributions and viewer pages of the worst episodes with their infractions marked."""

from __future__ import annotations

import json
import math
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from tbsim_env.benchmark.runner import by_traffic
from tbsim_env.benchmark.score import MULTIPLIERS, WEIGHTED, ScenarioResult
from tbsim_env.data.scenario import Scenario

COLUMNS = (
    ("episodes", "n"),
    ("score", "CLS"),
    ("pdm_score", "PDMS"),
    *((m, m) for m in ("no_at_fault_collisions", "drivable_area_compliance")),
    ("driving_direction_compliance", "direction"),
    ("making_progress", "progress>0.2"),
    ("ego_progress", "ego progress"),
    ("time_to_collision", "TTC"),
    ("speed_limit_compliance", "speed limit"),
    ("comfort", "comfort"),
    ("route_completion", "route"),
    ("failed", "failed"),
)
"""(field, header) of the summary table, in order."""


def summary(results: Sequence[ScenarioResult]) -> dict[str, dict[str, float]]:
    """{traffic: {field: mean over its episodes}} plus ``episodes`` and ``failed`` counts; a
    metric that does not apply (speed limits on maps without them) is averaged where it does
    (NaN if nowhere)."""
    out = {}
    for traffic, rs in by_traffic(results).items():
        row: dict[str, float] = {"episodes": float(len(rs))}
        row["failed"] = float(sum(r.error is not None for r in rs))
        for name in ("score", "pdm_score", *MULTIPLIERS, *WEIGHTED, "route_completion"):
            vals = [getattr(r, name) for r in rs if getattr(r, name) is not None]
            row[name] = float(np.mean(vals)) if vals else math.nan
        out[traffic] = row
    return out


def summary_table(results: Sequence[ScenarioResult], title: str = "") -> str:
    """The summary as a markdown table, one row per traffic mode."""
    head = "| traffic | " + " | ".join(h for _, h in COLUMNS) + " |"
    lines = [f"**{title}**\n" if title else "", head, "|" + "---|" * (len(COLUMNS) + 1)]
    for traffic, row in summary(results).items():
        cells = []
        for name, _ in COLUMNS:
            v = row[name]
            cells.append(
                f"{int(v)}" if name in ("episodes", "failed") else
                "-" if math.isnan(v) else f"{v:.1f}" if "score" in name else f"{v:.3f}"
            )  # fmt: skip
        lines.append(f"| {traffic} | " + " | ".join(cells) + " |")
    return "\n".join(x for x in lines if x != "") + "\n"


def scenario_table(results: Sequence[ScenarioResult]) -> str:
    """One line per episode: scene, traffic, agent, CLS, PDMS and what failed."""
    lines = ["| scene | traffic | agent | CLS | PDMS | infractions |", "|---|---|---|---|---|---|"]
    for r in results:
        what = r.error or "; ".join(f"step {s}: {w}" for s, w in r.infractions) or "-"
        lines.append(
            f"| {r.scenario_id} | {r.traffic} | {r.agent} | {r.score:.1f} | "
            f"{r.pdm_score:.1f} | {what} |"
        )
    return "\n".join(lines) + "\n"


def write_json(path: str | Path, results: Sequence[ScenarioResult], meta: dict) -> None:
    """Every per-episode field and the summary, with ``meta`` (settings), sorted keys."""
    doc = {
        "meta": meta,
        "summary": summary(results),
        "episodes": [r.to_json() for r in results],
    }
    text = json.dumps(doc, indent=1, sort_keys=True, allow_nan=True)
    Path(path).write_text(text + "\n")


def plot_scores(path: str | Path, results: Sequence[ScenarioResult], title: str = "") -> None:
    """PNG: the distribution of the CLS and of the PDM score per traffic mode."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    groups = by_traffic(results)
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.6), sharey=True)
    bins = np.linspace(0, 100, 21)
    for ax, field, name in zip(axes, ("score", "pdm_score"), ("CLS", "PDM score")):
        for traffic, rs in groups.items():
            vals = [getattr(r, field) for r in rs]
            ax.hist(vals, bins=bins, histtype="step", linewidth=1.6,
                    label=f"{traffic} (mean {np.mean(vals):.1f})")  # fmt: skip
        ax.set_xlabel(name)
        ax.legend(fontsize=8)
    axes[0].set_ylabel("episodes")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def worst(results: Sequence[ScenarioResult], count: int) -> list[ScenarioResult]:
    """The ``count`` lowest-scoring episodes (failed ones first), in a stable order."""
    order = sorted(range(len(results)), key=lambda k: (results[k].error is None, results[k].score))
    return [results[k] for k in order[:count]]


def page_name(r: ScenarioResult) -> str:
    """File name of an episode's viewer page."""
    agent = r.agent.replace("/", "_")
    return f"{r.scenario_id}-{r.traffic}-{agent}.html"


def write_pages(
    out_dir: str | Path,
    picks: Sequence[ScenarioResult],
    scenarios: dict[str, Scenario],
    render,
) -> list[Path]:
    """A viewer page per picked episode (``render(scenario, result) -> ViewerRollout``)."""
    from tbsim_env.rendering.viewer import write_viewer

    out_dir = Path(out_dir)
    paths = []
    for r in picks:
        sc = scenarios[r.scenario_id]
        marks = "; ".join(f"t={0.1 * s:.1f}s: {w}" for s, w in r.infractions) or "none"
        title = f"{r.traffic} traffic, {r.agent}: CLS {r.score:.1f}, infractions: {marks}"
        path = out_dir / page_name(r)
        write_viewer(path, sc, [render(sc, r)], title=title)
        paths.append(path)
    return paths


def episode_rollout(scenario: Scenario, record, result: ScenarioResult, limit: float = 0.3):
    """The episode as a viewer rollout on the WOSAC grid: the logged history, then the
    simulated states; the ego's at-fault collisions and departures from the drivable area
    flagged at their steps (``ViewerRollout``; ``limit``: m beyond a road edge that count,
    ``BenchmarkConfig.drivable_violation``)."""
    from tbsim_env.rendering.palette import AgentGroup
    from tbsim_env.rendering.viewer import ViewerRollout, wosac_grid

    grid = wosac_grid(scenario)
    t = grid.tracks
    a, n_t, cur = t.num_tracks, grid.num_steps, grid.current_index
    x, y = np.full((a, n_t), np.nan), np.full((a, n_t), np.nan)
    yaw, speed = np.full((a, n_t), np.nan), np.full((a, n_t), np.nan)
    valid = np.zeros((a, n_t), bool)
    hist = slice(0, cur + 1)
    valid[:, hist] = t.valid[:, hist]
    x[:, hist], y[:, hist] = t.xyz[:, hist, 0], t.xyz[:, hist, 1]
    yaw[:, hist], speed[:, hist] = t.heading[:, hist], np.linalg.norm(t.velocity[:, hist], axis=-1)
    rows = record.track_index
    used = rows >= 0
    states = min(len(record.ego_pose), n_t - cur)
    ok = record.others_valid[:states].copy()
    ok[:, record.slot] = True
    pose = record.others_pose[:states].copy()
    pose[:, record.slot] = record.ego_pose[:states]
    spd = record.others_speed[:states].copy()
    spd[:, record.slot] = record.ego_speed[:states]
    fut = slice(cur, cur + states)
    valid[rows[used], fut] = ok[:, used].T
    for arr, src in ((x, pose[..., 0]), (y, pose[..., 1]), (yaw, pose[..., 2]), (speed, spd)):
        arr[rows[used], fut] = np.where(ok[:, used], src[:, used], np.nan).T
    npc = AgentGroup.LOG_REPLAY if record.traffic == "log_replay" else AgentGroup.POLICY
    group = np.full(a, int(npc), np.int64)
    ego = int(rows[record.slot])
    group[ego] = int(AgentGroup.EXTERNAL)
    collision, offroad = np.zeros((a, n_t), bool), np.zeros((a, n_t), bool)
    for e in result.collisions:
        if e["at_fault"] and cur + e["step"] < n_t:
            collision[ego, cur + e["step"]] = True
    off = np.flatnonzero(record.offroad_distance[:states] > limit)
    offroad[ego, cur + off] = True
    flagged = np.zeros(a, bool)
    flagged[ego] = True
    name = f"{record.traffic}: {record.agent}"
    return ViewerRollout(name, x, y, yaw, valid, group, speed, collision, offroad, flagged)
