"""Assign every real WOMD scene the project has to train / validation / held_out / history_only.

The rule was fixed before any result on these scenes was looked at:

* held out: 637f20cafde22ff8 and db4edc9bd0c9d18c (the model card's held-out real scenes);
  train: ee519cf571686d19, 1c365f15b70ebdbf and ef3a8f65142f41ac (the real scenes the shipped
  weights trained on);
* the WOSAC test-split scenes, which log only the 11 history steps (``Scenario.has_future``
  False), go to ``history_only``: no future, so usable only for export;
* every other scene by its scenario id ``sid``:
  ``int(hashlib.sha256(sid.encode()).hexdigest()[:8], 16) % 10`` in {0, 1} -> held_out,
  {2, 3} -> validation, else train.

Scenes are every scenario ``tbsim_env.load_scenarios`` reads from the data folders under the
WOMD directory (``SCENE_FOLDERS``, recursively, gzip-compressed files included). The rule is a
function of the scenario id alone, so adding a folder (``gpudrive_codec/``, 168 scenes) extends
the splits without moving any scene already assigned. ``wosac_reference/`` is left out: its one
scene is the Nocturne scene ``gpudrive_history/nocturne_format/tfrecord-00082-of-01000_465.json``
converted for the official metrics (same scenario id), so that id is assigned once.

    python scripts/make_real_splits.py [--womd-dir ../shared/data/womd]
        [--out docs/model_card/real_splits.json]

The output depends only on the data: entries sorted by file, no dates.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import os
import warnings
from pathlib import Path

from tbsim_env.data.compressed import strip_gz
from tbsim_env.data.loader import detect_format, load_scenarios

REPO = Path(__file__).resolve().parents[1]
SCENE_FOLDERS = (
    "waymo-open-dataset",
    "gpudrive",
    "nocturne",
    "scenarionet",
    "scenarionet_more",
    "gpudrive_history",
    "gpudrive_codec",
)
SCENE_SUFFIXES = (".tfrecord", ".json", ".pkl")
"""Scene files by their name without a trailing ``.gz`` (``gpudrive_codec/`` is gzip JSON)."""
NOT_SCENES = frozenset({"MANIFEST.json"})
"""Data-folder files with a scene suffix that describe the folder instead."""
SPLITS = ("train", "validation", "held_out", "history_only")
KEEP = {
    "637f20cafde22ff8": "held_out",
    "db4edc9bd0c9d18c": "held_out",
    "ee519cf571686d19": "train",
    "1c365f15b70ebdbf": "train",
    "ef3a8f65142f41ac": "train",
}
RULE = (
    "kept: held_out 637f20cafde22ff8, db4edc9bd0c9d18c; train ee519cf571686d19, "
    "1c365f15b70ebdbf, ef3a8f65142f41ac. Scenes without a logged future (WOSAC test split) -> "
    "history_only. Else int(sha256(scenario_id).hexdigest()[:8], 16) % 10 in {0, 1} -> "
    "held_out, {2, 3} -> validation, else train."
)

FILES_NOTE = "relative to the WOMD data folder ($TBSIM_WOMD_DIR, default ../shared/data/womd)"


def split_of(scenario_id: str, has_future: bool = True) -> str:
    """The split of one scene by the rule above."""
    if scenario_id in KEEP:
        return KEEP[scenario_id]
    if not has_future:
        return "history_only"
    bucket = int(hashlib.sha256(scenario_id.encode()).hexdigest()[:8], 16) % 10
    return "held_out" if bucket < 2 else "validation" if bucket < 4 else "train"


def scene_files(womd_dir: Path) -> list[Path]:
    """Every scene file of ``SCENE_FOLDERS``, sorted by path relative to ``womd_dir``."""
    files = [
        p
        for folder in SCENE_FOLDERS
        for p in (womd_dir / folder).rglob("*")
        if p.is_file()
        and Path(strip_gz(p.name)).suffix in SCENE_SUFFIXES
        and p.name not in NOT_SCENES
    ]
    return sorted(files, key=lambda p: p.relative_to(womd_dir).as_posix())


def build_splits(womd_dir: Path) -> dict:
    """The splits document: the rule, the counts and one entry per scene in each split."""
    out: dict = {"rule": RULE, "files": FILES_NOTE, "excluded": {}, "counts": {}}
    out["excluded"]["wosac_reference/"] = (
        "conversion of gpudrive_history/nocturne_format/tfrecord-00082-of-01000_465.json "
        "for the official metrics (same scenario id)"
    )
    lists: dict[str, list] = {name: [] for name in SPLITS}
    for path in scene_files(womd_dir):
        rel = path.relative_to(womd_dir).as_posix()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # e.g. Nocturne objects without a recorded size
            scenes = load_scenarios(path)
        for s in scenes:
            entry = {
                "file": rel,
                "scenario_id": s.scenario_id,
                "format": detect_format(path).value,
                "steps": s.num_steps,
                "tracks": s.tracks.num_tracks,
            }
            lists[split_of(s.scenario_id, s.has_future)].append(entry)
    out["counts"] = {name: len(lists[name]) for name in SPLITS}
    out.update(lists)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    default_dir = os.environ.get("TBSIM_WOMD_DIR", str(REPO.parent / "shared" / "data" / "womd"))
    parser.add_argument("--womd-dir", type=Path, default=Path(default_dir))
    parser.add_argument(
        "--out", type=Path, default=REPO / "docs" / "model_card" / "real_splits.json"
    )
    args = parser.parse_args()
    doc = build_splits(args.womd_dir)
    args.out.write_text(json.dumps(doc, indent=1) + "\n")
    print(f"{args.out}: {doc['counts']}")


if __name__ == "__main__":
    main()
