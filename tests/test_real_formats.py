"""Every real-scene format through one loader: detection by content, a folder of mixed formats in
one call, ``tbsim info``, and a few scenes of each new format stepped in ``TrafficEnv``."""

from __future__ import annotations

import pickle
import shutil
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

from tbsim_env import TrafficEnv
from tbsim_env.core.errors import ScenarioFormatError
from tbsim_env.data.loader import ScenarioFileFormat, detect_format, load_scenarios

ONE_OF_EACH = {
    "waymo-open-dataset/motion_data_one_scenario.tfrecord": ScenarioFileFormat.TFRECORD,
    "waymo-open-dataset/motion_data_one_example.tfrecord": ScenarioFileFormat.TF_EXAMPLE,
    "scenarionet/sd_waymo_v1.2_eb4b91b10ca94ff2.pkl": ScenarioFileFormat.SCENARIONET_PICKLE,
    "gpudrive/tfrecord-00000-of-01000_222.json": ScenarioFileFormat.GPUDRIVE_JSON,
    "nocturne/tfrecord-00754-of-01000_171.json": ScenarioFileFormat.GPUDRIVE_JSON,
    "gpudrive_history/gpudrive_early/tfrecord-00002-of-00150_9c52d259d258d6a3.json": (
        ScenarioFileFormat.GPUDRIVE_JSON
    ),
}
# A few scenes of each new format: 20 s pickles (both signal layouts), 9 s pickle, tf.Example,
# every JSON dialect.
ENV_SCENES = (
    "scenarionet/sd_waymo_v1.2_eb4b91b10ca94ff2.pkl",
    "scenarionet_more/metadrive/0_at_f3b1e7b105.pkl",
    "scenarionet_more/scenestreamer/sd_waymo_v1.2_7b27ec36087b2fc1.pkl",
    "waymo-open-dataset/motion_data_one_example.tfrecord",
    "nocturne/tfrecord-00754-of-01000_171.json",
    "gpudrive_history/gpudrive_early/tfrecord-00000-of-00150_238786b3cccc4a0e.json",
    "gpudrive_history/nocturne_format/tfrecord-00082-of-01000_465.json",
)


def _load(source) -> list:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return load_scenarios(source)


def test_formats_are_detected_by_content(womd_dir: Path, tmp_path: Path) -> None:
    for name, fmt in ONE_OF_EACH.items():
        assert detect_format(womd_dir / name) is fmt, name
        renamed = tmp_path / f"no_extension_{len(list(tmp_path.iterdir()))}"
        shutil.copy(womd_dir / name, renamed)
        assert detect_format(renamed) is fmt, name  # content, not the name, decides


def test_a_folder_of_mixed_formats_loads_in_one_call(womd_dir: Path, tmp_path: Path) -> None:
    for name in ONE_OF_EACH:
        shutil.copy(womd_dir / name, tmp_path / Path(name).name)
    (tmp_path / "notes.md").write_text("not a scene")  # ignored by the folder listing
    scenes = _load(tmp_path)
    assert sorted(s.scenario_id for s in scenes) == sorted(
        [
            "637f20cafde22ff8",
            "a3bb37c25ce56418",
            "eb4b91b10ca94ff2",
            "1c365f15b70ebdbf",
            "tfrecord-00754-of-01000_171",
            "9c52d259d258d6a3",
        ]
    )


def test_a_refused_pickle_in_a_folder(tmp_path: Path) -> None:
    # exec, not print: an imported Ray replaces builtins.print with its own function.
    (tmp_path / "evil.pkl").write_bytes(pickle.dumps(exec))
    with pytest.raises(ScenarioFormatError, match=r"builtins\.exec.*refused"):
        _load(tmp_path)
    with pytest.warns(UserWarning, match="refused"), pytest.raises(ScenarioFormatError):
        load_scenarios(tmp_path, skip_bad=True)  # nothing loadable left


def test_tbsim_info_reads_the_new_formats(womd_dir: Path) -> None:
    files = [str(womd_dir / n) for n in ONE_OF_EACH if "gpudrive/" not in n]
    out = subprocess.run(
        [sys.executable, "-m", "tbsim_env.cli", "info", *files],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    assert "a3bb37c25ce56418" in out and "eb4b91b10ca94ff2" in out
    assert "tfrecord-00754-of-01000_171" in out and "9c52d259d258d6a3" in out


@pytest.mark.parametrize("name", ENV_SCENES)
def test_new_formats_step_in_the_env(womd_dir: Path, name: str, torch_one_thread) -> None:
    (scenario,) = _load(womd_dir / name)
    env = TrafficEnv(scenario, npc_policy="log_replay")
    obs, _ = env.reset(seed=0)
    assert env.agents and all(np.isfinite(o).all() for a in obs.values() for o in _leaves(a))
    for _ in range(5):
        obs, rewards, *_ = env.step(env.expert_actions())
        assert all(np.isfinite(r) for r in rewards.values())


def _leaves(obs) -> list:
    if isinstance(obs, dict):
        return [x for v in obs.values() for x in _leaves(v)]
    return [np.asarray(obs)]
