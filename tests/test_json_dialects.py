"""The GPUDrive / Nocturne JSON dialects (gpudrive_history/, nocturne/): every shared file against
the READMEs, degrees vs radians, roles chosen like the WOSAC reference conversion, signals in both
layouts, malformed input, fuzz."""

from __future__ import annotations

import copy
import json
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from tbsim_env.core.constants import CURRENT_INDEX, MapFeatureType, ObjectType, SignalState
from tbsim_env.core.errors import ScenarioFormatError
from tbsim_env.data.conversion import DEFAULT_BOX_HEIGHT_M, TYPICAL_BOX_SIZE_M
from tbsim_env.data.gpudrive import read_gpudrive_json, scenario_from_gpudrive
from tbsim_env.data.womd import read_scenarios
from tests.real_format_support import check_raw_heading, heading_error, mutate_document, outcome

ROW = re.compile(
    r"^\| `(?P<file>[^`]+\.json)` \| (?P<sid>[\w-]+) \| (?P<objects>\d+) \| (?P<roads>\d+) \| "
    r"(?P<lights>\d+) \|"
)
# nocturne/ (data/womd/README.md section 3): objects, roads, signal lanes.
NOCTURNE = {
    "nocturne/tfrecord-00358-of-01000_65.json": (45, 134, 0),
    "nocturne/tfrecord-00358-of-01000_280.json": (80, 148, 0),
    "nocturne/tfrecord-00754-of-01000_171.json": (77, 316, 11),
}
HISTORY_ONLY = {"fcb5b4973f486e78", "1c8f1f7b63fc6118"}  # WOSAC test split: 11 steps


def _expected(womd_dir: Path) -> dict[str, tuple]:
    """file (relative to womd_dir) -> (scenario id or None, objects, roads, signal lanes)."""
    out = {name: (None, *row) for name, row in NOCTURNE.items()}
    for line in (womd_dir / "gpudrive_history" / "README.md").read_text().splitlines():
        m = ROW.match(line)
        if m:
            sid = None if m["sid"] == "-" else m["sid"]
            row = (sid, int(m["objects"]), int(m["roads"]), int(m["lights"]))
            out["gpudrive_history/" + m["file"]] = row
    return out


@pytest.fixture(scope="module")
def real(womd_dir: Path) -> dict[str, tuple]:
    """file -> (expected README row, Scenario) for every JSON of gpudrive_history/ and nocturne/."""
    expected = _expected(womd_dir)
    files = sorted(
        str(p.relative_to(womd_dir))
        for pattern in ("gpudrive_history/*/*.json", "nocturne/*.json")
        for p in womd_dir.glob(pattern)
    )
    assert files == sorted(expected) and len(files) == 73
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        warnings.filterwarnings("ignore", ".*size not recorded")  # nocturne/ only (see below)
        return {f: (expected[f], read_gpudrive_json(womd_dir / f)) for f in files}


def test_every_file_matches_the_readmes(real: dict) -> None:
    kinds = np.zeros(len(MapFeatureType), int)
    for name, ((sid, n_objects, n_roads, n_lights), s) in real.items():
        assert s.scenario_id == (sid or Path(name).stem), name
        assert s.tracks.num_tracks == n_objects and s.road_map.num_features == n_roads
        assert s.signals.num_signals == n_lights, name
        assert s.num_steps == (11 if s.scenario_id in HISTORY_ONLY else 91)
        assert s.current_index == CURRENT_INDEX
        assert heading_error(s) < 0.1, name  # degrees read as radians give 0.3-2.1
        check_raw_heading(s)
        kinds += np.bincount(s.road_map.feature_type, minlength=len(MapFeatureType))
    assert (kinds > 0).all(), kinds


def test_roles_of_scenes_without_metadata(real: dict, womd_dir: Path) -> None:
    chosen = 0
    for name, (_, s) in real.items():
        if "metadata" in json.loads((womd_dir / name).read_text()):
            continue
        chosen += 1
        t = s.tracks
        assert t.object_type[s.sdc_index] == ObjectType.VEHICLE and t.valid[s.sdc_index].all()
        ttp = s.tracks_to_predict
        assert len(ttp) <= 8 and s.sdc_index not in ttp and (s.predict_difficulty == 0).all()
        assert t.valid[ttp, CURRENT_INDEX:].all() and len(s.objects_of_interest) == 0
    assert chosen == 15 + 52 + 3  # gpudrive_early, nocturne_format, nocturne


