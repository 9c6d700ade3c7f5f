"""Plot the scalars of a training run (``<run>/metrics.jsonl``) to a PNG.

Several run folders (stages of one run, each resuming the previous) are joined in step order; a
step logged twice (a segment resumed from an earlier checkpoint) keeps its last value, and a
dashed line marks where each later stage starts. ``RUN@N`` shifts a run's steps by N: a
fine-tuning stage (``tbsim train --init``) counts its steps from 1 again.

python scripts/plot_training.py runs/small_v1 [runs/small_v2 runs/small_v3@1030 ...] out.png
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

KEYS = (
    ("loss", "total loss"),
    ("imitation", "imitation (position/yaw/speed)"),
    ("destination", "destination CE"),
    ("tl_state", "TL-state NLL"),
)


def smooth(y: np.ndarray, k: int = 5) -> np.ndarray:
    if len(y) < k:
        return y
    return np.convolve(y, np.ones(k) / k, mode="valid")


def load_rows(runs: list[str]) -> tuple[list[dict], list[int]]:
    """Rows of all runs by step (later logs of a step win) and the first step of each later run.

    A run is a folder, or ``FOLDER@N`` to add N to its steps."""
    by_step: dict[int, dict] = {}
    starts = []
    for k, spec in enumerate(runs):
        folder, _, shift = spec.partition("@")
        rows = [json.loads(x) for x in (Path(folder) / "metrics.jsonl").read_text().splitlines()]
        rows = [{**r, "step": r["step"] + int(shift or 0)} for r in rows]
        if k > 0 and rows:
            starts.append(min(r["step"] for r in rows))
        for r in rows:
            by_step[r["step"]] = r
    return [by_step[s] for s in sorted(by_step)], starts


def main() -> None:
    *runs, out = sys.argv[1:]
    out = Path(out)
    rows, starts = load_rows(runs)
    steps = np.array([r["step"] for r in rows])
    fig, axes = plt.subplots(1, len(KEYS), figsize=(4 * len(KEYS), 3.2))
    for ax, (key, label) in zip(axes, KEYS):
        y = np.array([r[key] for r in rows])
        ax.plot(steps, y, alpha=0.3, color="tab:blue")
        ys = smooth(y)
        ax.plot(steps[len(steps) - len(ys) :], ys, color="tab:blue")
        for s0 in starts:
            ax.axvline(s0, color="gray", ls="--", lw=1)
        ax.set_title(label)
        ax.set_xlabel("optimiser step")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=80)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
