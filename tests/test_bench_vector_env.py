"""``bench/vector_env.py`` runs end to end on the embedded generated scenes with a tiny budget
and prints its machine line and one row per policy, timed in interleaved rounds, with the ratio
to the first policy (the figure the README and the issues quote)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("actions", ["zero", "random"])
def test_vector_env_bench_prints_a_row_per_policy_with_its_ratio_to_the_first(actions):
    cmd = [
        sys.executable,
        str(REPO / "bench" / "vector_env.py"),
        "--scenarios", "generated",
        "--npc-policy", "log_replay", "constant_velocity",
        "--batch-sizes", "2",
        "--steps", "3",
        "--rounds", "2",
        "--obs-layout", "indexed",
        "--actions", actions,
    ]  # fmt: skip
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env, cwd=REPO)
    assert proc.returncode == 0, proc.stderr[-3000:]
    lines = proc.stdout.splitlines()
    assert lines[0].startswith("machine: ") and "tiny op" in lines[0]
    assert f"actions {actions}" in lines[1]
    rows = [
        line.split()
        for line in lines
        if line.split()[:1] in (["log_replay"], ["constant_velocity"])
    ]
    assert [r[0] for r in rows] == ["log_replay", "constant_velocity"]
    for r in rows:
        assert r[1] == "indexed" and r[2] == "2"
        assert float(r[3].replace(",", "")) > 0  # agent steps/s
    assert rows[0][-1] == "1.00" and float(rows[1][-1]) > 0  # x 1st policy
