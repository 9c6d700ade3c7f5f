"""``StepFunction``: the episode core's ``step``, eager or as one ``torch.compile`` graph.

A batch-of-one step is a few hundred tiny tensor operations, so most of its time is
per-operation overhead (Python, the dispatcher, allocation). One compiled graph of fused C++
kernels removes most of it (``bench/env_step.py`` and ``bench/vector_env.py --compile`` print
both). The NPC policy acts before the step, outside the graph (``episode.npc_actions``).

A compiled graph cannot branch on data or size tensors by it, so the eager shortcuts are not
taken inside it (each checks ``torch.compiler.is_compiling()``): a batch of one reading its
step as a Python number, box tests of the near pairs only (the graph tests every pair), agent
pairs over each row's valid slots only and the grid's nearest-map-piece search (the graph
measures every slot and every piece), and off-road corners the road-edge grid cannot vouch for
recomputed over every segment. The graph recomputes a bounded number of such corners and
reports the rest in ``StepOutput.stale``; ``StepFunction`` then redoes the step eagerly (rare:
a corner far from the map, or in a cell crowded with edges).

The graph is the faster path where per-operation overhead dominates: few controlled agents
on the CPU (2.5x eager with the SDC controlled at B = 1, 1.4x at B = 64), or a GPU. With more
the eager step's shortcuts win (all agents controlled: 0.4-0.5x from B = 16), so
``compile=True`` steps them eagerly and says so in a warning (``COMPILE_CPU_MAX_BATCH``,
``COMPILE_CPU_MAX_OBSERVERS``); ``compile="always"`` forces the graph.

Compiled results equal the eager ones up to float rounding (inductor fuses and reorders
arithmetic: observations differ by ~1e-7). Compiling takes ~15 s on the first step (and again,
once, for another batch shape: the second graph has dynamic shapes) and needs a C++ compiler,
as ``torch.compile`` on the CPU does.
"""

from __future__ import annotations

import dataclasses
import warnings

import torch

from tbsim_env.core import constants as C
from tbsim_env.env.episode import EpisodeState, StepConfig, StepOutput, step


class StepFunction:
    """``episode.step`` with fixed constants, eager or compiled.

    Args:
        config: the step's constants (they become constants of the graph).
        compile: ``False``: eager. ``True``: one ``torch.compile`` graph (``fullgraph=True``)
            where it is the faster path: on a GPU, or on the CPU for batches of at most
            ``COMPILE_CPU_MAX_BATCH`` scenarios and ``COMPILE_CPU_MAX_OBSERVERS`` controlled
            agents (larger CPU batches step eagerly, with a warning that says so).
            ``"always"``: the graph whatever the batch.
        batch_size: scenarios per batch (None: unknown, taken as 1).
        observers: controlled agent slots of the whole batch (None: one per scenario).
        device: where the steps run.

    Attributes:
        eager_redos: compiled steps redone eagerly because a bounded search of the graph
            could not vouch for its result (``StepOutput.stale``).
    """

    def __init__(
        self,
        config: StepConfig,
        compile: bool | str = False,
        batch_size: int | None = None,
        device: torch.device | str = "cpu",
        observers: int | None = None,
    ) -> None:
        if compile not in (False, True, "always"):
            raise ValueError(f"compile must be False, True or 'always', got {compile!r}")
        self.config = config
        self.eager_redos = 0
        b = batch_size or 1
        graph = compile == "always" or (
            compile is True and _graph_pays(b, observers or b, torch.device(device))
        )
        if compile is True and not graph:
            warnings.warn(
                f"compile=True: a batch of {b} scenarios ({observers or b} controlled agents) "
                f"steps eagerly on the CPU, where the compiled graph is slower beyond "
                f"{C.COMPILE_CPU_MAX_BATCH} scenarios or {C.COMPILE_CPU_MAX_OBSERVERS} agents "
                "(it tests every agent pair and map piece); compile='always' forces the graph",
                stacklevel=3,
            )
        self._fn = torch.compile(step, fullgraph=True) if graph else None

    @property
    def compiled(self) -> bool:
        return self._fn is not None

    def __call__(
        self, state: EpisodeState, actions: torch.Tensor, npc_action: torch.Tensor | None
    ) -> tuple[EpisodeState, StepOutput]:
        """``step(state, actions, npc_action, config)``, through the graph when compiled."""
        if self._fn is None:
            return step(state, actions, npc_action, self.config)
        # The policy's state is not the graph's business (any structure, never read by step).
        body = dataclasses.replace(state, policy_state=None)
        nxt, out = self._fn(body, actions, npc_action, self.config)
        if bool(out.stale.any()):
            self.eager_redos += 1
            nxt, out = step(body, actions, npc_action, self.config)
        return dataclasses.replace(nxt, policy_state=state.policy_state), out


def _graph_pays(batch_size: int, observers: int, device: torch.device) -> bool:
    """Whether the compiled graph is the faster path for this batch (see
    ``COMPILE_CPU_MAX_BATCH``): always on a GPU, small batches on the CPU."""
    if device.type != "cpu":
        return True
    return batch_size <= C.COMPILE_CPU_MAX_BATCH and observers <= C.COMPILE_CPU_MAX_OBSERVERS


__all__ = ["StepFunction"]
