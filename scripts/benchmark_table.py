"""One table of planners x traffic modes from ``tbsim benchmark --json`` files.

    python scripts/benchmark_table.py runs/bench/*.json

Rows are planners (``meta.planner`` of each file), columns the traffic modes, cells
``CLS / PDMS (failed)`` averaged over the file's episodes; several files of one planner (e.g.
run per traffic mode) are merged.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path


def merged(paths: list[Path]) -> tuple[dict[str, dict[str, dict]], list[str], int]:
    """({planner: {traffic: summary row}}, traffic modes in first-seen order, episodes)."""
    table: dict[str, dict[str, dict]] = {}
    modes: list[str] = []
    scenes: set[str] = set()
    for path in paths:
        doc = json.loads(path.read_text())
        planner = doc["meta"]["planner"]
        for traffic, row in doc["summary"].items():
            table.setdefault(planner, {})[traffic] = row
            if traffic not in modes:
                modes.append(traffic)
        scenes |= {e["scenario_id"] for e in doc["episodes"]}
    return table, modes, len(scenes)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("files", nargs="+", type=Path)
    args = p.parse_args()
    table, modes, n = merged(args.files)
    print(f"CLS / PDMS over {n} scenes (failed episodes in brackets)\n")
    print("| planner | " + " | ".join(modes) + " |")
    print("|---|" + "---|" * len(modes))
    for planner, rows in table.items():
        cells = []
        for m in modes:
            r = rows.get(m)
            failed = f" ({int(r['failed'])})" if r and r["failed"] else ""
            cells.append(f"{r['score']:.1f} / {r['pdm_score']:.1f}{failed}" if r else "-")
        print(f"| {planner} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
