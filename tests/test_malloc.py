"""An environment on the CPU keeps the memory a step frees (``tbsim_env.core.malloc``)."""

from __future__ import annotations

import os
import platform
import subprocess
import sys

import pytest

pytestmark = pytest.mark.skipif(
    platform.system() != "Linux" or platform.libc_ver()[0] != "glibc",
    reason="the malloc thresholds are glibc's",
)

# Builds an env, then frees 200 MB of 20 MB tensors (below the fixed mmap threshold, above
# glibc's default one) and prints how much of it the process still holds.
_SCRIPT = """
import torch
from tbsim_env.env import BatchedTrafficEnv
from tbsim_env.core.malloc import keep_freed_memory

BatchedTrafficEnv(None, 2, npc_policy="constant_velocity")
def rss():
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096
base = rss()
blocks = [torch.ones(5 << 20) for _ in range(10)]
held = rss()
del blocks
print(keep_freed_memory(), (held - base) >> 20, (rss() - base) >> 20)
"""


def _run(keep: str) -> tuple[bool, int, int]:
    env = {**os.environ, "TBSIM_KEEP_FREED_MEMORY": keep}
    out = subprocess.run(
        [sys.executable, "-c", _SCRIPT], env=env, capture_output=True, text=True, check=True
    )
    kept, held, after = out.stdout.split()
    return kept == "True", int(held), int(after)


def test_a_cpu_env_keeps_freed_memory_in_the_process():
    kept, held, after = _run("1")
    assert kept and held >= 100  # (the heap's free memory served part of the 200 MB)
    assert after >= held - 10  # freed, still resident: a next step reuses it without faults


def test_the_environment_variable_turns_it_off():
    kept, held, after = _run("0")
    assert not kept and held >= 100
    assert after < held - 90  # glibc's default: returned to the operating system
