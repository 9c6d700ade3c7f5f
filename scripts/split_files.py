"""Print the files of one split of docs/model_card/real_splits.json, one absolute path a line.

    tbsim preprocess $(python scripts/split_files.py train) --out cache/real_train

The paths are under the WOMD data folder (``--womd-dir``, default ``$TBSIM_WOMD_DIR`` or
``../shared/data/womd``); every file holds one scene.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SPLITS_JSON = REPO / "docs" / "model_card" / "real_splits.json"


def split_files(split: str, womd_dir: Path) -> list[Path]:
    """Files of ``split`` (train, validation, held_out, history_only) in the splits' order.

    Raises:
        KeyError: no such split.
        FileNotFoundError: a listed file is missing under ``womd_dir``.
    """
    doc = json.loads(SPLITS_JSON.read_text())
    if split not in doc["counts"]:
        raise KeyError(f"no split {split!r}; the splits are {sorted(doc['counts'])}")
    files = [womd_dir / e["file"] for e in doc[split]]
    missing = [str(f) for f in files if not f.is_file()]
    if missing:
        raise FileNotFoundError(f"{len(missing)} file(s) of split {split!r} missing: {missing[:3]}")
    return files


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("split", choices=("train", "validation", "held_out", "history_only"))
    default = os.environ.get("TBSIM_WOMD_DIR", str(REPO.parent / "shared" / "data" / "womd"))
    p.add_argument("--womd-dir", type=Path, default=Path(default))
    args = p.parse_args()
    text = "\n".join(str(f) for f in split_files(args.split, args.womd_dir.resolve()))
    try:
        print(text)
    except BrokenPipeError:  # e.g. piped into head
        sys.stderr.close()


if __name__ == "__main__":
    main()
