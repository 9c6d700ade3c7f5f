"""Gzip-compressed scenario files: every format read as its plain file is, bad streams refused.

The real files are compressed here (the shared data stays untouched); the GPUDrive-CoDec scenes
of the shared folder come gzip-compressed as published.
"""

from __future__ import annotations

import gzip
import shutil
from pathlib import Path

import numpy as np
import pytest

from tbsim_env.cli import main
from tbsim_env.core.errors import ScenarioFormatError
from tbsim_env.data.compressed import is_gzip, read_all
from tbsim_env.data.loader import ScenarioFileFormat, detect_format, iter_scenarios, load_scenarios
from tbsim_env.data.scenario import Scenario
from tbsim_env.data.tfrecord import build_index, iter_records, read_record, write_records
from tbsim_env.distributed import load_by_id, plan_shards


def _gzip(src: Path, dst: Path) -> Path:
    with open(src, "rb") as fi, gzip.open(dst, "wb") as fo:
        shutil.copyfileobj(fi, fo)
    return dst


def _same(a: Scenario, b: Scenario) -> None:
    assert a.scenario_id == b.scenario_id
    np.testing.assert_array_equal(a.tracks.xyz, b.tracks.xyz)
    np.testing.assert_array_equal(a.tracks.valid, b.tracks.valid)
    np.testing.assert_array_equal(a.road_map.id, b.road_map.id)


@pytest.fixture
def two_scene_tfrecord(tmp_path: Path, one_scenario_path: Path, scenario_input_path: Path) -> Path:
    """A plain TFRecord of two real Scenario records."""
    payloads = [p for f in (one_scenario_path, scenario_input_path) for _, _, p in iter_records(f)]
    path = tmp_path / "two.tfrecord"
    write_records(path, payloads)
    return path


def test_every_format_reads_as_its_plain_file(
    tmp_path: Path, womd_dir: Path, two_scene_tfrecord: Path, tf_example_path: Path
) -> None:
    plain = [
        two_scene_tfrecord,
        tf_example_path,
        womd_dir / "gpudrive" / "tfrecord-00000-of-01000_4.json",
        womd_dir / "scenarionet" / "sd_waymo_v1.2_eb4b91b10ca94ff2.pkl",
    ]
    for src in plain:
        packed = _gzip(src, tmp_path / (src.name + ".gz"))
        assert is_gzip(packed) and not is_gzip(src)
        assert detect_format(packed) is detect_format(src)
        want, got = load_scenarios(src), load_scenarios(packed)
        assert len(got) == len(want) >= 1
        for a, b in zip(want, got):
            _same(a, b)


def test_published_gzip_json_scenes_load(womd_dir: Path) -> None:
    files = sorted((womd_dir / "gpudrive_codec").glob("*.json.gz"))[:3]
    assert len(files) == 3
    scenes = load_scenarios(files)
    assert [s.num_steps for s in scenes] == [91, 91, 91]
    assert all(s.current_index == 10 and s.tracks.num_tracks >= 2 for s in scenes)
    assert detect_format(files[0]) is ScenarioFileFormat.GPUDRIVE_JSON


def test_a_folder_lists_gzip_files(tmp_path: Path, womd_dir: Path) -> None:
    src = womd_dir / "gpudrive" / "tfrecord-00000-of-01000_4.json"
    shutil.copy(src, tmp_path / "a.json")
    _gzip(src, tmp_path / "b.json.gz")
    (tmp_path / "notes.txt.gz").write_bytes(gzip.compress(b"not a scene"))
    assert len(load_scenarios(tmp_path)) == 2


def test_a_gzip_tfrecord_is_streamed_record_by_record(
    tmp_path: Path, two_scene_tfrecord: Path
) -> None:
    """The first scene comes out before the damaged end of the stream is reached."""
    data = gzip.compress(two_scene_tfrecord.read_bytes())
    path = tmp_path / "cut.tfrecord.gz"
    path.write_bytes(data[: int(len(data) * 0.8)])
    it = iter_scenarios(path)
    first = next(it)
    assert first.scenario_id == "637f20cafde22ff8"
    with pytest.raises(ScenarioFormatError, match=r"record 1.*gzip stream") as err:
        next(it)
    assert str(path) in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(ScenarioFormatError):
        load_scenarios(path)  # nothing returned half
    with pytest.warns(UserWarning, match="cannot resynchronise"):
        assert [s.scenario_id for s in load_scenarios(path, skip_bad=True)] == [first.scenario_id]


@pytest.mark.parametrize("damage", ["truncated", "corrupt", "trailer"])
def test_a_bad_gzip_json_is_one_error_naming_the_file(
    tmp_path: Path, womd_dir: Path, damage: str
) -> None:
    src = womd_dir / "gpudrive" / "tfrecord-00000-of-01000_4.json"
    data = bytearray(gzip.compress(src.read_bytes()))
    if damage == "truncated":
        data = data[: len(data) // 2]
    elif damage == "corrupt":
        data[len(data) // 2 : len(data) // 2 + 64] = bytes(64)
    else:
        data[-8] ^= 0xFF  # the CRC-32 of the trailer
    path = tmp_path / "bad.json.gz"
    path.write_bytes(bytes(data))
    with pytest.raises(ScenarioFormatError, match="gzip stream") as err:
        load_scenarios(path)
    assert str(path) in str(err.value)


def test_a_file_with_only_the_gzip_magic_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "x.pkl.gz"
    path.write_bytes(b"\x1f\x8b\x08\x00garbage")
    with pytest.raises(ScenarioFormatError, match=r"x\.pkl\.gz.*gzip"):
        load_scenarios(path)
    with pytest.raises(ScenarioFormatError, match="gzip"):
        read_all(path)


def test_random_access_refuses_a_gzip_tfrecord(tmp_path: Path, two_scene_tfrecord: Path) -> None:
    path = _gzip(two_scene_tfrecord, tmp_path / "two.tfrecord.gz")
    with pytest.raises(ScenarioFormatError, match="gunzip the file for access"):
        build_index(path)
    with pytest.raises(ScenarioFormatError, match="gunzip the file for access"):
        read_record(path, 0)


def test_sharding_keeps_a_gzip_tfrecord_whole(tmp_path: Path, two_scene_tfrecord: Path) -> None:
    path = _gzip(two_scene_tfrecord, tmp_path / "two.tfrecord.gz")
    shards = plan_shards([str(path)], "s-{k}-of-{n}", shard_size=1)
    assert len(shards) == 1 and shards[0].items[0].start is None
    assert [s.scenario_id for s in load_by_id([str(path)], {"ee519cf571686d19"})] == [
        "ee519cf571686d19"
    ]


def test_cli_info_reads_a_gzip_file(capsys, womd_dir: Path) -> None:
    path = sorted((womd_dir / "gpudrive_codec").glob("*.json.gz"))[0]
    assert main(["info", str(path)]) == 0
    out = capsys.readouterr().out
    assert load_scenarios(path)[0].scenario_id in out
