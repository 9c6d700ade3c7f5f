"""Helpers of the reader tests for the converted real-scene formats: fuzzing and sanity checks."""

from __future__ import annotations

import copy
import warnings
from collections.abc import Callable
from typing import Any

import numpy as np

from tbsim_env.core.constants import ObjectType
from tbsim_env.core.errors import ScenarioFormatError
from tbsim_env.data.scenario import Scenario
from tests.test_bad_input import time_guard

FUZZ_CASE_LIMIT_S = 5.0
JUNK_VALUES: tuple[Any, ...] = (
    None,
    "x",
    -1,
    True,
    1e309,
    float("nan"),
    [],
    {},
    [1.0, "a"],
    {"x": 1},
    np.array([np.nan, 1.0]),
    np.zeros((2, 2, 2)),
)
"""Replacement values of the structure fuzzers (wrong types, shapes, non-finite numbers)."""


def outcome(call: Callable[[], Scenario]) -> str:
    """Run one fuzz case: 'ok' (a valid Scenario) or 'error' (ScenarioFormatError).

    Any other exception, a non-Scenario result, an invalid Scenario or a case over
    ``FUZZ_CASE_LIMIT_S`` fails the test.
    """
    with warnings.catch_warnings(), time_guard(FUZZ_CASE_LIMIT_S):
        warnings.simplefilter("ignore")
        try:
            result = call()
        except ScenarioFormatError:
            return "error"
    assert isinstance(result, Scenario), type(result)
    result.validate()
    return "ok"


def mutate_bytes(data: bytes, rng: np.random.Generator) -> bytes:
    """A truncation, a few flipped bytes, or an inserted / deleted run."""
    arr = bytearray(data)
    kind = rng.integers(4)
    if kind == 0:
        return bytes(arr[: int(rng.integers(0, len(arr)))])
    if kind == 1:
        for pos in rng.integers(0, len(arr), size=int(rng.integers(1, 6))):
            arr[pos] = int(rng.integers(256))
        return bytes(arr)
    pos = int(rng.integers(0, len(arr)))
    if kind == 2:
        return bytes(arr[:pos] + bytes(rng.integers(0, 256, 8).astype(np.uint8)) + arr[pos:])
    return bytes(arr[:pos] + arr[pos + int(rng.integers(1, 16)) :])


def _paths(obj: Any, prefix: tuple = ()) -> list[tuple]:
    """Every key / index path of a nested dict / list document (arrays are leaves)."""
    out = []
    items = (
        obj.items() if isinstance(obj, dict) else enumerate(obj) if isinstance(obj, list) else ()
    )
    for key, value in items:
        out.append((*prefix, key))
        if isinstance(value, (dict, list)) and len(out) < 5000:
            out.extend(_paths(value, (*prefix, key)))
    return out


def mutate_document(doc: Any, rng: np.random.Generator) -> Any:
    """A deep copy of ``doc`` with one nested entry deleted or replaced by a junk value."""
    out = copy.deepcopy(doc)
    paths = _paths(out)
    path = paths[int(rng.integers(len(paths)))]
    parent = out
    for key in path[:-1]:
        parent = parent[key]
    if rng.random() < 0.3 and isinstance(parent, dict):
        del parent[path[-1]]
    else:
        parent[path[-1]] = copy.deepcopy(JUNK_VALUES[int(rng.integers(len(JUNK_VALUES)))])
    return out


def heading_error(s: Scenario, min_speed: float = 3.0) -> float:
    """Median |heading - direction of velocity| (rad) of vehicles moving faster than
    ``min_speed`` m/s at valid steps: ~0.01 with the right angle unit, ~1 with the wrong one."""
    t = s.tracks
    speed = np.linalg.norm(t.velocity, axis=-1)
    moving = t.valid & (speed > min_speed) & (t.object_type == ObjectType.VEHICLE)[:, None]
    if not moving.any():
        return 0.0
    direction = np.arctan2(t.velocity[..., 1], t.velocity[..., 0])[moving]
    diff = np.angle(np.exp(1j * (t.heading[moving] - direction)))
    return float(np.median(np.abs(diff)))


def check_raw_heading(s: Scenario) -> None:
    """``raw_heading`` wraps to ``heading`` at valid steps (both float32)."""
    t = s.tracks
    assert t.raw_heading is not None
    wrapped = np.angle(np.exp(1j * t.raw_heading.astype(np.float64)))
    diff = np.angle(np.exp(1j * (wrapped - t.heading)))[t.valid]
    assert np.abs(diff).max(initial=0.0) < 1e-5
