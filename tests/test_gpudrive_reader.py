"""GPUDrive JSON reader: counts from the data README, conventions, and malformed input."""

from __future__ import annotations

import copy
import json
from pathlib import Path

import numpy as np
import pytest

from tbsim_env.core.constants import DT, MapFeatureType, ObjectType
from tbsim_env.core.errors import ScenarioFormatError
from tbsim_env.data.gpudrive import (
    INVALID_SENTINEL,
    ROAD_TYPES,
    map_element_to_feature,
    read_gpudrive_json,
    scenario_from_gpudrive,
)

# file -> (scenario_id, objects per type, roads, sdc index, #tracks_to_predict, objects_of_interest)
EXPECTED = {
    "tfrecord-00000-of-01000_222.json": ("1c365f15b70ebdbf", (23, 2, 0), 118, 24, 2, [1847, 1415]),
    "tfrecord-00000-of-01000_325.json": ("ef3a8f65142f41ac", (54, 8, 0), 157, 61, 3, []),
    "tfrecord-00000-of-01000_4.json": ("db4edc9bd0c9d18c", (68, 12, 1), 102, 80, 7, [18, 284]),
}


@pytest.fixture(scope="module")
def gpudrive_dir(womd_dir: Path) -> Path:
    return womd_dir / "gpudrive"


@pytest.fixture(scope="module")
def small_doc(gpudrive_dir: Path) -> dict:
    """The 25-object scene as decoded JSON (tests mutate deep copies)."""
    return json.loads((gpudrive_dir / "tfrecord-00000-of-01000_222.json").read_text())


@pytest.mark.parametrize("name", sorted(EXPECTED))
def test_real_files_match_readme_counts(gpudrive_dir: Path, name: str) -> None:
    sid, (veh, ped, cyc), roads, sdc, n_ttp, ooi = EXPECTED[name]
    raw = json.loads((gpudrive_dir / name).read_text())
    s = read_gpudrive_json(gpudrive_dir / name)
    assert s.scenario_id == sid
    types = np.bincount(s.tracks.object_type, minlength=5)
    assert (types[ObjectType.VEHICLE], types[ObjectType.PEDESTRIAN]) == (veh, ped)
    assert types[ObjectType.CYCLIST] == cyc and s.tracks.num_tracks == veh + ped + cyc
    assert s.road_map.num_features == roads
    assert s.sdc_index == sdc == s.tracks.num_tracks - 1
    assert len(s.tracks_to_predict) == n_ttp
    assert s.objects_of_interest.tolist() == ooi
    assert s.num_steps == 91 and s.current_index == 10
    np.testing.assert_allclose(s.timestamps, np.arange(91) * DT)
    assert s.signals.num_signals == 0
    # Object order and ids follow the JSON (metadata indices refer to it).
    assert s.tracks.id.tolist() == [o["id"] for o in raw["objects"]]
    # Map kinds agree with the JSON type strings, ids are kept.
    assert s.road_map.id.tolist() == [r["id"] for r in raw["roads"]]
    kinds = [int(ROAD_TYPES[r["type"]]) for r in raw["roads"]]
    assert s.road_map.feature_type.tolist() == kinds
    assert all(len(x) == 0 for x in s.road_map.entry_lanes)


def test_conventions_sentinel_sizes_heading(gpudrive_dir: Path, small_doc: dict) -> None:
    s = read_gpudrive_json(gpudrive_dir / "tfrecord-00000-of-01000_222.json")
    valid = np.array([o["valid"] for o in small_doc["objects"]])
    np.testing.assert_array_equal(s.tracks.valid, valid)
    raw_x = np.array([[p["x"] for p in o["position"]] for o in small_doc["objects"]])
    assert (raw_x[~valid] == INVALID_SENTINEL).all() and (~valid).sum() > 0
    inv = ~s.tracks.valid
    assert (s.tracks.xyz[inv] == 0).all() and (s.tracks.heading[inv] == 0).all()
    assert (s.tracks.velocity[inv] == 0).all() and (s.tracks.size[inv] == 0).all()
    np.testing.assert_array_equal(s.tracks.xyz[..., 0][~inv], raw_x[~inv])
    h = s.tracks.heading
    assert (h >= -np.float32(np.pi)).all() and (h < np.float32(np.pi)).all()
    for k, obj in enumerate(small_doc["objects"]):
        expect = np.array([obj["length"], obj["width"], obj["height"]], np.float32)
        assert (s.tracks.size[k][s.tracks.valid[k]] == expect).all()


