"""Several scenes' benchmark episodes stepped together: one batched simulation of B scenes,
one planner call a step for all of them.

Used where it gives what one scene at a time gives (``batchable``): the SDC driven, traffic
whose draws a batch can make per scene (``BATCHED_TRAFFIC``: log replay, ``idm``), so that a
scene's episode cannot depend on the scenes beside it, and a planner with ``act_batch`` (a
``BatchPlanner``: the built-ins). The
episode is the one of ``episode.run_episode`` (no termination; the same records), its cost
per scene a fraction: the simulation's step, the planner's rules and their fixed per-call
costs are paid once for the batch.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from tbsim_env.benchmark.episode import (
    ROUTE_POINTS,
    ROUTE_SPACING,
    EpisodeRecord,
    EpisodeSpec,
    PlannerError,
    Trace,
    make_record,
    slot_fields,
)
from tbsim_env.benchmark.planner import BatchInput, BatchPlanner
from tbsim_env.core.config import EnvConfig, TerminationConfig
from tbsim_env.core.torch_utils import torch_threads
from tbsim_env.env import episode as ep
from tbsim_env.env.compiled import StepFunction
from tbsim_env.env.setup import agent_name, make_npc_policy, select_scenarios
from tbsim_env.env.vector_env import route_features
from tbsim_env.observation.tokens import ObsConfig
from tbsim_env.sim.geometry import to_local

BATCHED_TRAFFIC = ("log_replay", "idm", "idm_lanes")
"""Traffic whose episodes a batch reproduces: log replay draws nothing; the ``idm`` policies
draw only at the start, each row from a generator seeded as its scene alone would be."""


def batch_eligible(spec: EpisodeSpec) -> bool:
    """Whether ``spec``'s episode may run in a batch with a planner that has ``act_batch``:
    the SDC driven, traffic of ``BATCHED_TRAFFIC``."""
    return spec.controlled == "sdc" and spec.traffic in BATCHED_TRAFFIC


def batchable(spec: EpisodeSpec, planner: Any) -> bool:
    """Whether ``spec``'s episode may run in a batch with ``planner`` (see the module)."""
    return batch_eligible(spec) and isinstance(planner, BatchPlanner)


@dataclass
class _Run:
    """The batch's simulation and what it has recorded so far (one list entry a state).

    Attributes:
        specs, names: the batch's episodes and their egos' agent names.
        state: the simulation now; step_fn: its step; policy: the NPC policy (acting when
            ``has_npc``, with ``generator``, as ``TrafficEnv`` steps it).
        pose, speed, valid, offroad, progress: what ``Trace`` is made of, per state.
    """

    specs: Sequence[EpisodeSpec]
    names: list[str]
    state: ep.EpisodeState
    step_fn: StepFunction
    policy: Any
    has_npc: bool
    generator: torch.Generator = field(default_factory=torch.Generator)
    pose: list[torch.Tensor] = field(default_factory=list)
    speed: list[torch.Tensor] = field(default_factory=list)
    valid: list[torch.Tensor] = field(default_factory=list)
    offroad: list[torch.Tensor] = field(default_factory=list)
    progress: list[torch.Tensor] = field(default_factory=list)

    def record(self, state: ep.EpisodeState, metrics: Any) -> None:
        """Keep the states of every slot and the egos' infos of ``state``."""
        sim = state.sim
        pose = sim.pose.double()
        pose[..., :2] += sim.origin.double()[:, None]
        infos = ep.agent_infos(state, metrics)
        self.pose.append(pose)
        self.speed.append(sim.speed.double())
        self.valid.append(sim.valid.clone())
        self.offroad.append(infos["offroad_distance"][:, 0].double())
        self.progress.append(infos["progress"][:, 0].double())
        self.state = state

    def advance(self, action: np.ndarray) -> None:
        """One step (0.1 s): the egos' actions [B, 2], the NPCs' from their policy; recorded."""
        state, npc = self.state, None
        act = torch.zeros(state.batch_size, state.setup.query.shape[1], 2)
        act[:, 0] = torch.from_numpy(action)
        if self.has_npc:
            npc, policy_state = ep.npc_actions(self.policy, state, self.generator)
            state = dataclasses.replace(state, policy_state=policy_state)
        state, out = self.step_fn(state, act, npc)
        self.record(state, out.metrics)


def _inputs(run: _Run, step: int, t0: int) -> BatchInput:
    """The batch's ``BatchInput`` at ``step`` (one ego per row: column 0 of the query)."""
    state = run.state
    setup, sim = state.setup, state.sim
    query = setup.query[:, :1]
    pose = sim.pose.gather(1, query[..., None].expand(-1, -1, 3))  # [B, 1, 3]
    route = route_features(setup.route, state.progress, pose, ROUTE_POINTS, ROUTE_SPACING)
    goal = to_local(setup.route.goal[:, :1, None, :], pose[..., None, :])[..., 0, :]
    experts = functools.cache(lambda: ep.expert_actions(state)[:, 0].float().numpy())
    b = state.batch_size
    return BatchInput(
        scenario_ids=[s.scenario.scenario_id for s in run.specs],
        agents=run.names,
        step=step,
        time_s=round((step - t0) * 0.1, 6),
        route=route[:, 0].numpy(),
        goal=goal[:, 0].float().numpy(),
        speed=sim.speed.gather(1, query)[:, 0].numpy(),
        rows=np.arange(b),
        slots=query[:, 0].numpy().copy(),
        sim=sim,
        experts=experts,
    )


