"""tbsim: multi-agent traffic simulation on real Waymo scenarios.

``TrafficEnv``, ``load_scenarios`` and ``Scenario`` are loaded on first use, so importing a
submodule (e.g. ``tbsim_env.sim.dynamics`` from a policy) stays light and free of cycles.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_LAZY = {
    "TrafficEnv": "tbsim_env.env",
    "load_scenarios": "tbsim_env.data.loader",
    "Scenario": "tbsim_env.data.scenario",
}
__all__ = sorted(_LAZY)


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'tbsim_env' has no attribute {name!r}")
