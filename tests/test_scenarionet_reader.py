"""ScenarioNet / MetaDrive pickle reader: every shared pickle against the READMEs, the restricted
unpickler (a pickle naming ``os.system`` runs nothing), malformed input, fuzz."""

from __future__ import annotations

import copy
import os
import pickle
import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from tbsim_env.core.constants import CURRENT_INDEX, DT, MapFeatureType, ObjectType, SignalState
from tbsim_env.core.errors import ScenarioFormatError
from tbsim_env.data.cache import TokenCache, build_cache
from tbsim_env.data.scenarionet import (
    ALLOWED_GLOBALS,
    MAP_TYPES,
    load_restricted_pickle,
    map_type,
    read_scenarionet_pickle,
    scenario_from_scenarionet,
)
from tests.real_format_support import (
    check_raw_heading,
    heading_error,
    mutate_bytes,
    mutate_document,
    outcome,
)

ROW = re.compile(
    r"^\| `(?P<file>[^`]+\.pkl)` \| (?P<sid>\w+) \| (?P<tracks>\d+) \((?P<types>[^)]*)\) \| "
    r"(?P<steps>\d+) \| (?P<map>\d+) \| (?P<lights>\d+) \|"
)
# The one file of scenarionet/ (data/womd/README.md section 4): tracks, steps, map, signals.
MAIN_FILE = ("scenarionet/sd_waymo_v1.2_eb4b91b10ca94ff2.pkl", "eb4b91b10ca94ff2", 45, 199, 209, 14)


def _expected(womd_dir: Path) -> dict[str, tuple]:
    """file (relative to womd_dir) -> (id, tracks, {type: count}, steps, map features, signals)."""
    out = {MAIN_FILE[0]: (MAIN_FILE[1], MAIN_FILE[2], {"VEHICLE": 45}, *MAIN_FILE[3:])}
    for line in (womd_dir / "scenarionet_more" / "README.md").read_text().splitlines():
        m = ROW.match(line)
        if m:
            types = {t.split()[1]: int(t.split()[0]) for t in m["types"].split(", ")}
            out["scenarionet_more/" + m["file"]] = (
                m["sid"],
                int(m["tracks"]),
                types,
                int(m["steps"]),
                int(m["map"]),
                int(m["lights"]),
            )
    return out


@pytest.fixture(scope="module")
def real(womd_dir: Path) -> dict[str, tuple]:
    """file -> (expected README row, Scenario) for every shared pickle (read without warnings)."""
    expected = _expected(womd_dir)
    files = sorted(str(p.relative_to(womd_dir)) for p in womd_dir.glob("scenarionet*/**/*.pkl"))
    assert files == sorted(expected) and len(files) == 43
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        return {f: (expected[f], read_scenarionet_pickle(womd_dir / f)) for f in files}


def test_every_pickle_matches_the_readme(real: dict) -> None:
    kinds = np.zeros(len(MapFeatureType), int)
    for name, ((sid, n_tracks, types, steps, n_map, n_lights), s) in real.items():
        assert s.scenario_id == sid and s.source.endswith(name)
        assert s.tracks.num_tracks == n_tracks and s.num_steps == steps
        counts = np.bincount(s.tracks.object_type, minlength=len(ObjectType))
        assert {t: int(counts[ObjectType[t]]) for t in types} == types
        assert s.road_map.num_features == n_map and s.signals.num_signals == n_lights
        assert s.current_index == CURRENT_INDEX  # 10 as stored, or for 0 / missing (docstring)
        assert s.timestamps[0] == 0.0 and abs(s.timestamps[-1] - DT * (steps - 1)) < 0.1
        assert heading_error(s) < 0.1, name
        check_raw_heading(s)
        assert s.tracks.valid[s.tracks_to_predict, s.current_index].all()
        kinds += np.bincount(s.road_map.feature_type, minlength=len(MapFeatureType))
    assert (kinds > 0).all(), kinds  # every map kind occurs (lanes ... driveways)