def _checked(action: Any, x: BatchInput) -> tuple[np.ndarray, dict[int, str]]:
    """The batch's actions as float32 [K, 2] (zero in failed rows) and {row: why it failed}
    (every row when the whole answer is malformed)."""
    k = len(x.agents)
    where = [f"scene {s}, agent {a}, step {x.step}" for s, a in zip(x.scenario_ids, x.agents)]
    try:
        a = np.asarray(action, np.float32)
    except (TypeError, ValueError) as err:
        return np.zeros((k, 2), np.float32), {i: f"{w}: action is not numeric ({err})"
                                              for i, w in enumerate(where)}  # fmt: skip
    if a.shape != (k, 2):
        why = f"act_batch returned shape {a.shape}, expected ({k}, 2) (accel, yaw rate)"
        return np.zeros((k, 2), np.float32), {i: f"{w}: {why}" for i, w in enumerate(where)}
    bad = np.flatnonzero(~np.isfinite(a).all(-1))
    failed = {int(i): f"{where[i]}: action {a[i].tolist()} is not finite" for i in bad}
    return np.where(np.isfinite(a), a, 0.0).astype(np.float32), failed


def _start(specs: Sequence[EpisodeSpec], config: EnvConfig) -> _Run:
    """The batch's simulation at its first state (recorded)."""
    first = specs[0]
    kwargs = None if first.npc_checkpoint is None else {"checkpoint": first.npc_checkpoint}
    policy = make_npc_policy(first.traffic, kwargs, torch.device("cpu"))
    sel = select_scenarios([s.scenario for s in specs], "sdc", config, policy, False)
    step_config = ep.StepConfig(config, ObsConfig(), dense=True, observe=False)
    exact = bool(getattr(policy, "exact_replay", False))
    bank = ep.build_bank(sel.scenarios, sel.queries, exact, step_config, torch.device("cpu"))
    state, metrics = ep.start(bank, torch.arange(len(specs)))
    has_npc = bool(state.setup.npc.any())
    if has_npc:  # as ``TrafficEnv``: NPCs act through the policy
        rows = {}
        if first.traffic != "log_replay":  # each row seeded as its scene's env alone
            rows["generators"] = [torch.Generator().manual_seed(int(s.seed)) for s in specs]
        start = policy.initial_state(state.sim, sel.scenarios, torch.Generator(), **rows)
        state = dataclasses.replace(state, policy_state=start)
    names = [agent_name(sc.tracks.id[q[0]]) for sc, q in zip(sel.scenarios, sel.queries)]
    run = _Run(specs, names, state, StepFunction(step_config, False), policy, has_npc)
    run.record(state, metrics)
    return run


def _act(planner: Any, x: BatchInput) -> tuple[np.ndarray, dict[int, str]]:
    """The planner's actions [B, 2] (zero in failed rows) and {row: why it failed}: the
    malformed rows, or every row when the planner raised."""
    try:
        return _checked(planner.act_batch(x), x)
    except Exception as err:  # the planner's own failure, reported, not raised
        why = f"planner raised {type(err).__name__}: {err}"
        failed = {k: f"scene {s}, agent {x.agents[k]}, step {x.step}: {why}"
                  for k, s in enumerate(x.scenario_ids)}  # fmt: skip
        return np.zeros((len(x.agents), 2), np.float32), failed


def _traces(run: _Run, ends: Sequence[int]) -> list[Trace]:
    """Each scene's ``Trace`` (its own agent slots, its states up to ``ends[k]``)."""
    pose, speed, valid = (torch.stack(x, 1).numpy() for x in (run.pose, run.speed, run.valid))
    offroad, progress = (torch.stack(x, 1).numpy() for x in (run.offroad, run.progress))
    agents = run.state.sim.agents
    out = []
    for k, spec in enumerate(run.specs):
        n, t = spec.scenario.tracks.num_tracks, ends[k] + 1
        out.append(
            Trace(
                pose=pose[k, :t, :n],
                speed=speed[k, :t, :n],
                valid=valid[k, :t, :n],
                offroad=offroad[k, :t],
                progress=progress[k, :t],
                **slot_fields(agents, k, n),
            )
        )
    return out


def run_batch(
    specs: Sequence[EpisodeSpec], planner: Any, torch_thread_count: int | None = 1
) -> list[EpisodeRecord]:
    """The episodes of ``specs`` (``batchable`` ones of one traffic mode), stepped together
    with one ``BatchPlanner``; one record per scene, in order, equal to ``run_episode``'s.
    A row whose action is malformed fails alone (its record carries the error and the states
    up to it); a planner that raises fails every row of the batch."""
    never = EnvConfig(termination=TerminationConfig(collision=False, goal=False))
    with torch_threads(torch_thread_count), torch.inference_mode():
        run = _start(specs, never)
        reset = getattr(planner, "reset_batch", None)
        if callable(reset):
            reset([s.scenario for s in specs], run.names, [s.seed for s in specs])
        t0 = never.start_step
        errors: dict[int, str] = {}
        ends = [never.last_step - t0] * len(specs)
        for i, step in enumerate(range(t0, never.last_step)):
            action, failed = _act(planner, _inputs(run, step, t0))
            for k, why in failed.items():
                if k not in errors:
                    errors[k], ends[k] = str(PlannerError(why)), i
            if len(errors) == len(specs):
                break
            run.advance(action)
    traces = _traces(run, ends)
    return [
        make_record(
            spec, run.names[k], int(run.state.setup.query[k, 0]), traces[k], never, errors.get(k)
        )  # fmt: skip
        for k, spec in enumerate(specs)
    ]


__all__ = ["BATCHED_TRAFFIC", "batch_eligible", "batchable", "run_batch"]
