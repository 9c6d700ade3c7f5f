"""The planner interface of the benchmark, its adapters and the built-in planners.

A planner drives one externally controlled agent. Each step it gets a ``PlannerInput`` (what
that agent sees: its pairwise-relative observation, the upcoming points of its logged route,
its goal, the time) and returns a physical action ``(acceleration m/s^2, yaw rate rad/s)``.
Anything with ``act(PlannerInput) -> action`` (and optionally ``reset``) is a planner; thin
adapters fit a plain function (``FunctionPlanner``), a torch module (``TorchPlanner``) and a
Stable-Baselines3 model (``SB3Planner``). ``load_planner("package.module:factory")`` builds
one from a command line.

Built in: ``expert`` (follows its log through the env's inverse dynamics: the benchmark's
ceiling), ``constant_velocity`` (holds speed and heading), ``idm`` (the rule-based ``idm``
controller on a lane route; ``idm_log`` on its logged path).
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from tbsim_env.data.scenario import Scenario
from tbsim_env.sim.state import SimState


@dataclass(frozen=True)
class PlannerInput:
    """What a controlled agent sees at one step.

    Attributes:
        scenario_id: the scene.
        agent: the env's name of the agent (``track_<id>``).
        step: the simulation step (the episode starts at the WOMD current step, 10).
        time_s: s since the episode started.
        observation: the agent's pairwise-relative observation (``TrafficEnv`` keys),
            computed when first read (from ``observations``, every agent's).
        route: [R, 2] float32, the next R points of its logged route in its own frame (x
            forward, y left, m), 2 m apart, ending at the goal.
        goal: [2] float32, the last logged position in its own frame, m.
        speed: m/s, its signed speed.
        expert_action: [2] float32, the action that follows its log (privileged: for the
            ``expert`` baseline; a planner under test should not read it). Computed when
            first read, for every agent of the step at once (``experts``).
        slot: the agent's slot in ``sim`` (its track row in the scenario).
        sim: the whole simulator state as an NPC policy sees it (privileged: for rule-based
            baselines such as ``idm``; a planner under test should read ``observation``).
        experts: () -> {agent: [2] float32} expert actions of the step (memoized by the
            caller); None: no expert (``expert_action`` raises).
    """

    scenario_id: str
    agent: str
    step: int
    time_s: float
    observations: Mapping[str, dict[str, np.ndarray]]
    route: np.ndarray
    goal: np.ndarray
    speed: float
    slot: int = -1
    sim: SimState | None = None
    experts: Callable[[], dict[str, np.ndarray]] | None = dataclasses.field(
        default=None, repr=False, compare=False
    )

    @property
    def observation(self) -> dict[str, np.ndarray]:
        """The agent's observation (see the class docs)."""
        return self.observations[self.agent]

    @property
    def expert_action(self) -> np.ndarray:
        """[2] float32, the action that follows this agent's log (see the class docs)."""
        if self.experts is None:
            raise ValueError(f"no expert action for agent {self.agent!r}: the input has none")
        return self.experts()[self.agent]


@runtime_checkable
class Planner(Protocol):
    """A planner: ``act`` each step; ``reset`` (optional) at the start of each episode."""

    def act(self, x: PlannerInput) -> Any:
        """(acceleration m/s^2, yaw rate rad/s) as anything ``np.asarray`` takes."""
        ...


@dataclass(frozen=True)
class BatchInput:
    """What K controlled agents, one per scene of the batch, see at one step (the batched
    ``PlannerInput``; agent k drives in batch row ``rows[k]``).

    Attributes:
        scenario_ids, agents: [K] the scenes and the env's agent names.
        step: the simulation step; time_s: s since the episode started.
        route: [K, R, 2] float32, the next R points of each logged route in the agent's own
            frame (x forward, y left, m), 2 m apart.
        goal: [K, 2] float32, the last logged position in the agent's frame, m.
        speed: [K] float32 m/s, signed.
        rows, slots: [K] int64, each agent's batch row and agent slot in ``sim``.
        sim: the batched simulator state (privileged, as ``PlannerInput.sim``).
        experts: () -> [K, 2] float32 expert actions (privileged; memoized by the caller).
    """

    scenario_ids: list[str]
    agents: list[str]
    step: int
    time_s: float
    route: np.ndarray
    goal: np.ndarray
    speed: np.ndarray
    rows: np.ndarray
    slots: np.ndarray
    sim: SimState
    experts: Callable[[], np.ndarray]

    @property
    def expert_actions(self) -> np.ndarray:
        """[K, 2] float32, the actions that follow each agent's log (see ``experts``)."""
        return self.experts()


@runtime_checkable
class BatchPlanner(Protocol):
    """A planner that drives the agents of several scenes at once: ``act_batch`` each step;
    ``reset_batch(scenarios, agents, seeds)`` (optional, [K] each) at the start."""

    def act_batch(self, x: BatchInput) -> Any:
        """[K, 2] (acceleration m/s^2, yaw rate rad/s) as anything ``np.asarray`` takes."""
        ...


def reset_planner(planner: Any, scenario: Scenario, agent: str, seed: int) -> None:
    """Call ``planner.reset(scenario, agent, seed)`` when the planner has one."""
    reset = getattr(planner, "reset", None)
    if callable(reset):
        reset(scenario, agent, seed)


@dataclass
class FunctionPlanner:
    """A plain function ``fn(PlannerInput) -> action`` as a planner."""

    fn: Callable[[PlannerInput], Any]
    name: str = "function"

    def act(self, x: PlannerInput) -> Any:
        return self.fn(x)


def _batched(observation: dict[str, np.ndarray]) -> dict[str, torch.Tensor]:
    """The observation as float32 tensors with a batch dimension of one."""
    return {k: torch.as_tensor(np.asarray(v, np.float32))[None] for k, v in observation.items()}


@dataclass
class TorchPlanner:
    """A torch module as a planner: ``module(obs, route)`` -> [1, 2] action.

    ``obs`` is the observation dict as float32 tensors [1, ...] and ``route`` the route points
    [1, R, 2]; the module runs under ``torch.no_grad``.
    """

    module: torch.nn.Module
    name: str = "torch"

    def act(self, x: PlannerInput) -> Any:
        route = torch.as_tensor(x.route, dtype=torch.float32)[None]
        with torch.no_grad():
            out = self.module(_batched(x.observation), route)
        return out.reshape(-1)[:2].cpu().numpy()


@dataclass
class SB3Planner:
    """A Stable-Baselines3 model as a planner: ``model.predict(features(x))``.

    Args:
        model: anything with SB3's ``predict(observation, deterministic=True)``.
        features: ``PlannerInput`` -> the observation the model was trained on (default: the
            observation dict with the route under ``"route"``, as a dict-observation policy
            of ``TrafficEnv`` with route points takes it).
        scale: multiplies the predicted action (models trained on normalised actions).
    """

    model: Any
    features: Callable[[PlannerInput], Any] | None = None
    scale: tuple[float, float] = (1.0, 1.0)
    name: str = "sb3"

    def act(self, x: PlannerInput) -> Any:
        obs = self.features(x) if self.features else {**x.observation, "route": x.route}
        action, _ = self.model.predict(obs, deterministic=True)
        return np.asarray(action, np.float32).reshape(-1)[:2] * np.asarray(self.scale)


class ExpertPlanner:
    """Follows its log: the env's inverse-dynamics action towards the next logged state."""

    name = "expert"

    def act(self, x: PlannerInput) -> Any:
        return x.expert_action

    def act_batch(self, x: BatchInput) -> Any:
        return x.expert_actions


class ConstantVelocityPlanner:
    """Holds its speed and heading: zero acceleration and yaw rate."""

    name = "constant_velocity"

    def act(self, x: PlannerInput) -> Any:
        return np.zeros(2, np.float32)

    def act_batch(self, x: BatchInput) -> Any:
        return np.zeros((len(x.agents), 2), np.float32)


class IDMPlanner:
    """The ``idm`` NPC controller driving the agent (``policies.idm``): IDM along a lane-graph
    route (or its logged path), keeping its gap, stopping for signals, stop signs and
    crossing agents. It reads the simulator state (``PlannerInput.sim``), as an NPC does,
    with the type's parameters as they are: no per-agent spread of desired speed or headway
    (that spread makes NPC rollouts differ; a planner baseline drives as designed), and it
    looks for its leader every step (``leader_period`` 1: NPCs search every third step to
    save time, one agent has none to save)."""

    def __init__(self, route: str = "lanes") -> None:
        from policies.idm import IDMPolicy

        self.policy = IDMPolicy(route=route, speed_spread=0.0, headway_spread=0.0, leader_period=1)
        self.name = "idm" if route == "lanes" else f"idm_{route}"
        self._scenario: Scenario | None = None
        self._scenarios: list[Scenario] = []
        self._seeds: list[int] = []
        self._plan: Any = None
        self._generator = torch.Generator()

    def reset(self, scenario: Scenario, agent: str, seed: int) -> None:
        self._scenario, self._plan = scenario, None
        self._generator.manual_seed(int(seed))

    def reset_batch(
        self, scenarios: Sequence[Scenario], agents: Sequence[str], seeds: Sequence[int]
    ) -> None:
        """Start a batch of episodes: agent k in ``scenarios[k]``, seeded by ``seeds[k]``
        (its row starts as ``reset`` with that seed starts it)."""
        del agents  # the slots come with the first input
        self._scenarios, self._plan = list(scenarios), None
        self._seeds = [int(s) for s in seeds]

    def act_batch(self, x: BatchInput) -> Any:
        if x.sim is None or not self._scenarios:
            raise ValueError("the idm planner needs BatchInput.sim and a reset_batch() first")
        if self._plan is None:  # each row's plan of its ego alone, drawn from its own seed
            tracks = [[int(s)] for s in x.slots]
            rows = [torch.Generator().manual_seed(s) for s in self._seeds]
            self._plan = self.policy.initial_state(
                x.sim, self._scenarios, self._generator, tracks, generators=rows
            )
        action, self._plan = self.policy.act(x.sim, self._plan, self._generator)
        return action[torch.from_numpy(x.rows), torch.from_numpy(x.slots)].numpy()

    def act(self, x: PlannerInput) -> Any:
        if x.sim is None or self._scenario is None:
            raise ValueError("the idm planner needs PlannerInput.sim and a reset() first")
        if self._plan is None:  # the route of this agent alone (its slot is its track row)
            self._plan = self.policy.initial_state(
                x.sim, [self._scenario], self._generator, tracks=[[x.slot]]
            )
        action, self._plan = self.policy.act(x.sim, self._plan, self._generator)
        return action[0, x.slot].numpy()


BUILTIN_PLANNERS: dict[str, Callable[[], Any]] = {
    "expert": ExpertPlanner,
    "constant_velocity": ConstantVelocityPlanner,
    "idm": IDMPlanner,
    "idm_log": lambda: IDMPlanner(route="log"),
}
"""Planners named without a module path."""


def load_planner(spec: str) -> Any:
    """A planner from a name of ``BUILTIN_PLANNERS`` or ``"package.module:NAME"``, where NAME is
    a planner object, a factory called without arguments, or a plain function of one argument
    (``PlannerInput`` -> action, wrapped in ``FunctionPlanner``).

    Raises:
        ValueError: a malformed spec, or what it names is no planner.
        ImportError / AttributeError: the module or the name does not exist.
    """
    if spec in BUILTIN_PLANNERS:
        return BUILTIN_PLANNERS[spec]()
    module_name, sep, attr = spec.partition(":")
    if not sep or not module_name or not attr:
        raise ValueError(
            f"planner {spec!r}: use one of {sorted(BUILTIN_PLANNERS)} or PACKAGE.MODULE:NAME"
        )
    obj = getattr(importlib.import_module(module_name), attr)
    if not isinstance(obj, type) and isinstance(obj, Planner):
        return obj
    if not callable(obj):
        raise ValueError(f"planner {spec!r}: {type(obj).__name__} is no planner")
    if not isinstance(obj, type) and _required_arguments(obj) == 1:
        return FunctionPlanner(obj, name=attr)
    planner = obj()
    if not isinstance(planner, Planner):
        raise ValueError(f"planner {spec!r}: {attr}() gave {type(planner).__name__}, no planner")
    return planner


def _required_arguments(fn: Callable) -> int:
    """Positional parameters of ``fn`` without a default."""
    kinds = (inspect.Parameter.POSITIONAL_ONLY, inspect.Parameter.POSITIONAL_OR_KEYWORD)
    try:
        params = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):
        return 0
    return sum(p.kind in kinds and p.default is inspect.Parameter.empty for p in params)


def planner_name(planner: Any) -> str:
    """A planner's display name (its ``name`` or its class name)."""
    return str(getattr(planner, "name", type(planner).__name__))
