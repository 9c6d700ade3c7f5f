"""load_scenarios / iter_scenarios: sources, format detection, errors, skip_bad."""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import pytest

from tbsim_env.core.errors import ScenarioFormatError
from tbsim_env.data import iter_scenarios, load_scenarios
from tbsim_env.data.loader import ScenarioFileFormat, detect_format

RAW_IDS = ["637f20cafde22ff8", "ee519cf571686d19"]
GPUDRIVE_IDS = ["1c365f15b70ebdbf", "ef3a8f65142f41ac", "db4edc9bd0c9d18c"]  # sorted file names


def _link(target: Path, link: Path) -> Path:
    """Symlink (no copy of the licensed data) into a temporary folder."""
    os.symlink(target, link)
    return link


def test_single_files_and_folder(womd_dir: Path, one_scenario_path: Path) -> None:
    assert [s.scenario_id for s in load_scenarios(one_scenario_path)] == RAW_IDS[:1]
    assert [s.scenario_id for s in load_scenarios(str(one_scenario_path))] == RAW_IDS[:1]
    assert [s.scenario_id for s in load_scenarios(womd_dir / "gpudrive")] == GPUDRIVE_IDS


def test_glob_and_list_preserve_order(
    womd_dir: Path, one_scenario_path: Path, scenario_input_path: Path
) -> None:
    pattern = str(womd_dir / "waymo-open-dataset" / "*scenario*.tfrecord")
    assert [s.scenario_id for s in load_scenarios(pattern)] == RAW_IDS
    mixed = load_scenarios([scenario_input_path, womd_dir / "gpudrive", one_scenario_path])
    assert [s.scenario_id for s in mixed] == [RAW_IDS[1], *GPUDRIVE_IDS, RAW_IDS[0]]


def test_scenario_objects_pass_through(one_scenario_path: Path) -> None:
    scenarios = load_scenarios(one_scenario_path)
    again = load_scenarios(scenarios)
    assert again == scenarios and again[0] is scenarios[0]
    mixed = load_scenarios([scenarios[0], one_scenario_path])
    assert mixed[0] is scenarios[0] and mixed[1].scenario_id == RAW_IDS[0]


def test_folder_is_sorted_and_filtered(
    tmp_path: Path, one_scenario_path: Path, scenario_input_path: Path, womd_dir: Path
) -> None:
    _link(scenario_input_path, tmp_path / "a.tfrecord-00000-of-00002")
    _link(one_scenario_path, tmp_path / "b.tfrecord-00001-of-00002")
    _link(womd_dir / "gpudrive" / "tfrecord-00000-of-01000_4.json", tmp_path / "c.json")
    (tmp_path / "notes.txt").write_text("not a scenario")
    (tmp_path / "sub").mkdir()
    got = [s.scenario_id for s in load_scenarios(tmp_path)]
    assert got == [RAW_IDS[1], RAW_IDS[0], GPUDRIVE_IDS[2]]


def test_format_detected_by_content(
    tmp_path: Path, one_scenario_path: Path, womd_dir: Path
) -> None:
    raw = _link(one_scenario_path, tmp_path / "scene.bin")
    js = _link(womd_dir / "gpudrive" / "tfrecord-00000-of-01000_222.json", tmp_path / "scene.dat")
    assert detect_format(raw) is ScenarioFileFormat.TFRECORD
    assert detect_format(js) is ScenarioFileFormat.GPUDRIVE_JSON
    assert [s.scenario_id for s in load_scenarios([raw, js])] == [RAW_IDS[0], GPUDRIVE_IDS[0]]
    junk = tmp_path / "junk.bin"
    junk.write_bytes(b"PK\x03\x04 definitely not a scenario")
    with pytest.raises(ScenarioFormatError, match="unrecognised scenario file"):
        load_scenarios(junk)
    # A broken file with a known extension gets the reader's own error.
    broken = tmp_path / "broken.json"
    broken.write_bytes(b"\x00\x01 not json")
    with pytest.raises(ScenarioFormatError, match="not valid JSON"):
        load_scenarios(broken)


def test_missing_paths(tmp_path: Path) -> None:
    with pytest.raises(FileNotFoundError, match="nope.tfrecord"):
        load_scenarios(tmp_path / "nope.tfrecord")
    with pytest.raises(FileNotFoundError, match="matched no files"):
        load_scenarios(str(tmp_path / "*.tfrecord"))
    with pytest.raises(FileNotFoundError, match="no \\*.tfrecord\\*, \\*.json or \\*.pkl files"):
        load_scenarios(tmp_path)
    with pytest.raises(FileNotFoundError):  # raised at call time, not on first next()
        iter_scenarios([tmp_path / "missing.json"])
    with pytest.raises(TypeError):
        load_scenarios(42)  # type: ignore[arg-type]


def test_empty_file_and_nothing_loadable(tmp_path: Path) -> None:
    empty = tmp_path / "empty.tfrecord"
    empty.write_bytes(b"")
    with pytest.raises(ScenarioFormatError, match="no scenarios in file"):
        load_scenarios(empty)
    with pytest.warns(UserWarning), pytest.raises(ScenarioFormatError, match="no scenarios"):
        load_scenarios(empty, skip_bad=True)


def test_iter_is_lazy(tmp_path: Path, one_scenario_path: Path) -> None:
    good = _link(one_scenario_path, tmp_path / "a.tfrecord")
    bad = tmp_path / "b.tfrecord"
    bad.write_bytes(b"\x00" * 40)
    it = iter_scenarios([good, bad])
    assert next(it).scenario_id == RAW_IDS[0]  # the bad file is not touched yet
    with pytest.raises(ScenarioFormatError, match="b.tfrecord"):
        next(it)


def test_skip_bad_across_files(
    tmp_path: Path, one_scenario_path: Path, tf_example_path: Path, womd_dir: Path
) -> None:
    cut = tmp_path / "example_cut.tfrecord"  # a tf.Example file cut inside its record
    cut.write_bytes(tf_example_path.read_bytes()[:-1000])
    no_objects = tmp_path / "no_objects.json"
    no_objects.write_text('{"scenario_id": "x", "roads": []}')
    sources = [
        cut,
        one_scenario_path,
        no_objects,
        womd_dir / "gpudrive" / "tfrecord-00000-of-01000_4.json",
    ]
    with pytest.raises(ScenarioFormatError, match="example_cut"):
        load_scenarios(sources)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = load_scenarios(sources, skip_bad=True)
    assert [s.scenario_id for s in got] == [RAW_IDS[0], GPUDRIVE_IDS[2]]
    text = "\n".join(str(w.message) for w in caught)
    assert "example_cut.tfrecord" in text and "no_objects.json" in text