def test_main_file_marks_and_unwrapped_headings(real: dict) -> None:
    _, s = real[MAIN_FILE[0]]
    t = s.tracks
    assert s.sdc_index == 44 and s.sdc_id == 51 and s.objects_of_interest.tolist() == [11, 17]
    assert t.id[:3].tolist() == [0, 1, 2] and t.id[44] == 51  # string keys "0" ... "51"
    assert t.valid.sum() == 4618  # data README: 742 of 4,618 valid headings outside [-pi, pi)
    raw = t.raw_heading[t.valid]
    assert ((raw < -np.pi) | (raw >= np.pi)).sum() == 742
    assert abs(s.timestamps[-1] - 19.799452) < 1e-5
    # The 20 s file marks no tracks to predict: chosen over the WOSAC horizon (steps 10-90).
    ttp = s.tracks_to_predict
    assert 0 < len(ttp) <= 8 and s.sdc_index not in ttp and (s.predict_difficulty == 0).all()
    assert t.valid[ttp, CURRENT_INDEX : CURRENT_INDEX + 81].all()
    lanes = s.road_map.indices_of(MapFeatureType.LANE)
    assert any(len(s.road_map.exit_lanes[i]) for i in lanes)  # connectivity kept
    assert s.road_map.speed_limit_mph[lanes].max() > 0


def test_twenty_second_scenes_enter_a_token_cache_in_the_motion_window(
    real: dict, womd_dir: Path, tmp_path: Path
) -> None:
    _, s = real[MAIN_FILE[0]]
    window = s.motion_window()
    assert window.num_steps == CURRENT_INDEX + 81 and s.num_steps == 199
    np.testing.assert_array_equal(window.tracks.xyz, s.tracks.xyz[:, : CURRENT_INDEX + 81])
    assert window.has_future and window.motion_window() is window
    manifest = build_cache([str(womd_dir / MAIN_FILE[0])], tmp_path, workers=1, progress=False)
    assert manifest["scenario_ids"] == [MAIN_FILE[1]] and not manifest["skipped"]
    (tokens,) = TokenCache(tmp_path)
    assert tokens.agent_valid.shape[-1] == CURRENT_INDEX + 81


def test_metadata_marks_are_kept(real: dict) -> None:
    _, s = real["scenarionet_more/scenestreamer/sd_waymo_v1.2_7b27ec36087b2fc1.pkl"]
    assert s.sdc_index == 131 and s.sdc_id == 4992
    assert s.tracks_to_predict.tolist() == [3, 131] and s.predict_difficulty.tolist() == [1, 1]
    assert s.objects_of_interest.tolist() == [4992, 1648]


def test_both_signal_layouts(real: dict) -> None:
    _, new = real[MAIN_FILE[0]]  # names per step, None where unknown
    assert new.signals.valid[new.signals.lane_id == 184].all()
    states = new.signals.state[new.signals.lane_id == 184][0]
    assert states[0] == SignalState.STOP and states[-1] == SignalState.GO
    unknown = new.signals.valid[new.signals.lane_id == 191][0]  # None at the first steps
    assert not unknown[0] and 0 < unknown.sum() < new.num_steps
    _, old = real["scenarionet_more/metadrive/0_at_f3b1e7b105.pkl"]  # per-step lane, 0 = none
    sig = old.signals
    assert 0 not in sig.lane_id.tolist() and sig.num_signals == 19
    row = sig.lane_id.tolist().index(269)
    assert sig.valid[row].sum() == old.num_steps - 53  # 53 placeholder steps of lane 269
    assert set(sig.state[row][sig.valid[row]].tolist()) <= {0, 4, 6}
    assert np.abs(sig.stop_point[row]).max() > 100  # a real stop point, not the placeholder


