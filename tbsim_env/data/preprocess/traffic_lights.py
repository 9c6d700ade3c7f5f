"""Traffic-light tokens: one per kept piece of each controlled lane.

docs/model.md §1.3, lane mode.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from tbsim_env.core.config import TokenConfig
from tbsim_env.core.constants import SIGNAL_TO_TL_STATE
from tbsim_env.data.preprocess.map_filter import min_distance
from tbsim_env.data.preprocess.map_pieces import LANE_CLASSES, MapPieces
from tbsim_env.data.scenario import TrafficSignals

_STATE_TABLE = np.asarray(SIGNAL_TO_TL_STATE, np.int64)


@dataclass(frozen=True)
class TrafficLightTokens:
    """Traffic-light tokens, L rows over T steps, unpadded.

    Attributes:
        piece: [L] int64, row of the controlled lane piece in the (kept) map pieces.
        state: [L, T] int64, ``TLState`` value, UNKNOWN where not valid.
        valid: [L, T] bool.
        signal: [L] int64, row in ``TrafficSignals`` the token comes from.
    """

    piece: np.ndarray
    state: np.ndarray
    valid: np.ndarray
    signal: np.ndarray

    @property
    def num_tokens(self) -> int:
        return int(self.piece.shape[0])


def map_signal_states(raw_state: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Raw WOMD signal states -> the 5 ``TLState`` classes, UNKNOWN where not valid.

    Raw values outside 0..8 (not in the WOMD enum) also become UNKNOWN.

    Args:
        raw_state: [...] int, ``SignalState`` values.
        valid: [...] bool.

    Returns:
        [...] int64 ``TLState`` values.
    """
    raw = np.asarray(raw_state, np.int64)
    known = valid & (raw >= 0) & (raw < _STATE_TABLE.shape[0])
    return np.where(known, _STATE_TABLE[np.clip(raw, 0, _STATE_TABLE.shape[0] - 1)], 0)


def attach_traffic_lights(
    signals: TrafficSignals,
    pieces: MapPieces,
    relevant_positions: np.ndarray,
    cfg: TokenConfig,
) -> TrafficLightTokens:
    """One TL token per (signal, kept lane piece of its controlled lane).

    Tokens are ordered by signal row, then piece row. Signals whose lane has no kept piece
    give no token (docs/model.md §1.3: such steps are invalidated). When more than
    ``cfg.max_traffic_lights`` tokens exist, the ones whose piece (node 0) is nearest to the
    relevant positions are kept, in their original order (the reference asserts instead:
    deliberate deviation).

    Args:
        signals: S controlled lanes over T steps.
        pieces: the kept map pieces (rows of the token map arrays), same frame as the positions.
        relevant_positions: [R, 3] float64 relevant-agent positions (history).
        cfg: ``max_traffic_lights``.

    Returns:
        The TL tokens.
    """
    is_lane = np.isin(pieces.map_class, LANE_CLASSES)
    match = (signals.lane_id[:, None] == pieces.feature_id[None, :]) & is_lane[None, :]
    signal, piece = np.nonzero(match)
    if signal.shape[0] > cfg.max_traffic_lights:
        dist = min_distance(pieces.pos[piece, 0], relevant_positions)
        nearest = np.sort(np.argsort(dist, kind="stable")[: cfg.max_traffic_lights])
        signal, piece = signal[nearest], piece[nearest]
    valid = signals.valid[signal].astype(bool)
    state = map_signal_states(signals.state[signal], valid)
    return TrafficLightTokens(
        piece=piece.astype(np.int64),
        state=state,
        valid=valid,
        signal=signal.astype(np.int64),
    )