def test_map_element_mapping_table() -> None:
    assert map_element_to_feature(2) == (MapFeatureType.LANE, 2)
    assert map_element_to_feature(5) == (MapFeatureType.ROAD_LINE, 0)
    assert map_element_to_feature(12) == (MapFeatureType.ROAD_LINE, 7)  # solid double yellow
    assert map_element_to_feature(13) == (MapFeatureType.ROAD_LINE, 8)
    assert map_element_to_feature(14) == (MapFeatureType.ROAD_EDGE, 0)
    assert map_element_to_feature(16) == (MapFeatureType.ROAD_EDGE, 2)
    assert map_element_to_feature(17) == (MapFeatureType.STOP_SIGN, 0)
    assert map_element_to_feature(20) == (MapFeatureType.DRIVEWAY, 0)
    assert map_element_to_feature(4) is None and map_element_to_feature(-1) is None


def test_real_subtypes(gpudrive_dir: Path, small_doc: dict) -> None:
    s = read_gpudrive_json(gpudrive_dir / "tfrecord-00000-of-01000_222.json")
    lines = s.road_map.indices_of(MapFeatureType.ROAD_LINE)
    edges = s.road_map.indices_of(MapFeatureType.ROAD_EDGE)
    raw_lines = [r["map_element_id"] for r in small_doc["roads"] if r["type"] == "road_line"]
    assert s.road_map.subtype[lines].tolist() == [e - 5 for e in raw_lines]
    assert set(s.road_map.subtype[edges].tolist()) == {1}  # 15: ROAD_EDGE_BOUNDARY
    stops = s.road_map.indices_of(MapFeatureType.STOP_SIGN)
    assert all(s.road_map.polylines[i].shape == (1, 3) for i in stops)


def _write(tmp_path: Path, doc: object) -> Path:
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(doc))
    return path


def _del(keys: list) -> object:
    def mutate(d: dict) -> None:
        target = d
        for k in keys[:-1]:
            target = target[k]
        del target[keys[-1]]

    return mutate