def test_map_type_names() -> None:
    assert MAP_TYPES["LANE_SURFACE_STREET"] == (MapFeatureType.LANE, 2)
    assert MAP_TYPES["ROAD_LINE_SOLID_DOUBLE_YELLOW"] == (MapFeatureType.ROAD_LINE, 7)
    assert MAP_TYPES["ROAD_EDGE_MEDIAN"] == (MapFeatureType.ROAD_EDGE, 2)
    assert MAP_TYPES["CROSS_WALK"] == MAP_TYPES["CROSSWALK"] == (MapFeatureType.CROSSWALK, 0)
    assert map_type("UNKNOWN", {"entry_lanes": [], "polyline": None}) == (MapFeatureType.LANE, 0)
    assert map_type("UNKNOWN", {"polyline": None}) is None
    assert map_type("SPACESHIP", {}) is None and map_type(3, {}) is None


# ----------------------------------------------------------------------------- restricted pickle


class _RunsCode:
    """Pickles as a call of ``os.system``: what a hostile file would hold."""

    def __init__(self, command: str) -> None:
        self.command = command

    def __reduce__(self):
        return (os.system, (self.command,))


def test_a_pickle_naming_os_system_is_refused_and_runs_nothing(tmp_path: Path) -> None:
    marker = tmp_path / "ran"
    path = tmp_path / "evil.pkl"
    path.write_bytes(pickle.dumps({"tracks": _RunsCode(f"touch {marker}")}))
    with pytest.raises(ScenarioFormatError, match=r"(os|posix)\.system.*refused") as info:
        read_scenarionet_pickle(path)
    assert info.value.path == str(path)
    assert not marker.exists()


@pytest.mark.parametrize(
    "payload",
    [
        pickle.dumps(eval),  # noqa: S307 - the function object, not a call
        pickle.dumps(getattr),
        pickle.dumps(np.load),
        pickle.dumps(copy.deepcopy),
        b"\x80\x04cbuiltins\nexec\n(V1\ntR.",
    ],
)
def test_other_globals_are_refused(payload: bytes) -> None:
    with pytest.raises(ScenarioFormatError, match="refused"):
        load_restricted_pickle(payload, source="mem")


def test_allowed_globals_build_plain_data_only() -> None:
    assert {m for m, _ in ALLOWED_GLOBALS} <= {
        "numpy",
        "numpy.core.multiarray",
        "numpy._core.multiarray",
        "collections",
        "builtins",
        "_codecs",
        "metadrive.scenario.scenario_description",
    }
    assert {n for m, n in ALLOWED_GLOBALS if m == "builtins"}.isdisjoint(
        {"eval", "exec", "getattr", "open", "__import__", "compile", "setattr"}
    )


def test_numpy_spellings_and_protocol_2(tmp_path: Path) -> None:
    doc = _tiny_scene()
    new = pickle.dumps(doc, protocol=4)
    assert b"numpy._core.multiarray" in new or b"numpy.core.multiarray" in new
    old = pickle.dumps(doc, protocol=2).replace(b"numpy._core.multiarray", b"numpy.core.multiarray")
    assert b"_codecs" in old and b"numpy.core.multiarray" in old
    for data in (new, old):
        s = scenario_from_scenarionet(load_restricted_pickle(data), source="mem")
        assert s.tracks.valid.all() and s.tracks.id.tolist() == [7, 8, 9]
        np.testing.assert_array_equal(s.tracks.xyz[0], doc["tracks"]["7"]["state"]["position"])
    bad = pickle.dumps(b"abc", protocol=2).replace(b"latin1", b"rot13!")
    with pytest.raises(ScenarioFormatError, match="not a readable pickle"):
        load_restricted_pickle(bad)


# ----------------------------------------------------------------------------- malformed input