def test_nocturne_scene_equals_the_wosac_reference_conversion(real: dict, womd_dir: Path) -> None:
    """The reference tfrecord is this JSON converted by the rule the reader documents."""
    (_, s) = real["gpudrive_history/nocturne_format/tfrecord-00082-of-01000_465.json"]
    (ref,) = list(
        read_scenarios(womd_dir / "wosac_reference" / "tfrecord-00082-of-01000_465.tfrecord")
    )
    assert s.scenario_id == ref.scenario_id and s.sdc_index == ref.sdc_index
    assert s.tracks_to_predict.tolist() == ref.tracks_to_predict.tolist() == [9, 0, 1]
    for field in (
        "id",
        "object_type",
        "valid",
        "xyz",
        "heading",
        "velocity",
        "size",
        "raw_heading",
    ):
        np.testing.assert_array_equal(getattr(s.tracks, field), getattr(ref.tracks, field))
    np.testing.assert_array_equal(s.road_map.id, ref.road_map.id)
    np.testing.assert_array_equal(s.road_map.feature_type, ref.road_map.feature_type)
    for a, b in zip(s.road_map.polylines, ref.road_map.polylines):
        np.testing.assert_array_equal(a, b)


def test_signals_in_both_layouts(real: dict, womd_dir: Path) -> None:
    name = "gpudrive_history/gpudrive_early/tfrecord-00001-of-00150_c9bbd79edc48bbcb.json"
    (_, s) = real[name]
    raw = json.loads((womd_dir / name).read_text())["tl_states"]
    for key, entry in raw.items():  # lists shorter than 91: one entry per known step
        row = s.signals.lane_id.tolist().index(int(key))
        assert s.signals.valid[row].sum() == len(entry["state"])
        assert np.flatnonzero(s.signals.valid[row]).tolist() == entry["time_index"]
    assert min(len(e["state"]) for e in raw.values()) < 91
    # nocturne/: no road ids, 2-D stop points; each signal goes to the lane starting there.
    (_, n) = real["nocturne/tfrecord-00754-of-01000_171.json"]
    rm = n.road_map
    for lane, stop in zip(n.signals.lane_id, n.signals.stop_point):
        k = rm.index_of_id()[int(lane)]
        assert rm.feature_type[k] == MapFeatureType.LANE
        assert np.linalg.norm(rm.polylines[k][0, :2] - stop[:2]) < 1e-6
    assert set(n.signals.state[n.signals.valid].tolist()) == {
        SignalState.STOP,
        SignalState.UNKNOWN,
        SignalState.ARROW_STOP,
    }


def test_unknown_sizes_of_nocturne_objects_get_typical_ones(womd_dir: Path) -> None:
    path = womd_dir / "nocturne" / "tfrecord-00358-of-01000_65.json"
    with pytest.warns(UserWarning, match=r"12 object\(s\) with length and width 0"):
        s = read_gpudrive_json(path)
    raw = json.loads(path.read_text())["objects"]
    k = next(i for i, o in enumerate(raw) if o["length"] == 0 and o["type"] == "pedestrian")
    assert tuple(s.tracks.size[k][s.tracks.valid[k]][0]) == pytest.approx(
        (*TYPICAL_BOX_SIZE_M[ObjectType.PEDESTRIAN], DEFAULT_BOX_HEIGHT_M)
    )


# ----------------------------------------------------------------------------- small documents


def _tiny_nocturne(n_steps: int = 20) -> dict:
    """A Nocturne-dialect scene: no ids, degrees, struct-of-arrays positions, one signal."""
    t = np.arange(n_steps, dtype=float)

    def obj(k: int, kind: str, heading_deg: float) -> dict:
        vx, vy = 5 * np.cos(np.radians(heading_deg)), 5 * np.sin(np.radians(heading_deg))
        return {
            "position": {"x": (10 * k + vx * t * 0.1).tolist(), "y": (vy * t * 0.1).tolist()},
            "velocity": {"x": [vx] * n_steps, "y": [vy] * n_steps},
            "heading": [heading_deg + 360.0] * n_steps,
            "valid": [True] * n_steps,
            "length": 4.5,
            "width": 2.0,
            "goalPosition": {"x": 0.0, "y": 0.0},
            "type": kind,
        }

    lane = [{"x": float(x), "y": 0.0} for x in range(0, 60, 10)]
    return {
        "name": "tiny.json",
        "objects": [obj(0, "vehicle", 90.0), obj(1, "vehicle", 0.0), obj(2, "pedestrian", 45.0)],
        "roads": [
            {"type": "road_edge", "geometry": [{"x": p["x"], "y": 5.0} for p in lane]},
            {"type": "lane", "geometry": lane},
            {"type": "stop_sign", "geometry": [{"x": 50.0, "y": 0.0}]},
        ],
        "tl_states": {
            "374": {
                "state": ["stop"] * (n_steps - 1) + ["arrow_go"],
                "x": [0.0] * n_steps,
                "y": [0.0] * n_steps,
                "time_index": list(range(n_steps)),
            }
        },
    }


