"""Typed simulator state: frozen dataclasses of batched tensors with ``valid`` masks beside them.

Shapes: B scenarios, N agent slots (all tracks of a scenario, padded to the largest scenario in
the batch), T log steps, S traffic-signal lanes, E road-edge segments.
Positions are in each scenario's frame shifted by ``origin`` (no rotation), float32 metres.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import torch


@dataclass(frozen=True)
class AgentInfo:
    """Static per-agent attributes.

    Attributes:
        track_id: [B, N] int64, WOMD track id (-1 for padding).
        track_index: [B, N] int64, row in ``Scenario.tracks`` (-1 for padding).
        object_type: [B, N] int64, ``ObjectType``.
        size: [B, N, 3] float32, (length, width, height) m, at the current step (or last valid).
        role: [B, N, 3] bool, (is SDC, object of interest, track to predict).
        mask: [B, N] bool, False for padding slots.
        action_limit: [B, N, 2] float32 (max |acceleration| m/s^2, max |yaw rate| rad/s) of the
            object type; derived from ``object_type`` when not given.
    """

    track_id: torch.Tensor
    track_index: torch.Tensor
    object_type: torch.Tensor
    size: torch.Tensor
    role: torch.Tensor
    mask: torch.Tensor
    action_limit: torch.Tensor | None = field(default=None)

    def __post_init__(self) -> None:
        if self.action_limit is None:
            from tbsim_env.sim.dynamics import action_limits

            limit = torch.stack(action_limits(self.object_type), dim=-1)
            object.__setattr__(self, "action_limit", limit)


@dataclass(frozen=True, eq=False)
class Shared:
    """A table of K scenarios that batch rows read through a row map (``CellLists.row``,
    ``LogTrajectory.row``).

    Row operations (``tbsim_env.observation.rows``) pass it through instead of splitting it:
    rows of one bank share its tables, so starting a new episode in a row copies none of them
    (a road-edge grid is megabytes per scenario).

    Attributes:
        value: [K, ...] tensor.
    """

    value: torch.Tensor


@dataclass(frozen=True)
class LogTrajectory:
    """The logged trajectories of every agent slot: per-scenario tables (``Shared``, K rows)
    that batch rows read through ``row``, so that starting a new episode in a row, or
    repeating a row for rollouts, copies none of them (about 1.2 MB per real scenario).

    Attributes:
        pose: Shared [K, N, T, 3] float32 (x m, y m, yaw rad wrapped).
        speed: Shared [K, N, T] float32 signed speed m/s.
        velocity: Shared [K, N, T, 2] float32 m/s.
        z: Shared [K, N, T] float32 box-centre height m.
        valid: Shared [K, N, T] bool.
        by_step: Shared [K, T, N, 5] float32, what a simulation step reads of the log,
            time-major (x, y, yaw, speed, valid as 0 / 1): one contiguous block per scenario
            and step, so that reading step t of every row is one ``index_select``.
        first_valid: [B, N] int64, first step the agent is valid (T if never).
        row: [B] int64, each batch row's row of the tables.
        row_steps: [B] int64, ``row * T``: the row's first block of the flattened
            ``by_step`` [K T, N, 5].

    ``LogTrajectory.of_tables`` makes one from [K, ...] tensors (batch row k reads row k);
    ``take`` gives a table's rows of the batch.
    """

    pose: Shared
    speed: Shared
    velocity: Shared
    z: Shared
    valid: Shared
    by_step: Shared
    first_valid: torch.Tensor
    row: torch.Tensor
    row_steps: torch.Tensor

    @classmethod
    def of_tables(
        cls,
        pose: torch.Tensor,
        speed: torch.Tensor,
        velocity: torch.Tensor,
        z: torch.Tensor,
        valid: torch.Tensor,
    ) -> LogTrajectory:
        """The log of K scenarios from their [K, N, T, ...] tensors (as the attributes'),
        batch row k reading table row k; ``by_step`` and ``first_valid`` derived."""
        k, n_t = valid.shape[0], valid.shape[-1]
        cols = [pose, speed[..., None], valid[..., None].to(pose.dtype)]
        steps = torch.arange(n_t, device=valid.device)
        first = torch.where(valid, steps, n_t).amin(-1)
        row = torch.arange(k, device=valid.device)
        return cls(
            pose=Shared(pose),
            speed=Shared(speed),
            velocity=Shared(velocity),
            z=Shared(z),
            valid=Shared(valid),
            by_step=Shared(torch.cat(cols, -1).transpose(1, 2).contiguous()),
            first_valid=first.long(),
            row=row,
            row_steps=row * n_t,
        )

    @property
    def num_steps(self) -> int:
        """T, the log's steps."""
        return int(self.valid.value.shape[-1])

    def of_slots(
        self, name: str, slots: torch.Tensor, steps: torch.Tensor | None = None
    ) -> torch.Tensor:
        """The table ``name`` (as ``take``'s) at the agent slots ``slots`` [B, S] of each
        batch row, every step ([B, S, T, ...]) or the steps ``steps`` (broadcastable with
        ``slots``: [B, S, ...])."""
        table, row = getattr(self, name).value, self.row[:, None]
        return table[row, slots] if steps is None else table[row, slots, steps]

    def take(self, name: str) -> torch.Tensor:
        """[B, ...] the table ``name`` (``pose``, ``speed``, ``velocity``, ``z``, ``valid``,
        ``by_step``) of every batch row: a gathered copy (for code off the hot path)."""
        return getattr(self, name).value.index_select(0, self.row)


@dataclass(frozen=True)
class SignalLog:
    """Traffic-signal lane states from the log.

    Attributes:
        lane_id: [B, S] int64 controlled lane id (-1 padding).
        state: [B, S, T] int64 ``TLState`` (5 classes).
        valid: [B, S, T] bool.
        stop_point: [B, S, 2] float32 m.
    """

    lane_id: torch.Tensor
    state: torch.Tensor
    valid: torch.Tensor
    stop_point: torch.Tensor


@dataclass(frozen=True)
class CellLists:
    """A uniform grid over each of B scenarios whose cells list the targets nearest to their
    centre (``tbsim_env.sim.edge_grid``): road-edge segments (``EdgeGrid``) or map pieces
    (``map_knn.PieceGrid``). Padded to the largest grid; the large per-cell tables are
    ``Shared`` by the rows of a bank.

    A query point p in (or clamped to) a cell with centre c has no unlisted target nearer than
    ``bound - |p - c|`` (triangle inequality).

    Attributes:
        cell: [B, 1, 1] float32, cell size (m).
        lower: [B, 2] float32, the grid's lower-left corner (m, state frame).
        shape: [B, 2] int64, cells along x and y (at least 1 each).
        row: [B] int64, each batch row's row of the shared tables.
        cells: Shared [K, G, Cc] int32, per cell (x-major: ``ix * shape_y + iy``) the indices
            of its Cc targets nearest to the centre, nearest first (padding: see the subclass).
        bound: Shared [K, G] float32, distance from the cell centre of the nearest target not
            listed (inf when every target is listed), less a rounding slack.
        center: Shared [K, G, 2] float32, cell centres.
        corner: [B, 1, 2] float32, ``lower`` shaped for a lookup (derived, as the rest).
        last: [B, 1, 2] float32, the last cell index along x and y (``shape - 1``).
        stride: [B, 1, 2] float32, (``shape_y``, 1): a cell's flat index is ``ij . stride``.
        row_cells: [B, 1] int64, ``row * G``: the row's first cell in the flattened tables.
        cell_info: Shared [K, G, 3] float32, (centre x, centre y, bound) per cell: what a
            lookup reads of its cell, in one gather.
    """

    cell: torch.Tensor
    lower: torch.Tensor
    shape: torch.Tensor
    row: torch.Tensor
    cells: Shared
    bound: Shared
    center: Shared
    corner: torch.Tensor
    last: torch.Tensor
    stride: torch.Tensor
    row_cells: torch.Tensor
    cell_info: Shared


@dataclass(frozen=True)
class EdgeGrid(CellLists):
    """``CellLists`` of road-edge segments (the off-road check's lookup); padding entries of
    ``cells`` repeat the last real one.

    Attributes:
        segments: Shared [K, 5, E] float32, the road-edge segments as a lookup reads them,
            a column each: start x, start y, (end - start) x, (end - start) y, squared
            length clamped to >= 1e-12 m^2; in the order of the rows of their ``RoadEdges``.
        row_columns: [B, 1, 1] int64, ``row * 5 E``: the row's first entry of the flattened
            ``segments``.
        has_edge: [B, 1] bool, the row's scene has a road edge.
        joints: optional Shared [K, 3 E, 9] float32, what the side rule at polyline joints
            (``joint_sign``) reads of a segment s, per case k of its projection parameter t
            (row ``3 s + k``; k = 0: t < 0, 1: 0 <= t <= 1, 2: t > 1): s's (start x, start y,
            vector y, vector x), the same of the segment it meets there (the previous one
            for k = 0, the next one for k = 2; s itself for k = 1 or where it meets none),
            and +1 where the two make a convex turn (the side is the max of theirs), else -1
            (the min). None: the lookup gathers both segments and decides per step.
        row_joints: [B, 1] int64, ``row * 3 E``.
    """

    segments: Shared
    row_columns: torch.Tensor
    has_edge: torch.Tensor
    joints: Shared | None = None
    row_joints: torch.Tensor | None = None


@dataclass(frozen=True)
class RoadEdges:
    """Road-edge segments for off-road checks; the road lies on the LEFT of each segment.

    Attributes:
        start: [B, E, 2] float32 segment start m.
        end: [B, E, 2] float32 segment end m.
        valid: [B, E] bool.
        prev_index: [B, E] int64, index of the previous segment of the same polyline
            (wrapping for closed polylines), or the segment itself when there is none.
        next_index: [B, E] int64, likewise for the next segment.
        grid: the segments bucketed by a grid for the per-step lookup (None: every query
            scans every segment).
    """

    start: torch.Tensor
    end: torch.Tensor
    valid: torch.Tensor
    prev_index: torch.Tensor
    next_index: torch.Tensor
    grid: EdgeGrid | None = None


@dataclass(frozen=True)
class SimState:
    """Everything that changes in a rollout plus the static context it needs.

    Attributes:
        step: [B] int64 index of the current step in the log time grid.
        pose: [B, N, 3] float32 current (x, y, yaw).
        speed: [B, N] float32 current signed speed m/s.
        valid: [B, N] bool, the agent is present in the simulation now. Once an agent
            leaves (log invalid while replayed, or removed) it never comes back.
        controlled: [B, N] bool, the agent is driven by actions (not replayed from the log).
        agents: static attributes.
        log: logged trajectories.
        signals: logged traffic-signal states.
        road_edges: road-edge segments.
        origin: [B, 2] float64, scenario-frame xy of this state's (0, 0).
    """

    step: torch.Tensor
    pose: torch.Tensor
    speed: torch.Tensor
    valid: torch.Tensor
    controlled: torch.Tensor
    agents: AgentInfo
    log: LogTrajectory
    signals: SignalLog
    road_edges: RoadEdges
    origin: torch.Tensor

    @property
    def batch_size(self) -> int:
        return int(self.pose.shape[0])

    @property
    def num_agents(self) -> int:
        return int(self.pose.shape[1])

    @property
    def device(self) -> torch.device:
        return self.pose.device

    def replace(self, **changes) -> SimState:
        """A copy with ``changes`` (field name: value), like ``dataclasses.replace``.

        Copies the instance dictionary instead of calling ``__init__`` (a step replaces the
        state once or twice; ``dataclasses.replace`` costs more than several tensor ops).
        """
        unknown = changes.keys() - _SIM_STATE_FIELDS
        if unknown:
            raise TypeError(f"SimState has no field(s) {sorted(unknown)}")
        new = object.__new__(SimState)
        new.__dict__.update(self.__dict__)
        new.__dict__.update(changes)
        return new

    def tl_state_now(self) -> tuple[torch.Tensor, torch.Tensor]:
        """([B, S] TLState, [B, S] valid) at the current step."""
        idx = self.step.clamp(0, self.signals.state.shape[-1] - 1)[:, None, None]
        idx = idx.expand(-1, self.signals.state.shape[1], 1)
        return (
            self.signals.state.gather(2, idx)[..., 0],
            self.signals.valid.gather(2, idx)[..., 0],
        )


_SIM_STATE_FIELDS = frozenset(f.name for f in dataclasses.fields(SimState))
