"""docs/model_card/real_splits.json: disjoint lists that cover every real scene the loader reads
from the shared folder, by the rule scripts/make_real_splits.py states (reproduced here)."""

from __future__ import annotations

import json
import runpy
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
SPLITS_JSON = REPO / "docs" / "model_card" / "real_splits.json"
SCRIPT = runpy.run_path(str(REPO / "scripts" / "make_real_splits.py"))
SPLITS = SCRIPT["SPLITS"]


@pytest.fixture(scope="module")
def committed() -> dict:
    return json.loads(SPLITS_JSON.read_text())


def test_lists_are_disjoint_and_follow_the_rule(committed: dict) -> None:
    ids = [e["scenario_id"] for name in SPLITS for e in committed[name]]
    files = [e["file"] for name in SPLITS for e in committed[name]]
    assert len(ids) == len(set(ids)) and len(files) == len(set(files))
    assert committed["counts"] == {name: len(committed[name]) for name in SPLITS}
    split_of = SCRIPT["split_of"]
    for name in SPLITS:
        for e in committed[name]:
            assert split_of(e["scenario_id"], e["steps"] > 11) == name, e
    where = {e["scenario_id"]: name for name in SPLITS for e in committed[name]}
    assert {k: where[k] for k in SCRIPT["KEEP"]} == SCRIPT["KEEP"]
    assert {e["scenario_id"] for e in committed["history_only"]} == {
        "fcb5b4973f486e78",
        "1c8f1f7b63fc6118",
    }
    assert "tfrecord-00082-of-01000_465" in where  # the wosac_reference scene, once
    assert committed["counts"]["held_out"] >= 40


def test_the_file_is_what_the_script_builds_from_every_scene(
    committed: dict, womd_dir: Path
) -> None:
    """Every scenario the loader reads from the data folders has its entry (and no other)."""
    fresh = SCRIPT["build_splits"](womd_dir)
    assert fresh == committed
    files = SCRIPT["scene_files"](womd_dir)
    assert len(files) == sum(committed["counts"].values()) == 290
    formats = {e["format"] for name in SPLITS for e in committed[name]}
    assert formats == {"tfrecord", "tf_example", "scenarionet_pickle", "gpudrive_json"}
