"""Rules shared by the readers of converted WOMD scenes (ScenarioNet pickles, WOMD tf.Example
records, the GPUDrive / Nocturne JSON dialects): one implementation of each.

* Signal state names: ``"LANE_STATE_STOP"``, ``"stop"``, ``"arrow_go"`` ... -> ``SignalState``.
* Traffic signals from (step, lane id, state, stop point) entries -> ``TrafficSignals``.
* Roles of scenes whose file marks none (``choose_sdc``, ``choose_tracks_to_predict``): the
  rule of the WOSAC reference conversion (data/womd/wosac_reference/README.md), which marked
  the vehicle valid at every step nearest the centre of the map as SDC and, as tracks to
  predict, up to 8 other objects valid from the current step on whose path from there is the
  longest, over 2 m. "From the current step on" means the WOSAC horizon, the current step and
  the ``NUM_FUTURE`` (80) after it, so that 20 s scenes are judged like 9 s ones.
"""

from __future__ import annotations

import numpy as np

from tbsim_env.core.constants import NUM_FUTURE, ObjectType, SignalState
from tbsim_env.data.scenario import RoadMap, Tracks, TrafficSignals

MAX_CHOSEN_TRACKS_TO_PREDICT = 8
"""Most tracks to predict ``choose_tracks_to_predict`` marks (WOMD marks up to 8)."""
MIN_CHOSEN_PATH_M = 2.0
"""Metres. Shortest path (current step to last) of a track ``choose_tracks_to_predict`` marks."""
DEFAULT_BOX_HEIGHT_M = 1.5
"""Metres. Box height of objects whose source stores none (Nocturne JSON), as in the WOSAC
reference conversion of a Nocturne scene."""
TYPICAL_BOX_SIZE_M: dict[int, tuple[float, float]] = {
    int(ObjectType.VEHICLE): (4.64, 2.06),
    int(ObjectType.PEDESTRIAN): (0.88, 0.84),
    int(ObjectType.CYCLIST): (1.90, 0.86),
}
"""Metres, (length, width) per ``ObjectType``: the median per-track size of each type over the
43 ScenarioNet scenes (2,768 vehicles, 248 pedestrians, 22 cyclists). Used for objects whose
file records no size (``fill_unknown_sizes``); other types take the vehicle's."""

_STATE_PREFIX = "lane_state_"


def signal_state_from_name(name: object) -> SignalState | None:
    """``SignalState`` of a state name, or None when the name is not one.

    Accepts the WOMD enum names with or without the ``LANE_STATE_`` prefix, in any case
    (ScenarioNet writes ``"LANE_STATE_ARROW_GO"``, the JSON dialects ``"arrow_go"``).
    """
    if not isinstance(name, str):
        return None
    key = name.strip().lower()
    key = key[len(_STATE_PREFIX) :] if key.startswith(_STATE_PREFIX) else key
    try:
        return SignalState[key.upper()]
    except KeyError:
        return None


def signals_from_entries(
    step: np.ndarray,
    lane: np.ndarray,
    state: np.ndarray,
    stop_point: np.ndarray,
    num_steps: int,
) -> TrafficSignals:
    """``TrafficSignals`` with one row per lane id, from N observed (step, lane) states.

    Args:
        step: [N] int step index in [0, num_steps).
        lane: [N] int64 controlled lane id.
        state: [N] int raw ``SignalState`` value.
        stop_point: [N, 3] float64 stop point at that step; the row keeps the lane's first.
        num_steps: T.

    Returns:
        Rows sorted by lane id; a later entry for the same (lane, step) overrides an earlier.
    """
    if len(lane) == 0:
        return TrafficSignals.empty(num_steps)
    lane_id, row = np.unique(np.asarray(lane, np.int64), return_inverse=True)
    n = lane_id.shape[0]
    out_state = np.zeros((n, num_steps), np.int8)
    valid = np.zeros((n, num_steps), bool)
    out_state[row, step] = state
    valid[row, step] = True
    order = np.lexsort((np.asarray(step), row))  # per lane, by step
    first = order[np.unique(row[order], return_index=True)[1]]
    stops = np.zeros((n, 3), np.float64)
    stops[row[first]] = np.asarray(stop_point, np.float64).reshape(-1, 3)[first]
    return TrafficSignals(lane_id=lane_id, state=out_state, valid=valid, stop_point=stops)