def test_tiny_nocturne_document() -> None:
    s = scenario_from_gpudrive(_tiny_nocturne(), source="some/dir/tiny-scene.json")
    t = s.tracks
    assert s.scenario_id == "tiny-scene" and t.id.tolist() == [1, 2, 3]
    assert t.heading[0, 0] == pytest.approx(np.pi / 2) and t.raw_heading[0, 0] == pytest.approx(
        np.radians(450.0)
    )
    assert (t.size[:, 0, 2] == DEFAULT_BOX_HEIGHT_M).all() and (t.xyz[..., 2] == 0).all()
    assert s.road_map.id.tolist() == [1, 2, 3] and s.road_map.subtype.tolist() == [0, 0, 0]
    assert s.signals.lane_id.tolist() == [2]  # the lane starting at the stop point
    assert s.signals.state[0, -1] == SignalState.ARROW_GO
    assert s.sdc_index in (0, 1) and len(s.objects_of_interest) == 0
    doc = _tiny_nocturne()
    for entry in doc["tl_states"].values():
        del entry["time_index"]  # lists covering every step need no time_index
    assert scenario_from_gpudrive(doc).signals.valid.all()


def _set(keys: list, value):
    def mutate(doc: dict) -> None:
        for k in keys[:-1]:
            doc = doc[k]
        doc[keys[-1]] = value

    return mutate


def _del(keys: list):
    def mutate(doc: dict) -> None:
        for k in keys[:-1]:
            doc = doc[k]
        del doc[keys[-1]]

    return mutate


TL = ["tl_states", "374"]


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (_set(["objects", 1, "id"], 5), r"objects\[0\]: missing key 'id'"),
        (_set(["objects", 0, "position", "x"], [0.0] * 19), r"objects\[0\]\.position: the lists"),
        (_del(["objects", 2, "position", "y"]), r"objects\[2\]\.position: missing key 'y'"),
        (_set(["objects", 1, "position", "y", 4], "north"), r"objects\[1\]\.position\.y"),
        (_set(["objects", 0, "height"], "tall"), r"objects\[0\]\.height"),
        (_set(["objects", 0, "length"], -1.0), "not positive"),
        (_set(["objects", 0, "heading", 2], float("nan")), "non-finite"),
        (_set(["roads", 0, "id"], 7), r"roads\[1\]: missing key 'id'"),
        (_set([*TL, "state", 3], "purple"), r"tl_states\['374'\]\.state\[3\]: unknown"),
        (_set([*TL, "time_index", 3], 99), r"tl_states\['374'\]\.time_index: a step outside"),
        (_set([*TL, "time_index", 3], 2.5), r"tl_states\['374'\]\.time_index\[3\]: expected"),
        (_del([*TL, "x"]), r"tl_states\['374'\]: missing key 'x'"),
        (_set([*TL, "x"], [0.0] * 3), r"tl_states\['374'\]: the lists"),
        (_set(["tl_states"], [1]), "'tl_states' must be an object"),
        (_set(["metadata"], {"sdc_track_index": 9}), "'sdc_track_index' 9 outside"),
    ],
)
def test_malformed_dialect_names_file_and_field(tmp_path: Path, mutate, message: str) -> None:
    doc = _tiny_nocturne()
    mutate(doc)
    path = tmp_path / "scene.json"
    path.write_text(json.dumps(doc))
    with pytest.raises(ScenarioFormatError, match=message) as info:
        read_gpudrive_json(path)
    assert info.value.path == str(path)


def test_signal_key_must_be_a_lane_id_when_roads_have_ids() -> None:
    doc = _tiny_nocturne()
    for k, road in enumerate(doc["roads"]):
        road["id"] = 10 + k
    doc["tl_states"]["lane-a"] = copy.deepcopy(doc["tl_states"]["374"])
    with pytest.raises(ScenarioFormatError, match="key 'lane-a' is not a lane id"):
        scenario_from_gpudrive(doc)
    del doc["tl_states"]["lane-a"]
    assert scenario_from_gpudrive(doc).signals.lane_id.tolist() == [374]


def test_signal_without_a_lane_at_its_stop_point_is_dropped() -> None:
    doc = _tiny_nocturne()
    doc["tl_states"]["374"]["x"] = [500.0] * 20
    with pytest.warns(UserWarning, match=r"dropped 1 signal\(s\)"):
        assert scenario_from_gpudrive(doc).signals.num_signals == 0


def test_seeded_fuzz_gives_a_scenario_or_a_format_error() -> None:
    rng = np.random.default_rng(25)
    doc = _tiny_nocturne()
    results = [
        outcome(lambda: scenario_from_gpudrive(mutate_document(doc, rng), source="f"))
        for _ in range(60)
    ]
    assert "error" in results and "ok" in results
