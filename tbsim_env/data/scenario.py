"""The typed ``Scenario``: one WOMD scenario as numpy arrays, independent of the file format.

Coordinates are the scenario's own frame (metres, the origin is arbitrary per scenario), headings
are wrapped to [-pi, pi). Invalid entries hold zeros and must be masked with ``valid``.
A scenario may hold fewer steps than a WOMD episode: WOSAC test-split scenes log only the history
(11 steps, current step 10). ``Scenario.has_future`` says whether a logged future exists, and
``Scenario.on_time_grid`` puts a scenario on a simulation's time grid (steps past the log are
invalid there), so a simulation's horizon never depends on the log's length.
Every reader (raw TFRecord, GPUDrive JSON, the procedural generator) produces this type and
nothing else, so simulation code never sees a file format.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from tbsim_env.core import constants as C
from tbsim_env.core.constants import DT, MapFeatureType, ObjectType, SignalState
from tbsim_env.core.errors import MissingFutureError, ScenarioFormatError


def wrap_angle_np(angle: np.ndarray) -> np.ndarray:
    """Wrap angles (radians) to [-pi, pi)."""
    return (np.asarray(angle) + np.pi) % (2.0 * np.pi) - np.pi


@dataclass(frozen=True)
class Tracks:
    """All objects of a scenario, A tracks over T steps.

    Attributes:
        id: [A] int64, WOMD ``Track.id`` (unique, non-negative).
        object_type: [A] int8, ``ObjectType`` values.
        xyz: [A, T, 3] float64, box centre in metres.
        heading: [A, T] float32, yaw in radians wrapped to [-pi, pi), CCW from +x.
        velocity: [A, T, 2] float32, (vx, vy) in m/s.
        size: [A, T, 3] float32, (length, width, height) in metres.
        valid: [A, T] bool.
        raw_heading: [A, T] float32 yaw as the source file stores it, before wrapping (WOMD
            headings are often off by whole turns), or None when it equals ``heading``. Only
            the WOSAC metrics read it: the official code uses headings as stored, and its
            time-to-collision compares them unwrapped (docs/metrics.md).
    """

    id: np.ndarray
    object_type: np.ndarray
    xyz: np.ndarray
    heading: np.ndarray
    velocity: np.ndarray
    size: np.ndarray
    valid: np.ndarray
    raw_heading: np.ndarray | None = None

    @property
    def num_tracks(self) -> int:
        return int(self.id.shape[0])

    @property
    def num_steps(self) -> int:
        return int(self.valid.shape[1])

    def stored_heading(self) -> np.ndarray:
        """[A, T] float32 yaw as stored in the source (``raw_heading``, else ``heading``)."""
        return self.heading if self.raw_heading is None else self.raw_heading

    def on_time_grid(self, num_steps: int) -> Tracks:
        """The tracks over ``num_steps`` steps: cut, or extended by invalid zero entries."""
        n = self.num_steps

        def fit(a: np.ndarray | None) -> np.ndarray | None:
            if a is None or num_steps <= n:
                return None if a is None else a[:, :num_steps]
            pad = np.zeros((a.shape[0], num_steps - n, *a.shape[2:]), a.dtype)
            return np.concatenate([a, pad], axis=1)

        fields = ("xyz", "heading", "velocity", "size", "valid", "raw_heading")
        return dataclasses.replace(self, **{f: fit(getattr(self, f)) for f in fields})


@dataclass(frozen=True)
class RoadMap:
    """Static map features, F features (ragged polylines kept as a tuple of arrays).

    Attributes:
        id: [F] int64, ``MapFeature.id``.
        feature_type: [F] int8, ``MapFeatureType``.
        subtype: [F] int8, lane type / road-line type / road-edge type (raw WOMD enum value);
            0 for stop signs and polygons.
        polylines: F arrays [n_i, 3] float64. Lane centre lines, road lines and road edges are
            open polylines; crosswalk, speed bump and driveway are closed polygons (last point
            connects to the first); a stop sign is its single position.
        speed_limit_mph: [F] float32, lanes only (0 elsewhere or when unknown).
        entry_lanes: F int64 arrays, feature ids of predecessor lanes (lanes only).
        exit_lanes: F int64 arrays, feature ids of successor lanes (lanes only).
        left_neighbors: F int64 arrays, ids of left neighbour lanes (lanes only).
        right_neighbors: F int64 arrays, ids of right neighbour lanes (lanes only).
        controlled_lanes: F int64 arrays, lanes a stop sign controls (stop signs only).
    """

    id: np.ndarray
    feature_type: np.ndarray
    subtype: np.ndarray
    polylines: tuple[np.ndarray, ...]
    speed_limit_mph: np.ndarray
    entry_lanes: tuple[np.ndarray, ...]
    exit_lanes: tuple[np.ndarray, ...]
    left_neighbors: tuple[np.ndarray, ...]
    right_neighbors: tuple[np.ndarray, ...]
    controlled_lanes: tuple[np.ndarray, ...]

    @property
    def num_features(self) -> int:
        return int(self.id.shape[0])

    def indices_of(self, kind: MapFeatureType) -> np.ndarray:
        """Indices of the features of one type, in file order."""
        return np.flatnonzero(self.feature_type == int(kind))

    def index_of_id(self) -> dict[int, int]:
        """Map from feature id to feature index."""
        return {int(i): k for k, i in enumerate(self.id)}

    @staticmethod
    def from_polylines(
        ids: np.ndarray | list[int],
        feature_type: np.ndarray | list[int],
        subtype: np.ndarray | list[int],
        polylines: tuple[np.ndarray, ...] | list[np.ndarray],
    ) -> RoadMap:
        """A map of geometry only: no speed limits, lane connectivity or stop-sign lanes.

        Args:
            ids: [F] feature ids; feature_type: [F] ``MapFeatureType``; subtype: [F].
            polylines: F arrays [n_i, 3] float64.
        """
        f = len(ids)
        empty = tuple(np.zeros(0, np.int64) for _ in range(f))
        return RoadMap(
            id=np.asarray(ids, np.int64),
            feature_type=np.asarray(feature_type, np.int8),
            subtype=np.asarray(subtype, np.int8),
            polylines=tuple(polylines),
            speed_limit_mph=np.zeros(f, np.float32),
            entry_lanes=empty,
            exit_lanes=empty,
            left_neighbors=empty,
            right_neighbors=empty,
            controlled_lanes=empty,
        )

    @staticmethod
    def empty() -> RoadMap:
        e: tuple[np.ndarray, ...] = ()
        return RoadMap(
            id=np.zeros(0, np.int64),
            feature_type=np.zeros(0, np.int8),
            subtype=np.zeros(0, np.int8),
            polylines=e,
            speed_limit_mph=np.zeros(0, np.float32),
            entry_lanes=e,
            exit_lanes=e,
            left_neighbors=e,
            right_neighbors=e,
            controlled_lanes=e,
        )


@dataclass(frozen=True)
class TrafficSignals:
    """Traffic-signal lane states, S controlled lanes over T steps.

    One row per unique controlled lane id seen in any step.

    Attributes:
        lane_id: [S] int64, the controlled lane's ``MapFeature.id``.
        state: [S, T] int8, raw ``SignalState`` value (0 where not valid).
        valid: [S, T] bool, whether the lane had a state at that step.
        stop_point: [S, 3] float64, where objects must stop (first valid value).
    """

    lane_id: np.ndarray
    state: np.ndarray
    valid: np.ndarray
    stop_point: np.ndarray

    @property
    def num_signals(self) -> int:
        return int(self.lane_id.shape[0])

    def on_time_grid(self, num_steps: int) -> TrafficSignals:
        """The signals over ``num_steps`` steps: cut, or extended by steps with no state."""
        n = int(self.state.shape[1])
        if num_steps <= n:
            return dataclasses.replace(
                self, state=self.state[:, :num_steps], valid=self.valid[:, :num_steps]
            )
        pad = num_steps - n
        return dataclasses.replace(
            self,
            state=np.pad(self.state, ((0, 0), (0, pad))),
            valid=np.pad(self.valid, ((0, 0), (0, pad))),
        )

    @staticmethod
    def empty(num_steps: int) -> TrafficSignals:
        return TrafficSignals(
            lane_id=np.zeros(0, np.int64),
            state=np.zeros((0, num_steps), np.int8),
            valid=np.zeros((0, num_steps), bool),
            stop_point=np.zeros((0, 3), np.float64),
        )


_STATE_PARTS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("xyz", ("center_x", "center_y", "center_z")),
    ("heading", ("heading",)),
    ("raw_heading", ("heading",)),
    ("velocity", ("velocity_x", "velocity_y")),
    ("size", ("length", "width", "height")),
)
"""Track arrays checked at valid states, with the names of their components."""


def _impossible_state(tracks: Tracks) -> str | None:
    """The first physically impossible value of a valid track state, described, or None.

    Poses and velocities must be finite, positions within ``MAX_ABS_COORDINATE`` of the
    origin, headings as stored within ``MAX_ABS_HEADING``, speeds at most ``MAX_SPEED``, box
    sizes (length, width, height) positive and at most ``MAX_BOX_SIZE`` (constants.py).
    """
    for name, parts in _STATE_PARTS:
        arr = getattr(tracks, name)
        if arr is None:
            continue
        arr = arr if arr.ndim == 3 else arr[..., None]  # [A, T, C]
        valid = tracks.valid[..., None]
        finite = np.isfinite(arr)
        magnitude = np.abs(np.where(finite, arr, 0.0))
        checks = [(valid & ~finite, "is non-finite")]
        if name == "xyz":
            far = magnitude > C.MAX_ABS_COORDINATE
            checks.append((valid & far, f"lies beyond {C.MAX_ABS_COORDINATE:g} m of the origin"))
        elif name == "raw_heading":
            turns = magnitude > C.MAX_ABS_HEADING
            checks.append((valid & turns, f"is beyond {C.MAX_ABS_HEADING:g} rad"))
        elif name == "size":
            checks.append((valid & finite & (arr <= 0), "is not positive (a box needs a size)"))
            big = magnitude > C.MAX_BOX_SIZE
            checks.append((valid & big, f"is larger than {C.MAX_BOX_SIZE:g} m"))
        for bad, what in checks:
            if bad.any():
                k, step, c = (int(i) for i in np.argwhere(bad)[0])
                return (
                    f"track {int(tracks.id[k])} (index {k}) at step {step}: field "
                    f"{parts[c]!r} of a valid state {what}: {float(arr[k, step, c])!r}"
                )
    # Finite components: the norm in float64 cannot overflow.
    speed = np.linalg.norm(tracks.velocity.astype(np.float64), axis=-1)
    fast = tracks.valid & (speed > C.MAX_SPEED)
    if fast.any():
        k, step = (int(i) for i in np.argwhere(fast)[0])
        return (
            f"track {int(tracks.id[k])} (index {k}) at step {step}: the speed of a valid state "
            f"(fields 'velocity_x', 'velocity_y') is {float(speed[k, step]):.6g} m/s, beyond "
            f"{C.MAX_SPEED:g} m/s"
        )
    return None


def _out_of_range(values: np.ndarray, lo: int, hi: int) -> int | None:
    """Index of the first entry of ``values`` outside [lo, hi], or None."""
    bad = (values < lo) | (values > hi)
    return int(np.argmax(bad)) if bad.any() else None


def _scene_extent_problem(scenario: Scenario) -> str | None:
    """Describe a scene wider or higher than ``MAX_SCENE_EXTENT`` (valid track positions and
    map points), naming the two points farthest apart along that axis; None if it fits."""
    t = scenario.tracks
    a_idx, s_idx = np.nonzero(t.valid)
    track_xy = t.xyz[a_idx, s_idx, :2]
    m = scenario.road_map
    sizes = [len(p) for p in m.polylines]
    map_xy = np.concatenate([p[:, :2] for p in m.polylines]) if sizes else np.zeros((0, 2))
    xy = np.concatenate([track_xy, map_xy])
    if xy.shape[0] == 0:
        return None
    span = xy.max(0) - xy.min(0)
    axis = int(np.argmax(span))
    if span[axis] <= C.MAX_SCENE_EXTENT:
        return None
    feature = np.repeat(np.arange(len(sizes)), sizes)

    def label(row: int) -> str:
        if row < track_xy.shape[0]:
            return f"track {int(t.id[a_idx[row]])} at step {int(s_idx[row])}"
        return f"map feature {int(m.id[feature[row - track_xy.shape[0]]])}"

    lo, hi = int(np.argmin(xy[:, axis])), int(np.argmax(xy[:, axis]))
    name = "xy"[axis]
    return (
        f"the scene spans {span[axis]:.6g} m along {name} ({label(lo)} at {name} = "
        f"{xy[lo, axis]:.6g}, {label(hi)} at {name} = {xy[hi, axis]:.6g}); a scene may span at "
        f"most {C.MAX_SCENE_EXTENT:g} m"
    )


@dataclass(frozen=True)
class Scenario:
    """One scenario: tracks, map, signals and the WOMD metadata.

    Attributes:
        scenario_id: WOMD id (16 hex chars) or a generated name.
        timestamps: [T] float64 seconds (not an exact 0.1 s grid in real data).
        current_index: index of the current step (10 in WOMD).
        tracks: all objects.
        road_map: static map.
        signals: traffic-signal states per step.
        sdc_index: index into tracks of the self-driving car.
        tracks_to_predict: [k] int64 track **indices**.
        predict_difficulty: [k] int8 difficulty level per tracks_to_predict entry.
        objects_of_interest: [m] int64 track **ids**.
        source: where it came from (file path, record), for messages.
        logged_steps: steps 0 .. logged_steps - 1 of the time grid come from the log; None
            when all do (every reader). Set by ``on_time_grid`` when it extends the grid past
            the log: the added steps hold no valid track or signal state.
    """

    scenario_id: str
    timestamps: np.ndarray
    current_index: int
    tracks: Tracks
    road_map: RoadMap
    signals: TrafficSignals
    sdc_index: int
    tracks_to_predict: np.ndarray
    predict_difficulty: np.ndarray
    objects_of_interest: np.ndarray
    source: str = field(default="<memory>", compare=False)
    logged_steps: int | None = None

    @property
    def num_steps(self) -> int:
        """T, steps of the time grid (the logged steps for a scenario as read)."""
        return self.tracks.num_steps

    @property
    def num_logged_steps(self) -> int:
        """Steps that come from the log (91 in WOMD training/validation, 11 in its test split)."""
        return self.num_steps if self.logged_steps is None else self.logged_steps

    @property
    def num_future_steps(self) -> int:
        """Logged steps after the current one (80 in a full WOMD scene, 0 if history only)."""
        return max(self.num_logged_steps - 1 - self.current_index, 0)

    @property
    def has_future(self) -> bool:
        """The log goes on after the current step (False for WOSAC test-split scenes)."""
        return self.num_future_steps > 0

    def require_log_until(self, step: int, task: str) -> None:
        """Raise ``MissingFutureError`` unless the log holds steps up to ``step``.

        The one check of everything that needs logged states (log replay, scoring against the
        log, training targets); the message names the scenario, its source and ``task``.
        """
        if step >= self.num_logged_steps:
            raise MissingFutureError(
                self.scenario_id,
                self.source,
                task,
                int(step),
                self.num_logged_steps,
                self.current_index,
            )

    def on_time_grid(self, num_steps: int) -> Scenario:
        """This scenario over exactly ``num_steps`` steps (the time grid of a simulation).

        Steps after the log are appended with no valid track or signal state (zero
        placeholders; timestamps go on every ``DT``) and ``logged_steps`` remembers where the
        log ends, so ``has_future`` stays what it was. A longer log is cut. Returns ``self``
        when the grid is the scenario's own.

        Args:
            num_steps: T of the grid, more than the current index.
        """
        if num_steps == self.num_steps:
            return self
        if num_steps <= self.current_index:
            raise ValueError(
                f"scenario {self.scenario_id!r}: a time grid of {num_steps} steps leaves out "
                f"the current step {self.current_index}"
            )
        n = min(self.num_steps, num_steps)
        ts = self.timestamps[:n]
        if num_steps > n:
            ts = np.concatenate([ts, ts[-1] + DT * np.arange(1, num_steps - n + 1)])
        logged = min(self.num_logged_steps, num_steps)
        return self.replace(
            timestamps=ts,
            tracks=self.tracks.on_time_grid(num_steps),
            signals=self.signals.on_time_grid(num_steps),
            logged_steps=None if logged == num_steps else logged,
        )

    def motion_window(self) -> Scenario:
        """This scenario within WOMD's motion window: a scene logged beyond the
        ``NUM_FUTURE`` steps after the current one (WOMD's 20 s scenes, ScenarioNet
        conversions of them) is cut to its first ``current + 1 + NUM_FUTURE`` steps, as WOSAC
        scores it and as TrafficBots trains on it; a shorter one is returned as it is."""
        end = self.current_index + 1 + C.NUM_FUTURE
        return self.on_time_grid(end) if self.num_steps > end else self

    @property
    def sdc_id(self) -> int:
        return int(self.tracks.id[self.sdc_index])

    def replace(self, **changes) -> Scenario:
        return dataclasses.replace(self, **changes)

    def transformed(self, yaw: float = 0.0, shift: tuple[float, float] = (0.0, 0.0)) -> Scenario:
        """The scenario rotated by ``yaw`` (rad) about (0, 0), then moved by ``shift`` (x, y
        metres): tracks at valid steps (positions, headings, velocities), every map polyline
        and the signal stop points. Invalid track steps keep their placeholder values."""
        c, s = np.cos(yaw), np.sin(yaw)

        def rotate(xy: np.ndarray) -> np.ndarray:
            """[..., >=2] float64 copy with x, y rotated (other columns kept)."""
            out = np.array(xy, np.float64, copy=True)
            if yaw:
                out[..., 0] = c * xy[..., 0] - s * xy[..., 1]
                out[..., 1] = s * xy[..., 0] + c * xy[..., 1]
            return out

        def move(xyz: np.ndarray) -> np.ndarray:
            out = rotate(xyz)
            out[..., 0] += shift[0]
            out[..., 1] += shift[1]
            return out

        t = self.tracks
        ok = t.valid
        changes = {"xyz": np.where(ok[..., None], move(t.xyz), t.xyz)}
        if yaw:
            vel = np.where(ok[..., None], rotate(t.velocity), t.velocity)
            heading = np.where(ok, wrap_angle_np(t.heading.astype(np.float64) + yaw), t.heading)
            changes.update(velocity=vel.astype(np.float32), heading=heading.astype(np.float32))
            if t.raw_heading is not None:
                raw = np.where(ok, t.raw_heading.astype(np.float64) + yaw, t.raw_heading)
                changes.update(raw_heading=raw.astype(np.float32))
        m = self.road_map
        road_map = dataclasses.replace(m, polylines=tuple(move(p) for p in m.polylines))
        sig = dataclasses.replace(self.signals, stop_point=move(self.signals.stop_point))
        return self.replace(
            tracks=dataclasses.replace(t, **changes), road_map=road_map, signals=sig
        )

    def sim_agent_mask(self) -> np.ndarray:
        """[A] bool: the sim agents, the tracks valid at the current step (what WOSAC
        simulates and a submission must hold, and what the environments start with)."""
        return self.tracks.valid[:, self.current_index].copy()

    def sim_agent_indices(self) -> np.ndarray:
        """[K] int64 track indices of the sim agents (``sim_agent_mask``), in track order."""
        return np.flatnonzero(self.sim_agent_mask()).astype(np.int64)

    def role_mask(self) -> np.ndarray:
        """[A, 3] bool: (is SDC, in objects_of_interest, in tracks_to_predict)."""
        a = self.tracks.num_tracks
        role = np.zeros((a, 3), bool)
        role[self.sdc_index, 0] = True
        role[:, 1] = np.isin(self.tracks.id, self.objects_of_interest)
        role[self.tracks_to_predict, 2] = True
        return role

    def validate(self) -> Scenario:
        """Check shapes, dtypes, cross references and plausibility; raise
        ``ScenarioFormatError`` naming the track or feature, step and field at fault.

        The plausibility bounds (units and reasons in ``tbsim_env.core.constants``, section
        "plausibility"): valid track states finite, within ``MAX_ABS_COORDINATE``, speeds up to
        ``MAX_SPEED``, boxes positive and up to ``MAX_BOX_SIZE``, stored headings within
        ``MAX_ABS_HEADING``; the scene within ``MAX_SCENE_EXTENT``; ids in their proto ranges
        (track ids ``[0, MAX_TRACK_ID]``, map and signal lane ids ``[0, MAX_FEATURE_ID]``, map
        ids unique), difficulties 0-2, signal states 0-8 with finite stop points; timestamps
        finite and increasing; the current step among the steps with a track valid at it.

        Returns self so that readers can ``return Scenario(...).validate()``.
        """

        def fail(msg: str) -> None:
            raise ScenarioFormatError(f"scenario {self.scenario_id!r}: {msg}", path=self.source)

        t = self.tracks
        if t.num_tracks == 0:
            fail("field 'tracks' is empty (a scenario needs at least one track)")
        n_t = self.timestamps.shape[0]
        self._validate_timestamps(fail)
        a = t.num_tracks
        expect = {
            "id": (a,),
            "object_type": (a,),
            "xyz": (a, n_t, 3),
            "heading": (a, n_t),
            "velocity": (a, n_t, 2),
            "size": (a, n_t, 3),
            "valid": (a, n_t),
        }
        for name, shape in expect.items():
            got = getattr(t, name).shape
            if got != shape:
                fail(f"track field {name!r} has shape {got}, expected {shape}")
        if t.valid.dtype != bool:
            fail("track field 'valid' must be bool")
        bad = _out_of_range(t.id, 0, C.MAX_TRACK_ID)
        if bad is not None:
            fail(f"track index {bad}: id {int(t.id[bad])} outside [0, {C.MAX_TRACK_ID}]")
        if len(np.unique(t.id)) != a:
            fail("track ids ('Track.id') are not unique")
        bad_type = ~np.isin(t.object_type, [int(x) for x in ObjectType])
        if bad_type.any():
            fail(f"track {int(t.id[np.argmax(bad_type)])}: unknown 'object_type'")
        if t.raw_heading is not None and t.raw_heading.shape != (a, n_t):
            fail(f"track field 'raw_heading' has shape {t.raw_heading.shape}, expected {(a, n_t)}")
        impossible = _impossible_state(t)
        if impossible:
            fail(impossible)
        if not 0 <= self.current_index < n_t:
            fail(
                f"'current_time_index' {self.current_index} is not among the {n_t} steps "
                "(a scenario needs at least its current step)"
            )
        if not self.sim_agent_mask().any():
            fail(
                f"no track is valid at the current step {self.current_index} "
                "('current_time_index'): nothing to simulate"
            )
        if self.logged_steps is not None:
            if not self.current_index < self.logged_steps <= n_t:
                fail(f"'logged_steps' {self.logged_steps} outside ({self.current_index}, {n_t}]")
            after = slice(self.logged_steps, None)
            if t.valid[:, after].any() or self.signals.valid[:, after].any():
                fail(f"a track or signal is valid after the log's end (step {self.logged_steps})")
        if not 0 <= self.sdc_index < a:
            fail(f"'sdc_track_index' {self.sdc_index} outside [0, {a})")
        self._validate_roles(fail)
        self._validate_map(fail)
        self._validate_signals(fail, n_t)
        extent = _scene_extent_problem(self)
        if extent:
            fail(extent)
        return self

    def _validate_timestamps(self, fail) -> None:
        """At least two steps, finite and increasing."""
        n_t = self.timestamps.shape[0]
        if n_t < 2:
            fail(f"field 'timestamps_seconds' has {n_t} entries; need at least 2 steps")
        if not np.isfinite(self.timestamps).all():
            fail("field 'timestamps_seconds' has a non-finite value")
        if not (np.diff(self.timestamps) > 0).all():
            step = int(np.argmax(np.diff(self.timestamps) <= 0)) + 1
            fail(f"field 'timestamps_seconds' is not increasing at step {step}")

    def _validate_roles(self, fail) -> None:
        """Tracks to predict, their difficulties and the objects of interest."""
        a = self.tracks.num_tracks
        ttp = self.tracks_to_predict
        bad = _out_of_range(ttp, 0, a - 1)
        if bad is not None:
            fail(
                f"'tracks_to_predict' entry {bad}: track_index {int(ttp[bad])} outside the "
                f"track list [0, {a})"
            )
        if self.predict_difficulty.shape != ttp.shape:
            fail(
                f"'tracks_to_predict' has {ttp.shape[0]} entries but "
                f"{self.predict_difficulty.shape[0]} difficulties"
            )
        bad = _out_of_range(self.predict_difficulty, 0, C.NUM_DIFFICULTY_LEVELS - 1)
        if bad is not None:
            fail(
                f"'tracks_to_predict' entry {bad}: difficulty {int(self.predict_difficulty[bad])}"
                f" outside [0, {C.NUM_DIFFICULTY_LEVELS - 1}]"
            )
        bad = _out_of_range(self.objects_of_interest, 0, C.MAX_TRACK_ID)
        if bad is not None:
            fail(
                f"'objects_of_interest' entry {bad}: id {int(self.objects_of_interest[bad])} "
                f"outside [0, {C.MAX_TRACK_ID}]"
            )

    def _validate_map(self, fail) -> None:
        """Map shapes, ids, polylines and speed limits."""
        m = self.road_map
        f = m.num_features
        for name in ("id", "feature_type", "subtype", "speed_limit_mph"):
            if getattr(m, name).shape != (f,):
                fail(f"map field {name!r} has shape {getattr(m, name).shape}, expected ({f},)")
        for name in (
            "polylines",
            "entry_lanes",
            "exit_lanes",
            "left_neighbors",
            "right_neighbors",
            "controlled_lanes",
        ):
            if len(getattr(m, name)) != f:
                fail(f"map field {name!r} has {len(getattr(m, name))} entries, expected {f}")
        bad = _out_of_range(m.id, 0, C.MAX_FEATURE_ID)
        if bad is not None:
            fail(f"map feature index {bad}: id {int(m.id[bad])} outside [0, {C.MAX_FEATURE_ID}]")
        ids, first, counts = np.unique(m.id, return_index=True, return_counts=True)
        if (counts > 1).any():
            k = int(np.argmax(counts > 1))
            fail(
                f"map feature id {int(ids[k])} is used by {int(counts[k])} features (the "
                f"first at index {int(first[k])}); map feature ids must be unique"
            )
        bad_type = ~np.isin(m.feature_type, [int(x) for x in MapFeatureType])
        if bad_type.any():
            fail(f"map feature {int(m.id[np.argmax(bad_type)])}: unknown feature type")
        for k, pl in enumerate(m.polylines):
            if pl.ndim != 2 or pl.shape[1] != 3 or pl.shape[0] == 0:
                fail(f"map feature {int(m.id[k])}: polyline has shape {pl.shape}")
            if not np.isfinite(pl).all():
                fail(f"map feature {int(m.id[k])}: polyline has a non-finite point")
            if np.abs(pl).max() > C.MAX_ABS_COORDINATE:
                fail(
                    f"map feature {int(m.id[k])}: polyline has a point beyond "
                    f"{C.MAX_ABS_COORDINATE:g} m of the origin ({np.abs(pl).max():.6g} m)"
                )
        limit = m.speed_limit_mph
        bad_limit = ~np.isfinite(limit) | (limit < 0)
        if bad_limit.any():
            k = int(np.argmax(bad_limit))
            fail(f"map feature {int(m.id[k])}: 'speed_limit_mph' is {float(limit[k])!r}")

    def _validate_signals(self, fail, n_t: int) -> None:
        """Signal shapes, lane ids, states and stop points."""
        s = self.signals
        n = s.num_signals
        if s.state.shape != (n, n_t) or s.valid.shape != (n, n_t):
            fail("traffic-signal arrays do not match (num_signals, num_steps)")
        if s.stop_point.shape != (n, 3):
            fail(f"traffic-signal 'stop_point' has shape {s.stop_point.shape}, expected ({n}, 3)")
        bad = _out_of_range(s.lane_id, 0, C.MAX_FEATURE_ID)
        if bad is not None:
            fail(f"traffic signal {bad}: lane id {int(s.lane_id[bad])} is negative")
        if len(np.unique(s.lane_id)) != n:
            fail("traffic signals: a lane id has two rows")
        bad_state = s.valid & ((s.state < 0) | (s.state >= len(SignalState)))
        if bad_state.any():
            k, step = (int(i) for i in np.argwhere(bad_state)[0])
            fail(
                f"traffic signal of lane {int(s.lane_id[k])} at step {step}: unknown state "
                f"{int(s.state[k, step])}"
            )
        finite = np.isfinite(s.stop_point)
        far = np.abs(np.where(finite, s.stop_point, 0.0)) > C.MAX_ABS_COORDINATE
        if (~finite | far).any():
            k, c = (int(i) for i in np.argwhere(~finite | far)[0])
            fail(
                f"traffic signal of lane {int(s.lane_id[k])}: 'stop_point' {'xyz'[c]} is "
                f"{float(s.stop_point[k, c])!r}; it must be finite and within "
                f"{C.MAX_ABS_COORDINATE:g} m of the origin"
            )