def fill_unknown_sizes(size: np.ndarray, object_type: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Give objects stored with length = width = 0 (size not recorded) the typical size.

    The older Nocturne conversion writes 0 for both for some objects valid at many steps
    (data/womd/nocturne: 58 objects in its 3 files); any other non-positive size is left for
    ``Scenario.validate`` to refuse.

    Args:
        size: [A, 3] float64 (length, width, height) metres, one box per object.
        object_type: [A] ``ObjectType`` values.

    Returns:
        (the sizes with length and width filled from ``TYPICAL_BOX_SIZE_M``, [A] bool mask of
        the filled objects).
    """
    unknown = (size[:, 0] == 0.0) & (size[:, 1] == 0.0)
    if not unknown.any():
        return size, unknown
    vehicle = TYPICAL_BOX_SIZE_M[int(ObjectType.VEHICLE)]
    typical = np.array([TYPICAL_BOX_SIZE_M.get(int(t), vehicle) for t in object_type])
    out = size.copy()
    out[unknown, :2] = typical[unknown]
    return out, unknown


def map_centre(road_map: RoadMap, tracks: Tracks) -> np.ndarray:
    """[2] float64 centre of the bounding box of every map point (x, y), metres.

    Without map features: the centre of the box of every valid track position.
    """
    if road_map.num_features:
        pts = np.concatenate([p[:, :2] for p in road_map.polylines])
    else:
        pts = tracks.xyz[..., :2][tracks.valid]
    if pts.shape[0] == 0:
        return np.zeros(2)
    return (pts.min(axis=0) + pts.max(axis=0)) / 2.0


def choose_sdc(tracks: Tracks, road_map: RoadMap, current_index: int) -> int:
    """Index of the track to mark as SDC in a scene whose file marks none.

    The vehicle valid at every step whose position at the current step is nearest the map
    centre (``map_centre``); with no such vehicle, the vehicle valid at the current step
    nearest it; then any track valid at the current step; then track 0. Ties: lowest index.

    Args:
        tracks: A tracks over T steps.
        road_map: the scene's map (for its centre).
        current_index: the current step.
    """
    centre = map_centre(road_map, tracks)
    dist = np.linalg.norm(tracks.xyz[:, current_index, :2] - centre, axis=-1)
    vehicle = tracks.object_type == int(ObjectType.VEHICLE)
    now = tracks.valid[:, current_index]
    for candidates in (vehicle & tracks.valid.all(axis=1), vehicle & now, now):
        if candidates.any():
            return int(np.argmin(np.where(candidates, dist, np.inf)))
    return 0


def path_length(tracks: Tracks, start: int, stop: int) -> np.ndarray:
    """[A] float64 metres travelled from step ``start`` to step ``stop - 1`` (valid pairs)."""
    xy = tracks.xyz[:, start:stop, :2]
    valid = tracks.valid[:, start:stop]
    step = np.linalg.norm(np.diff(xy, axis=1), axis=-1)
    return np.where(valid[:, 1:] & valid[:, :-1], step, 0.0).sum(axis=1)


def choose_tracks_to_predict(tracks: Tracks, sdc_index: int, current_index: int) -> np.ndarray:
    """[k] int64 indices of the tracks to predict in a scene whose file marks none.

    Up to ``MAX_CHOSEN_TRACKS_TO_PREDICT`` tracks other than the SDC that are valid at every
    step of the horizon (the current step and the ``NUM_FUTURE`` after it, as far as the log
    goes) and travel more than ``MIN_CHOSEN_PATH_M`` over it, longest path first (ties: lowest
    index).
    """
    stop = min(current_index + NUM_FUTURE + 1, tracks.num_steps)
    length = path_length(tracks, current_index, stop)
    ok = tracks.valid[:, current_index:stop].all(axis=1) & (length > MIN_CHOSEN_PATH_M)
    ok[sdc_index] = False
    idx = np.flatnonzero(ok)
    order = np.argsort(-length[idx], kind="stable")
    return idx[order][:MAX_CHOSEN_TRACKS_TO_PREDICT].astype(np.int64)