def _set(keys: list, value: object) -> object:
    def mutate(d: dict) -> None:
        target = d
        for k in keys[:-1]:
            target = target[k]
        target[keys[-1]] = value

    return mutate


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (_set(["scenario_id"], 5), "'scenario_id' must be a non-empty string"),
        (_del(["objects"]), "missing key 'objects'"),
        (_set(["metadata"], [1]), "metadata: expected a JSON object"),
        (_del(["metadata", "sdc_track_index"]), "metadata: missing key 'sdc_track_index'"),
        (_del(["objects", 3, "position"]), r"objects\[3\]: missing key 'position'"),
        (_del(["objects", 5, "valid"]), r"objects\[5\]: missing key 'valid'"),
        (_del(["objects", 2, "width"]), r"objects\[2\]: missing key 'width'"),
        (_del(["objects", 4, "id"]), r"objects\[4\]: missing key 'id'"),
        (_del(["objects", 1, "position", 7, "x"]), r"objects\[1\]\.position\[7\]"),
        (_del(["roads", 6, "geometry"]), r"roads\[6\]: missing key 'geometry'"),
        (_del(["roads", 6, "type"]), r"roads\[6\]: missing key 'type'"),
        (_set(["objects"], []), "non-empty list"),
        (_set(["objects", 0, "type"], "spaceship"), r"objects\[0\]\.type: unknown object type"),
        (_set(["objects", 0, "heading", 3], "north"), r"objects\[0\]\.heading"),
        (_set(["objects", 2, "valid"], [True] * 90), r"objects\[2\]: .*different lengths"),
        (_set(["objects", 10, "valid"], [True] * 91), r"objects\[10\]: step \d+ .*sentinel"),
        (_set(["roads", 0, "map_element_id"], 17), r"roads\[0\]: type '\w+' disagrees"),
        (_set(["metadata", "sdc_track_index"], 99), "sdc_track_index"),
        (_set(["objects", 1, "id"], "x"), r"objects\[1\]\.id"),
        (_set(["objects", 0, "position", 0, "x"], float("nan")), "non-finite"),
        # Physically impossible values of valid states name the object (track id, index),
        # the step and the field.
        (_set(["objects", 0, "length"], 0.0), r"track \d+ \(index 0\) at step \d+: field 'length'"),
        (_set(["objects", 3, "width"], -1.8), r"\(index 3\) .* field 'width' .*not positive"),
        (_set(["objects", 3, "height"], float("nan")), r"\(index 3\) .* 'height' .*non-finite"),
        (_set(["objects", 0, "velocity", 0, "y"], float("inf")), r"'velocity_y' .*non-finite"),
        (_set(["objects", 0, "heading", 0], float("nan")), r"at step 0: field 'heading'"),
        (_set(["objects", 0, "position", 0, "y"], -1e30), r"'center_y' .* lies beyond"),
    ],
)
def test_malformed_json_names_key_and_index(
    tmp_path: Path, small_doc: dict, mutate, message: str
) -> None:
    doc = copy.deepcopy(small_doc)
    mutate(doc)
    assert not all(small_doc["objects"][10]["valid"])  # the sentinel case needs invalid steps
    path = _write(tmp_path, doc)
    with pytest.raises(ScenarioFormatError, match=message) as info:
        read_gpudrive_json(path)
    assert info.value.path == str(path)


def test_not_json_and_not_an_object(tmp_path: Path) -> None:
    bad = tmp_path / "bad.json"
    bad.write_bytes(b'{"scenario_id": "ab", "objects": [')
    with pytest.raises(ScenarioFormatError, match="not valid JSON"):
        read_gpudrive_json(bad)
    bad.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(ScenarioFormatError, match="not valid JSON"):
        read_gpudrive_json(bad)
    with pytest.raises(ScenarioFormatError, match="expected a JSON object"):
        read_gpudrive_json(_write(tmp_path, [1, 2, 3]))
    with pytest.raises(FileNotFoundError):
        read_gpudrive_json(tmp_path / "none.json")


def test_unknown_roads_and_empty_geometry_skipped_with_warning(small_doc: dict) -> None:
    doc = copy.deepcopy(small_doc)
    doc["roads"][0].update(type="unknown", map_element_id=-1)
    doc["roads"][1]["geometry"] = []
    with pytest.warns(UserWarning, match=r"skipped 2 road\(s\)"):
        s = scenario_from_gpudrive(doc, source="mem")
    assert s.road_map.num_features == len(doc["roads"]) - 2


def test_missing_map_element_id_falls_back_to_type(small_doc: dict) -> None:
    doc = copy.deepcopy(small_doc)
    for road in doc["roads"]:
        del road["map_element_id"]
    s = scenario_from_gpudrive(doc)
    assert s.road_map.feature_type.tolist() == [int(ROAD_TYPES[r["type"]]) for r in doc["roads"]]
    assert (s.road_map.subtype == 0).all()


def test_no_roads_warns(small_doc: dict) -> None:
    doc = copy.deepcopy(small_doc)
    doc["roads"] = []
    with pytest.warns(UserWarning, match="no map features"):
        s = scenario_from_gpudrive(doc)
    assert s.road_map.num_features == 0
