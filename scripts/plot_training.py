"""Plot the scalars of a training run (``<run>/metrics.jsonl``) to a PNG.

python scripts/plot_training.py runs/small_v1 docs/model_card/loss_curve.png
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


def main() -> None:
    run, out = Path(sys.argv[1]), Path(sys.argv[2])
    rows = [json.loads(x) for x in (run / "metrics.jsonl").read_text().splitlines()]
    steps = np.array([r["step"] for r in rows])
    fig, axes = plt.subplots(1, len(KEYS), figsize=(4 * len(KEYS), 3.2))
    for ax, (key, label) in zip(axes, KEYS):
        y = np.array([r[key] for r in rows])
        ax.plot(steps, y, alpha=0.3, color="tab:blue")
        ys = smooth(y)
        ax.plot(steps[len(steps) - len(ys) :], ys, color="tab:blue")
        ax.set_title(label)
        ax.set_xlabel("optimiser step")
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=80)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