def _tiny_scene(n_steps: int = 20) -> dict:
    """A three-track ScenarioNet scene (new signal layout), built like the real files."""
    t = np.arange(n_steps, dtype=np.float32)

    def track(k: int, kind: str) -> dict:
        pos = np.stack([t * 5.0 + 10 * k, np.full_like(t, 3.0 * k), np.zeros_like(t)], 1)
        return {
            "type": kind,
            "state": {
                "position": pos,
                "heading": np.full(n_steps, 0.0, np.float32),
                "velocity": np.stack([np.full_like(t, 50.0), np.zeros_like(t)], 1),
                "valid": np.ones(n_steps, bool),
                "length": np.full(n_steps, 4.5, np.float32),
                "width": np.full(n_steps, 2.0, np.float32),
                "height": np.full(n_steps, 1.5, np.float32),
            },
            "metadata": {"object_id": str(k + 7), "type": kind},
        }

    lane = np.stack([np.linspace(0, 100, 11), np.zeros(11), np.zeros(11)], 1).astype(np.float32)
    return {
        "id": "tiny",
        "version": "v1.2",
        "length": n_steps,
        "tracks": {
            str(k + 7): track(k, kind) for k, kind in enumerate(["VEHICLE"] * 2 + ["CYCLIST"])
        },
        "map_features": {
            "1": {
                "type": "LANE_SURFACE_STREET",
                "polyline": lane,
                "entry_lanes": [],
                "exit_lanes": [2],
                "left_neighbor": [],
                "right_neighbor": [{"feature_id": "3"}],
                "speed_limit_mph": 25.0,
            },
            "2": {"type": "ROAD_EDGE_BOUNDARY", "polyline": lane + [0, 5, 0]},
            "4": {"type": "STOP_SIGN", "lane": [1], "position": np.array([100.0, 0, 0])},
            "5": {"type": "CROSSWALK", "polygon": lane[:4] + [0, -3, 0]},
        },
        "dynamic_map_states": {
            "1": {
                "type": "TRAFFIC_LIGHT",
                "lane": 1,
                "stop_point": np.array([100.0, 0.0, 0.0]),
                "state": {
                    "object_state": ["LANE_STATE_GO"] * (n_steps - 2) + [None, "LANE_STATE_STOP"]
                },
            },
        },
        "metadata": {
            "id": "tiny",
            "ts": t * 0.1,
            "sdc_id": "9",
            "current_time_index": 10,
            "tracks_to_predict": {"8": {"track_index": 1, "track_id": "8", "difficulty": 2}},
            "objects_of_interest": ["7", "8"],
        },
    }


def test_tiny_scene_reads() -> None:
    s = scenario_from_scenarionet(_tiny_scene(), source="mem")
    assert s.sdc_index == 2 and s.tracks_to_predict.tolist() == [1]
    assert s.predict_difficulty.tolist() == [2] and s.objects_of_interest.tolist() == [7, 8]
    assert s.road_map.feature_type.tolist() == [0, 2, 3, 4]
    assert s.road_map.exit_lanes[0].tolist() == [2] and s.road_map.right_neighbors[0].tolist() == [
        3
    ]
    assert s.road_map.controlled_lanes[2].tolist() == [1] and s.road_map.speed_limit_mph[0] == 25
    assert s.signals.valid.tolist() == [[True] * 18 + [False, True]]
    assert s.signals.state[0, -1] == SignalState.STOP and s.signals.state[0, 0] == SignalState.GO


def _at(doc: dict, keys: list):
    for k in keys[:-1]:
        doc = doc[k]
    return doc, keys[-1]


def _set(keys: list, value):
    def mutate(doc: dict) -> None:
        parent, key = _at(doc, keys)
        parent[key] = value

    return mutate


def _del(keys: list):
    def mutate(doc: dict) -> None:
        parent, key = _at(doc, keys)
        del parent[key]

    return mutate


T8 = ["tracks", "8", "state"]


