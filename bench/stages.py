"""Where an environment step spends its time: exclusive seconds per stage.

``stage_times(totals)`` wraps the functions the episode core and the envs call for each stage
(restored on exit). Times are *exclusive*: a stage's own time without the stages it calls
(the autoreset's history and observations count as autoreset), so the stages and the
remainder ("glue": action checks, packaging, Python) add up to the measured time.

Eager only: a compiled step is one graph, the wrappers see none of it.
"""

from __future__ import annotations

import contextlib
import time
from collections.abc import Iterator

from tbsim_env.env import agent_metrics, episode, vector_env
from tbsim_env.sim import core

STAGES: dict[str, tuple[object, str]] = {
    "npc policy": (episode, "npc_actions"),
    "dynamics": (core, "step"),
    "collision": (agent_metrics, "collided_with_others"),
    "off-road": (agent_metrics, "box_offroad_distance"),
    "metrics": (episode, "step_metrics"),
    "rewards": (episode, "reward_and_termination"),
    "history": (episode, "push_history"),
    "observations": (episode, "observe_indexed"),
    "densify": (episode, "densify_flat"),
    "autoreset": (vector_env.BatchedTrafficEnv, "_restart"),
}
"""Stage name -> (module or class, attribute) of the function that does it."""


@contextlib.contextmanager
def stage_times(totals: dict[str, float]) -> Iterator[dict[str, float]]:
    """Accumulate exclusive seconds per stage into ``totals`` while the block runs."""
    saved = {name: getattr(owner, attr) for name, (owner, attr) in STAGES.items()}
    stack: list[float] = []  # seconds spent in nested stages, per open stage

    def wrap(name, fn):
        def timed(*args, **kwargs):
            stack.append(0.0)
            start = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                elapsed = time.perf_counter() - start
                nested = stack.pop()
                totals[name] = totals.get(name, 0.0) + elapsed - nested
                if stack:
                    stack[-1] += elapsed

        return timed

    for name, (owner, attr) in STAGES.items():
        setattr(owner, attr, wrap(name, saved[name]))
    try:
        yield totals
    finally:
        for name, (owner, attr) in STAGES.items():
            setattr(owner, attr, saved[name])


def format_split(totals: dict[str, float], wall: float) -> str:
    """'stage 12% | ...' of ``totals`` over ``wall`` seconds, the remainder as glue."""
    parts = [(n, t) for n, t in totals.items() if t > 0]
    parts.append(("glue", max(wall - sum(totals.values()), 0.0)))
    return " | ".join(f"{n} {100 * t / wall:.0f}%" for n, t in parts)


__all__ = ["STAGES", "format_split", "stage_times"]
