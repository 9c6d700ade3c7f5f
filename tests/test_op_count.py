"""The ATen operations of one eager ``TrafficEnv`` step stay within their budget.

A batch-of-one step is hundreds of tiny tensor operations, so its time is about its operation
count times the cost of one tiny operation; the count (torch profiler, nested operations
included) is the same on every machine. The bound is the count reached (issue 43: the SDC
controlled, log-replayed NPCs, the real one-scenario sample) plus about 5%: a change that
adds operations to the step fails here and must say why. ``bench/env_step.py`` prints the
count; the target is at most 400.
"""

from __future__ import annotations

import numpy as np
import pytest

from tbsim_env.core.torch_utils import aten_op_count
from tbsim_env.data import load_scenarios
from tbsim_env.env import TrafficEnv

MAX_STEP_OPS = 775
"""ATen operations per step allowed (the count reached, rounded up by about 5%)."""


@pytest.mark.usefixtures("torch_one_thread")
def test_traffic_env_step_op_count(one_scenario_path) -> None:
    scenarios = load_scenarios(str(one_scenario_path))
    env = TrafficEnv(scenarios[0], npc_policy="log_replay")
    env.reset(seed=0)
    zero = {a: np.zeros(2, np.float32) for a in env.agents}
    for _ in range(3):  # warm the caches (constants, index tensors)
        env.step(zero)
    ops = aten_op_count(lambda: env.step(zero), 10)
    assert ops <= MAX_STEP_OPS, f"{ops:.0f} ATen operations per step > {MAX_STEP_OPS}"