@pytest.mark.parametrize(
    ("mutate", "message"),
    [
        (_del(["tracks"]), "top level: missing key 'tracks'"),
        (_del(["map_features"]), "missing key 'map_features'"),
        (_set(["tracks"], {}), "'tracks' must be a non-empty dict"),
        (_del([*T8, "position"]), r"tracks\['8'\]\.state: missing key 'position'"),
        (_del([*T8, "height"]), r"tracks\['8'\]\.state: missing key 'height'"),
        (_set([*T8, "position"], np.zeros((20, 4))), r"tracks\['8'\]\.state\.position: has shape"),
        (_set([*T8, "heading"], np.zeros(19)), r"tracks\['8'\]\.state\.heading: has shape"),
        (_set([*T8, "valid"], "yes"), r"tracks\['8'\]\.state\.valid: expected 20 booleans"),
        (_set([*T8, "velocity"], [["a", "b"]] * 20), r"state\.velocity: values are not numbers"),
        (_set(["tracks", "8", "type"], "SPACESHIP"), r"tracks\['8'\]\.type: unknown object type"),
        (
            _set(
                [
                    "tracks",
                    "x8",
                ],
                _tiny_scene()["tracks"]["8"],
            ),
            r"tracks\['x8'\] \(key\): expected an integer id",
        ),
        (_set([*T8, "position", 3, 0], np.nan), "non-finite"),
        (_set(["length"], 91), "'length' 91 but the tracks hold 20 steps"),
        (_set(["metadata", "ts", 5], -1.0), r"metadata\.ts: is not increasing at step 5"),
        (_set(["metadata", "sdc_id"], "99"), r"metadata\.sdc_id: no track has id 99"),
        (_set(["metadata", "sdc_track_index"], 0), "is not the track of sdc_id"),
        (_set(["metadata", "current_time_index"], "ten"), r"metadata\.current_time_index"),
        (_set(["metadata", "current_time_index"], 25), "'current_time_index' 25"),
        (_set(["metadata", "tracks_to_predict", "8", "track_id"], "77"), "no track has id 77"),
        (_set(["metadata", "objects_of_interest"], [1.5]), r"objects_of_interest\[0\]"),
        (
            _set(["map_features", "2", "polyline"], np.zeros((5, 4))),
            r"map_features\['2'\]\.polyline",
        ),
        (_set(["map_features", "1", "exit_lanes"], "2"), r"map_features\['1'\]\.exit_lanes"),
        (_set(["map_features", "4", "position"], np.zeros(5)), r"map_features\['4'\]\.position"),
        (
            _set(["dynamic_map_states", "1", "state", "object_state", 3], "PURPLE"),
            r"object_state\[3\]: unknown",
        ),
        (_set(["dynamic_map_states", "1", "state", "object_state"], []), "expected 20 states"),
        (_del(["dynamic_map_states", "1", "stop_point"]), "missing key 'stop_point'"),
    ],
)
def test_malformed_scene_names_file_and_field(tmp_path: Path, mutate, message: str) -> None:
    doc = _tiny_scene()
    mutate(doc)
    path = tmp_path / "scene.pkl"
    path.write_bytes(pickle.dumps(doc))
    with pytest.raises(ScenarioFormatError, match=message) as info:
        read_scenarionet_pickle(path)
    assert info.value.path == str(path)


def test_truncated_and_foreign_files(tmp_path: Path) -> None:
    path = tmp_path / "scene.pkl"
    data = pickle.dumps(_tiny_scene())
    for cut in (1, 2, 100, len(data) // 2, len(data) - 1):
        path.write_bytes(data[:cut])
        with pytest.raises(ScenarioFormatError, match="not a readable pickle") as info:
            read_scenarionet_pickle(path)
        assert info.value.path == str(path)
    path.write_bytes(pickle.dumps([1, 2, 3]))
    with pytest.raises(ScenarioFormatError, match="expected a ScenarioDescription dict"):
        read_scenarionet_pickle(path)
    with pytest.raises(FileNotFoundError):
        read_scenarionet_pickle(tmp_path / "none.pkl")


def test_seeded_fuzz_gives_a_scenario_or_a_format_error() -> None:
    rng = np.random.default_rng(25)
    doc = _tiny_scene()
    data = pickle.dumps(doc)
    results = [
        outcome(
            lambda: scenario_from_scenarionet(
                load_restricted_pickle(mutate_bytes(data, rng)), source="fuzz"
            )
        )
        for _ in range(30)
    ]
    results += [
        outcome(lambda: scenario_from_scenarionet(mutate_document(doc, rng), source="fuzz"))
        for _ in range(40)
    ]
    assert "error" in results and "ok" in results
