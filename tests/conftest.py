"""Shared fixtures. Real WOMD data is read from ``$TBSIM_WOMD_DIR`` (default ../shared/data/womd).

Without the data those tests skip with a reason; under CI (``CI=true``) a missing folder fails.
"""

from __future__ import annotations

import os
import warnings
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def womd_root() -> Path:
    return Path(os.environ.get("TBSIM_WOMD_DIR", REPO.parent / "shared" / "data" / "womd"))


@pytest.fixture(scope="session")
def womd_dir() -> Path:
    root = womd_root()
    if not (root / "waymo-open-dataset").is_dir():
        msg = (
            f"real WOMD sample data not found at {root} "
            "(set TBSIM_WOMD_DIR to the folder holding waymo-open-dataset/ and gpudrive/)"
        )
        if os.environ.get("CI", "").lower() == "true":
            pytest.fail(msg + "; under CI the data folder is required")
        pytest.skip(msg)
    return root


@pytest.fixture(scope="session")
def one_scenario_path(womd_dir: Path) -> Path:
    return womd_dir / "waymo-open-dataset" / "motion_data_one_scenario.tfrecord"


@pytest.fixture(scope="session")
def scenario_input_path(womd_dir: Path) -> Path:
    return womd_dir / "waymo-open-dataset" / "womd_scenario_input.tfrecord"


@pytest.fixture(scope="session")
def tf_example_path(womd_dir: Path) -> Path:
    return womd_dir / "waymo-open-dataset" / "motion_data_one_example.tfrecord"


@pytest.fixture(scope="module")
def torch_one_thread():
    """Run a module with one torch intra-op thread (tiny tensors; docs/performance.md)."""
    import torch

    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


def check_parallel_api(env, num_cycles: int) -> None:
    """PettingZoo's ``parallel_api_test`` on ``env``.

    An env over several scenarios has the union of their agents as ``possible_agents``, so when
    an episode ends, the agents of the scenarios it did not play have not terminated, and the
    API test warns "No agents present but not all possible_agents are terminated or truncated".
    That one warning is ignored for such envs only; a single-scenario env still shows it.
    """
    from pettingzoo.test import parallel_api_test

    with warnings.catch_warnings():
        if len(getattr(env, "scenarios", ())) > 1:
            warnings.filterwarnings("ignore", "No agents present but not all possible_agents")
        parallel_api_test(env, num_cycles=num_cycles)
