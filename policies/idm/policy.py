"""``IDMPolicy``: rule-based reactive traffic as a ``Policy`` (see ``policies/idm/__init__``).

Every step, each agent with a route (all agent slots at once, no loop over agents or steps):

1. finds its progress along its route (``tracking.advance_progress``);
2. takes the IDM acceleration (``tbsim_env.sim.idm``) toward its desired speed, capped in
   bends, against the most constraining of: the leader in its corridor (``leaders``), the
   stop line of a red or yellow signal, of a stop sign before its full stop and a clear
   junction, of a crosswalk with a pedestrian on it (``yielding``), and the end of a route
   that cannot go on;
3. steers with pure pursuit (``tracking.pursuit_curvature``): yaw rate = curvature x speed.

Actions are the unicycle's (acceleration m/s^2, yaw rate rad/s); the simulator clips them to
the type's limits, so every agent obeys one dynamics.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import torch

from policies.idm.lanes import LaneGraph, lane_graph
from policies.idm.leaders import Agents, Leader, corridor, find_leaders
from policies.idm.params import (
    CROSSWALK_VERTICES,
    HEADWAY_FIT_SHARE,
    HEADWAY_FIT_SPEED,
    HEADWAY_RELAX_TIME,
    HORIZON_BASE,
    HORIZON_TIME,
    MAX_CROSSWALKS,
    MAX_SIGN_STOPS,
    MAX_SIGNAL_STOPS,
    ROUTE_SPACING,
    SCENE_CROSSWALKS,
    IDMConfig,
)
from policies.idm.plan import PARAM_FIELDS, ScenePlan, scene_plan
from policies.idm.tracking import advance_progress, pursuit_curvature
from policies.idm.yielding import (
    crosswalk_distance,
    crosswalks_occupied,
    junction_clear,
    sign_distance,
    sign_progress,
    signal_distance,
)
from tbsim_env.core.constants import DT, ObjectType
from tbsim_env.core.lru import LRU
from tbsim_env.core.torch_utils import select_rows, true_index
from tbsim_env.data.scenario import Scenario
from tbsim_env.sim.idm import (
    MIN_DESIRED_SPEED,
    IDMTerms,
    acceleration,
    approach_gap,
    crowding,
    terms_at,
)
from tbsim_env.sim.state import SimState

BRANCH_VARIANTS = 4
"""Route variants per scene: a rollout draws one (its random fork branches), so that a scene's
routes are built at most this many times however many rollouts start from it."""
HEADWAY_RELAX_STEP = math.exp(-DT / HEADWAY_RELAX_TIME)
"""The factor a step leaves of ``IDMState.headway_cut``."""
CACHE_SCENES = 256
"""Scene plans kept (least recently used dropped first)."""


_START_MOTION = {
    "progress": 0.0,
    "lead_gap": float("inf"),
    "lead_speed": 0.0,
    "yield_gap": float("inf"),
    "stand_arc": float("inf"),
    "headway_cut": 0.0,
}
"""``IDMState.motion`` of every slot at the start: no leader, crossing, stand line nor cut."""
MOTION_FIELDS = tuple(_START_MOTION)
"""The columns of ``IDMState.motion``, in order."""


def _motion_column(name: str) -> property:
    """A read-only [B, N] view of the column ``name`` of ``IDMState.motion``."""
    k = MOTION_FIELDS.index(name)
    return property(lambda self: self.motion[..., k], doc=f"[B, N] ``motion``'s {name}.")


@dataclass(frozen=True)
class IDMState:
    """Per-rollout memory of ``IDMPolicy``: B rows, N agent slots, in the state's frame.

    Attributes:
        route: [B, N, P, 2] float32 route points, m, ``ROUTE_SPACING`` apart.
        speed_cap: [B, N, P] float32 m/s the route's bends allow.
        desired_speed: [B, N] float32 m/s (drawn per rollout).
        params: [B, N, F] float32, the ``plan.PARAM_FIELDS`` of each agent (time headway
            drawn per rollout).
        lines: [B, N, Ks + Kt + Kc + 1] float32 arc lengths (m) along the route of the
            signal stop lines (Ks), the stop-sign lines (Kt), the crosswalk entries (Kc) and
            the route's end (+inf: open route); +inf padding, and every line +inf for the
            agents that do not stop for signals, stop signs or crosswalks (pedestrians), so
            that one gather reads all that holds an agent (``LINE_COLUMNS``).
        line_row: [B, N, Ks + Kc] int64 rows of ``SimState.signals`` (Ks) and of
            ``crosswalks`` (Kc) of those lines (-1 padding).
        sign_flags: [B, N, 2, Kt] bool, per stop-sign line: the full stop there is made
            (``[..., 0, :]``), and the junction was clear after it: the agent goes
            (``[..., 1, :]``).
        lead_known: [B, N] bool, the agent has searched for leaders since the start.
        motion: [B, N, 6] float32, what a step reads and writes of each agent, in one table
            (``MOTION_FIELDS``; each column also a property of that name, [B, N]): progress m,
            the agent's arc length along its route; lead_gap m, bumper gap to the leader of
            the last search, carried on since (+inf: none); lead_speed m/s, that leader's
            speed; yield_gap m to the crossing yielded to (+inf: none), likewise; stand_arc m,
            arc length along the route where the agent must stand (the nearest stop line that
            holds it, or its route's end; +inf: none) as of its row's last search, carried on
            in between (``IDMConfig.leader_period``); headway_cut s taken off the drawn time
            headway now: the cut that lets an agent follow its leader at the start at its
            logged gap (``_start_cut``; NaN until the agent's first leader search fixes
            it), shrinking by ``HEADWAY_RELAX_TIME``.
        crosswalks: [B, W, V, 2] float32 m crosswalk outlines (zeros: none).
        valid: [B, N] bool, the slot has a route (agents that never appear have none).
        clock: the batch's step count for the search cadence: its rows' step when the state
            started, one more each ``act``. The rows look for leaders and stand lines
            together when it is a multiple of ``IDMConfig.leader_period`` (and a row at its
            first act), so that a row restarted alone (``BatchedTrafficEnv``) searches on
            the others' steps after its first, not on steps of its own (a search of a few
            agents costs the tensor operations of a search of all). A number, kept as it
            is when rows are replaced (``rows.with_rows(strict=False)``).
    """

    route: torch.Tensor
    speed_cap: torch.Tensor
    desired_speed: torch.Tensor
    params: torch.Tensor
    lines: torch.Tensor
    line_row: torch.Tensor
    sign_flags: torch.Tensor
    lead_known: torch.Tensor
    motion: torch.Tensor
    crosswalks: torch.Tensor
    valid: torch.Tensor
    clock: int = 0

    progress = _motion_column("progress")
    lead_gap = _motion_column("lead_gap")
    lead_speed = _motion_column("lead_speed")
    yield_gap = _motion_column("yield_gap")
    stand_arc = _motion_column("stand_arc")
    headway_cut = _motion_column("headway_cut")


_SIGNS = MAX_SIGNAL_STOPS + MAX_SIGN_STOPS
LINE_COLUMNS = {
    "signal": slice(0, MAX_SIGNAL_STOPS),
    "sign": slice(MAX_SIGNAL_STOPS, _SIGNS),
    "crosswalk": slice(_SIGNS, _SIGNS + MAX_CROSSWALKS),
    "end": _SIGNS + MAX_CROSSWALKS,
}
"""The columns of ``IDMState.lines`` per kind of stop line (the last one: the route's end);
``IDMState.line_row`` holds the signal rows, then the crosswalk rows."""
_PAD = {"params": 1.0, "lines": np.inf, "line_row": -1}
"""The value of the slots (and crosswalk rows) past a scene's own, per field (others: 0)."""


def _row(plan: ScenePlan, origin: np.ndarray) -> dict[str, np.ndarray]:
    """One batch row's fields of a scene plan, in the state's frame, unpadded: [A, ...] per
    agent, crosswalks [W, V, 2]."""
    r, e = plan.routes, plan.events
    lines = np.concatenate([e.signal_arc, e.sign_arc, e.crosswalk_arc], 1)
    lines[~plan.obeys] = np.inf
    return {
        "route": r.points - origin,
        "speed_cap": plan.speed_cap,
        "desired_speed": plan.desired_speed,
        "params": plan.params,
        "lines": np.concatenate([lines, r.end[:, None]], 1),
        "line_row": np.concatenate([e.signal_row, e.crosswalk_row], 1),
        "crosswalks": plan.crosswalks.reshape(-1, CROSSWALK_VERTICES, 2) - origin,
        "valid": r.valid,
    }


def _batch(rows: Sequence[dict[str, np.ndarray]], n: int) -> dict[str, torch.Tensor]:
    """The rows' fields as [B, N, ...] tensors (crosswalks [B, ``SCENE_CROSSWALKS``, V, 2]),
    float32 for floats, padded with ``_PAD``: each distinct row (rows that are one object,
    ``IDMPolicy``'s cache of rows, are padded once) written once, then gathered."""
    distinct = list({id(row): row for row in rows}.values())  # in order of first use
    slot = {id(row): k for k, row in enumerate(distinct)}
    which = np.array([slot[id(row)] for row in rows])
    out = {}
    for name, first in rows[0].items():
        size = SCENE_CROSSWALKS if name == "crosswalks" else n
        dtype = np.float32 if first.dtype.kind == "f" else first.dtype
        padded = np.full((len(distinct), size, *first.shape[1:]), _PAD.get(name, 0), dtype)
        for k, row in enumerate(distinct):
            padded[k, : len(row[name])] = row[name]
        out[name] = torch.from_numpy(padded.take(which, axis=0))
    return out


def _row_draws(
    generators: Sequence[torch.Generator], counts: Sequence[int], n: int
) -> tuple[list[int], torch.Tensor]:
    """(branch variant per row, [2, B, n] uniform draws): row k's drawn from
    ``generators[k]`` as ``initial_state`` draws them for its scene alone (``counts[k]``
    slots), zero in the padding."""
    variant, u = [], torch.zeros(2, len(counts), n)
    for k, (g, c) in enumerate(zip(generators, counts)):
        variant.append(int(torch.randint(BRANCH_VARIANTS, (1,), generator=g)))
        u[:, k, :c] = torch.rand(2, 1, c, generator=g)[:, 0]
    return variant, u


def _rows(x: torch.Tensor, agent: torch.Tensor) -> torch.Tensor:
    """The rows ``agent`` [L] (flat slot indices b * N + n) of ``x`` [B, N, ...]: [L, ...]."""
    return select_rows(x, agent).view(agent.shape[0], *x.shape[2:])


class IDMPolicy:
    """Rule-based reactive traffic: IDM along a route, pure-pursuit steering (see the module
    docstring and ``policies/idm/__init__``).

    Args:
        route: ``"log"`` or ``"lanes"`` (overrides ``config.route`` when given).
        config: the settings (``IDMConfig``); keyword arguments replace its fields, e.g.
            ``IDMPolicy(route="lanes", vehicle={"time_headway": 1.5})``.

    Raises:
        ValueError: a parameter out of range (named in the message).
    """

    name = "idm"
    owns_state = True
    """Every tensor of an ``IDMState`` is made for it (``initial_state`` pads the cached rows
    into new tables; ``act`` carries them on or makes new ones): a batched env writes
    restarted rows into them in place (``tbsim_env.sim.policy``)."""
    exact_replay = False

    def __init__(self, route: str | None = None, config: IDMConfig | None = None, **fields):
        cfg = config or IDMConfig()
        if route is not None:
            fields["route"] = route
        unknown = set(fields) - {f.name for f in dataclasses.fields(IDMConfig)}
        if unknown:
            raise ValueError(f"unknown IDM setting(s) {sorted(unknown)}")
        self.config = dataclasses.replace(cfg, **fields) if fields else cfg
        self._graphs: LRU[int, tuple[Scenario, LaneGraph]] = LRU(CACHE_SCENES)
        self._plans: LRU[tuple, tuple[Scenario, ScenePlan]] = LRU(CACHE_SCENES)
        self._rows: LRU[tuple, tuple[ScenePlan, dict[str, np.ndarray]]] = LRU(CACHE_SCENES)

    # ------------------------------------------------------------------ planning
    def lane_graph(self, scenario: Scenario) -> LaneGraph:
        """The scenario's lane graph (built once per scenario object)."""
        key = id(scenario)
        hit = self._graphs.get(key)
        if hit is None or hit[0] is not scenario:
            hit = self._graphs.put(key, (scenario, lane_graph(scenario.road_map)))
        return hit[1]

    def plan(
        self,
        scenario: Scenario,
        start: int,
        variant: int = 0,
        tracks: Sequence[int] | None = None,
    ) -> ScenePlan:
        """The scene plan from step ``start`` with branch variant ``variant`` (cached), of
        every track or of the track rows ``tracks`` alone (the others get no route)."""
        only = None if tracks is None else tuple(sorted(int(k) for k in tracks))
        key = (id(scenario), int(start), int(variant), only)
        hit = self._plans.get(key)
        if hit is None or hit[0] is not scenario:
            rng = np.random.default_rng([int(variant), int(start)])
            mask = None
            if only is not None:
                mask = np.zeros(scenario.tracks.num_tracks, bool)
                mask[list(only)] = True
            graph = self.lane_graph(scenario)
            built = scene_plan(scenario, graph, start, self.config, rng, mask)
            hit = self._plans.put(key, (scenario, built))
        return hit[1]

    def _row(self, plan: ScenePlan, origin: np.ndarray) -> dict[str, np.ndarray]:
        """``_row`` of a plan and a frame origin [2] (cached: the rows of a batch that start
        one scene share it; never modified)."""
        key = (id(plan), origin.tobytes())
        hit = self._rows.get(key)
        if hit is None or hit[0] is not plan:
            hit = self._rows.put(key, (plan, _row(plan, origin)))
        return hit[1]

    def initial_state(
        self,
        state: SimState,
        scenarios: Sequence[Scenario],
        generator: torch.Generator,
        tracks: Sequence[Sequence[int]] | None = None,
        generators: Sequence[torch.Generator] | None = None,
    ) -> IDMState:
        """Routes and per-agent parameters of every row (desired speed and time headway drawn
        from ``generator``); with ``tracks``, per row the track rows (= slots) the policy
        will drive, the others getting no route (``IDMPlanner`` drives one agent); with
        ``generators``, one per row instead of ``generator``: row k draws from its own what a
        batch of its scene alone draws, so that it starts as it would alone."""
        b, n = state.batch_size, state.num_agents
        if generators is None:
            variant = torch.randint(BRANCH_VARIANTS, (b,), generator=generator).tolist()
            u = torch.rand(2, b, n, generator=generator)
        else:
            counts = [sc.tracks.num_tracks for sc in scenarios]  # a scene's slots alone
            variant, u = _row_draws(generators, counts, n)
        steps = state.step.tolist()
        origins = state.origin.cpu().numpy()
        rows = [
            self._row(
                self.plan(sc, steps[k], variant[k], None if tracks is None else tracks[k]),
                origins[k],
            )
            for k, sc in enumerate(scenarios)
        ]
        dev = state.device
        f = {k: v.to(dev) for k, v in _batch(rows, n).items()}
        u = u.to(dev) * 2.0 - 1.0
        cfg = self.config
        f["desired_speed"] = f["desired_speed"] * (1.0 + cfg.speed_spread * u[0])
        headway = PARAM_FIELDS.index("time_headway")
        f["params"][..., headway] *= 1.0 + cfg.headway_spread * u[1]
        start = IDMState(
            sign_flags=torch.zeros(b, n, 2, MAX_SIGN_STOPS, dtype=torch.bool, device=dev),
            lead_known=torch.zeros(b, n, dtype=torch.bool, device=dev),
            motion=torch.tensor(list(_START_MOTION.values()), device=dev).repeat(b, n, 1),
            clock=steps[0] if steps else 0,
            **f,
        )
        # The start headway of each agent that follows is fixed at its first leader search
        # (``_start_cut``, in ``act``): NaN until then.
        pending = state.valid & start.valid & (start.desired_speed >= MIN_DESIRED_SPEED)
        start.motion[..., MOTION_FIELDS.index("headway_cut")].masked_fill_(pending, float("nan"))
        return start

    def _start_cut(
        self, speed: torch.Tensor, desired: torch.Tensor, leader: Leader, terms: IDMTerms
    ) -> torch.Tensor:
        """[L] s: the ``headway_cut`` of agents at their first leader search (speed and desired
        speed [L] m/s, the leaders found, their IDM terms with the drawn time headway): for an
        agent that follows a leader closer than its time headway T allows, the cut that lowers
        T to what its gap allows, no lower than ``IDMConfig.min_headway``; 0 for the others.

        With v its speed, v0 its desired speed, s and v_l its leader's gap and speed, the
        lowered T makes the IDM's desired gap s* = s0 + v T + v (v - v_l) / (2 sqrt(a b))
        equal rho s, rho^2 = max(1 - (v / v0)^delta, ``HEADWAY_FIT_SHARE``): the agent keeps
        its logged gap in equilibrium (zero acceleration) instead of braking at once; the cut
        then shrinks by ``HEADWAY_RELAX_TIME`` (the headway relaxation of Schakel, Knoop &
        van Arem 2012), so that later conflicts, a merge say, meet its own headway. Agents
        slower than ``HEADWAY_FIT_SPEED`` or with no leader get no cut.
        """
        v = speed.clamp_min(HEADWAY_FIT_SPEED)
        free = 1.0 - (v / desired.clamp_min(MIN_DESIRED_SPEED)) ** terms.exponent
        rho = free.clamp_min(HEADWAY_FIT_SHARE).sqrt()
        closing = approach_gap(v, leader.speed, terms)
        fit = (rho * leader.gap - terms.standstill_gap - closing) / v
        fitted = (speed >= HEADWAY_FIT_SPEED) & torch.isfinite(leader.gap)
        cut = (terms.time_headway - fit.clamp_min(self.config.min_headway)).clamp_min(0.0)
        return torch.where(fitted, cut, torch.zeros_like(cut))

    # ------------------------------------------------------------------ acting
    def act(
        self, state: SimState, policy_state: IDMState, generator: torch.Generator
    ) -> tuple[torch.Tensor, IDMState]:
        """Actions [B, N, 2] (acceleration m/s^2, yaw rate rad/s) of every slot (zero where the
        slot has no route or is absent) and the next policy state."""
        del generator  # everything random was drawn in ``initial_state``
        ps, cfg = policy_state, self.config
        b, n = state.batch_size, state.num_agents
        # [L] the present agents, less the parked ones: held (no desired speed: they never
        # move again in this rollout) and standing, whose action is zero and whose progress,
        # stop-sign flags and leaders nothing reads; about half the agents of real scenes.
        parked = (ps.desired_speed < MIN_DESIRED_SPEED) & (state.speed == 0.0)
        agent = true_index(state.valid & ps.valid & ~parked)
        take = functools.partial(_rows, agent=agent)
        pose, speed, size = take(state.pose), take(state.speed), take(state.agents.size)
        # The MOTION_FIELDS, in order.
        last, gap, lead_speed, crossing, stand_arc, cut = take(ps.motion).unbind(-1)
        progress = advance_progress(ps.route, agent, last, pose[:, :2])
        a, decel, headway, s0, delta, max_decel, look0, look_t = take(ps.params).unbind(-1)
        # Stand lines and leaders are looked for by all rows together, on the batch's steps
        # that are multiples of ``leader_period`` (``IDMState.clock``), and by a row at its
        # first act (nobody has searched), and carried on in between: one search of a few
        # agents costs the tensor operations of a search of all, so two steps in three skip
        # both whole.
        if ps.clock % cfg.leader_period == 0:
            turn = torch.ones(b, dtype=torch.bool, device=state.device)
        else:
            turn = ~ps.lead_known.any(1)  # [B]
        turn = turn.index_select(0, agent // n)  # [L]
        searching = bool(turn.any())
        pending = None  # agents whose start headway this search fixes (NaN cut)
        if searching:
            pending = torch.isnan(cut)
            if bool(pending.any()):
                cut = torch.where(pending, 0.0, cut)
            else:
                pending = None
        terms = IDMTerms(a, decel, headway - cut, s0, delta)
        if searching:  # else the stand lines and stop-sign flags stay as they are
            where = (progress, size[:, 0], speed, decel)
            stand_arc, flags = self._stand_lines(state, ps, agent, where, (turn, stand_arc))
        desired = take(ps.desired_speed)
        follow = desired >= MIN_DESIRED_SPEED  # held agents need no leader
        carried = Leader(gap, lead_speed, crossing)
        now = (progress, follow & turn)
        leader, known = self._leaders(state, ps, (agent, carried), now, terms)
        if pending is not None:
            cut = torch.where(pending, self._start_cut(speed, desired, leader, terms), cut)
            terms = IDMTerms(a, decel, headway - cut, s0, delta)
        # The stand line, the leader and the crossing yielded to, in one [3, L] evaluation
        # (agents along the contiguous dimension: their terms broadcast at full width).
        zero = torch.zeros_like(speed)
        gaps = torch.stack([stand_arc - progress + s0, leader.gap, leader.crossing], 0)
        leads = torch.stack([zero, leader.speed, zero], 0)
        crowd = crowding(speed, gaps, leads, terms, cfg.min_gap).amax(0)
        cap_index = (progress / ROUTE_SPACING).round().long().clamp(0, ps.speed_cap.shape[-1] - 1)
        cap = ps.speed_cap.view(-1).index_select(0, agent * ps.speed_cap.shape[-1] + cap_index)
        acc = acceleration(speed, torch.minimum(desired, cap), crowd, terms)
        acc = torch.where(follow, acc, -speed / DT)
        acc = torch.maximum(torch.minimum(acc, a), -max_decel)
        acc = torch.maximum(acc, -speed / DT)  # brake to a stop, never into reverse
        lookahead = look0 + look_t * speed.clamp_min(0.0)
        curvature = pursuit_curvature(ps.route, agent, progress, pose, lookahead)
        yaw_rate = curvature * (speed + 0.5 * DT * acc).clamp_min(0.0)
        action = torch.zeros(b * n, 2, dtype=pose.dtype, device=pose.device)
        action = action.index_copy(0, agent, torch.stack([acc, yaw_rate], -1)).view(b, n, 2)
        put = lambda x, v: x.flatten(0, 1).index_copy(0, agent, v).view_as(x)  # noqa: E731
        row = torch.stack([progress, leader.gap, leader.speed, leader.crossing, stand_arc, cut], -1)
        motion = put(ps.motion, row)
        motion[..., MOTION_FIELDS.index("headway_cut")] *= HEADWAY_RELAX_STEP  # every slot's
        if not searching:
            return action, dataclasses.replace(ps, motion=motion, clock=ps.clock + 1)
        nxt = dataclasses.replace(
            ps,
            motion=motion,
            clock=ps.clock + 1,
            sign_flags=put(ps.sign_flags, flags),
            lead_known=ps.lead_known if known is None else put(ps.lead_known, known),
        )
        return action, nxt

    def _leaders(
        self,
        state: SimState,
        ps: IDMState,
        agents: tuple[torch.Tensor, Leader],
        now: tuple[torch.Tensor, torch.Tensor],
        terms: IDMTerms,
    ) -> tuple[Leader, torch.Tensor | None]:
        """The L agents' leaders: searched anew (``leaders.find_leaders``) for the agents
        ``asking`` [L] bool (``now`` = (progress [L] m, asking)), carried on from the last search
        for the others (``agents`` = (agent [L] flat slots, their leaders of the last step):
        gaps closing at a step's speed difference). Returns (leaders, ``lead_known`` [L] with
        the searching agents set; None when none searches: it stays as it is)."""
        (agent, last), (progress, asking) = agents, now
        speed = _rows(state.speed, agent)
        gap = last.gap - (speed - last.speed) * DT
        lead = Leader(gap, last.speed, last.crossing - speed * DT)
        search = true_index(asking)
        if search.numel() == 0:
            return lead, None
        speed_now = speed.index_select(0, search).clamp_min(0.0)
        horizon = (HORIZON_BASE + HORIZON_TIME * speed_now).clamp_max(self.config.horizon)
        ask = agent.index_select(0, search)
        lanes = corridor(ps.route, ask, progress.index_select(0, search), horizon)
        pedestrian = None
        if not self.config.pedestrian_gaps:
            pedestrian = state.agents.object_type == int(ObjectType.PEDESTRIAN)
        agents = Agents(state.pose, state.speed, state.agents.size[..., :2], pedestrian)
        sub = terms_at(terms, search)
        found = find_leaders(agents, (state.valid, ask), lanes, sub, self.config)
        lead = Leader(
            gap=lead.gap.index_copy(0, search, found.gap),
            speed=lead.speed.index_copy(0, search, found.speed),
            crossing=lead.crossing.index_copy(0, search, found.crossing),
        )
        return lead, _rows(ps.lead_known, agent).index_fill(0, search, True)

    def _stand_lines(
        self,
        state: SimState,
        ps: IDMState,
        agent: torch.Tensor,
        where: tuple[torch.Tensor, ...],
        carried: tuple[torch.Tensor, torch.Tensor],
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(``stand_arc`` [L] m, ``sign_flags`` [L, 2, Kt]) of the L agents ``agent`` (``where``
        as ``_stand_distance``'s): looked up anew for the agents whose turn it is
        (``carried`` = (turn [L] bool, stand_arc [L] of the last step)), carried on for the
        others."""
        turn, last = carried
        if bool(turn.all()):
            stand, flags = self._stand_distance(state, ps, agent, where)
            return where[0] + stand, flags
        flags_before = _rows(ps.sign_flags, agent)
        due = true_index(turn)
        if due.numel() == 0:
            return last, flags_before
        now = tuple(x.index_select(0, due) for x in where)
        stand, flags = self._stand_distance(state, ps, agent.index_select(0, due), now)
        return last.index_copy(0, due, now[0] + stand), flags_before.index_copy(0, due, flags)

    def _stand_distance(
        self,
        state: SimState,
        ps: IDMState,
        agent: torch.Tensor,
        where: tuple[torch.Tensor, ...],
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(distance to stand [L] m: the nearest of the stop lines that hold the agent and the
        end of its route; stop-sign flags ``sign_flags`` [L, 2, Kt]) of the L agents ``agent``
        (``where`` = (progress m, length m, speed m/s, comfortable deceleration m/s^2), [L]
        each)."""
        cfg = self.config
        progress, length, speed, comfort = where
        row = agent // state.num_agents
        lines = _rows(ps.lines, agent)  # [L, K + 1]: one gather of all that can hold it
        gap = lines - (progress + 0.5 * length).unsqueeze(-1)  # from the front bumper
        line_row = _rows(ps.line_row, agent)
        signal = LINE_COLUMNS["signal"]
        d_signal = signal_distance(
            gap[:, signal], (row, line_row[:, signal]), state.tl_state_now(), speed, comfort
        )
        sign_arc, sign_gap = lines[:, LINE_COLUMNS["sign"]], gap[:, LINE_COLUMNS["sign"]]
        stopped_before, cleared_before = _rows(ps.sign_flags, agent).unbind(1)
        stopped = sign_progress(sign_gap, stopped_before, cleared_before, speed)
        waiting = stopped & ~cleared_before & torch.isfinite(sign_arc)
        others = (state.pose[..., :2], state.speed, state.valid)
        clear = junction_clear(waiting, (ps.route, sign_arc), agent, others, cfg.junction_radius)
        cleared = cleared_before | (waiting & clear)
        d_sign = sign_distance(sign_gap, cleared)
        walker = state.valid & (state.agents.object_type == int(ObjectType.PEDESTRIAN))
        cross_row = line_row[:, signal.stop :]
        used = max(int(cross_row.max()) + 1, 1)  # the polygons these agents' routes cross
        occupied = crosswalks_occupied(
            ps.crosswalks[:, :used], walker.nonzero(as_tuple=True), others[0]
        )
        d_cross = crosswalk_distance(gap[:, LINE_COLUMNS["crosswalk"]], (row, cross_row), occupied)
        stand = torch.minimum(torch.minimum(d_signal, d_sign), d_cross) - cfg.stop_gap
        end = lines[:, LINE_COLUMNS["end"]] - progress
        return torch.minimum(stand, end), torch.stack([stopped, cleared], 1)


__all__ = ["BRANCH_VARIANTS", "IDMPolicy", "IDMState"]
