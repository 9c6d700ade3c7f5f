"""Keep at most ``max_map_pieces`` pieces near the relevant agents.

docs/model.md §1.6, map steps 2-4.
"""

from __future__ import annotations

import numpy as np

from tbsim_env.core.config import TokenConfig
from tbsim_env.data.preprocess import spec
from tbsim_env.data.preprocess.map_pieces import MapPieces


def min_distance(points: np.ndarray, targets: np.ndarray, chunk: int = 1 << 22) -> np.ndarray:
    """Distance from every point to its nearest target (batched, in chunks of bounded memory).

    Args:
        points: [..., D] float64 metres.
        targets: [R, D] float64 metres.
        chunk: upper bound on the elements of one temporary [points, R] matrix.

    Returns:
        [...] float64, +inf where there is no target.
    """
    if targets.shape[0] == 0:
        return np.full(points.shape[:-1], np.inf)
    flat = points.reshape(-1, points.shape[-1])
    step = max(1, chunk // targets.shape[0])
    t2 = (targets**2).sum(-1)
    out = np.empty(flat.shape[0])
    for lo in range(0, flat.shape[0], step):
        part = flat[lo : lo + step]
        d2 = (part**2).sum(-1)[:, None] + t2[None, :] - 2.0 * part @ targets.T
        out[lo : lo + step] = d2.min(axis=1)
    return np.sqrt(np.maximum(out, 0.0)).reshape(points.shape[:-1])


def prune_by_distance(
    distance: np.ndarray, keep: np.ndarray, protected: np.ndarray, limit: int, start_radius: float
) -> np.ndarray:
    """Drop far candidates in index order until ``limit`` remain, halving the radius per pass.

    A pass with radius r walks the kept, unprotected rows in index order and drops those with
    ``distance >= r``, stopping the moment exactly ``limit`` rows remain (docs/model.md §1.6 map
    step 4 and agent filter f).

    Args:
        distance: [K] float64 metres, the distance of each row to the relevant positions.
        keep: [K] bool, rows still kept.
        protected: [K] bool, rows never dropped.
        limit: how many rows may remain.
        start_radius: first radius (metres).

    Returns:
        [K] bool, the new keep mask (more than ``limit`` only if the protected rows exceed it).
    """
    keep = keep.copy()
    radius = start_radius
    while keep.sum() > limit:
        droppable = keep & ~protected & (distance >= radius)
        if not droppable.any() and radius == 0.0:
            break
        excess = int(keep.sum()) - limit
        keep[np.flatnonzero(droppable)[:excess]] = False
        radius = radius / 2.0 if radius / 2.0 >= spec.PRUNE_MIN_RADIUS else 0.0
    return keep


def rotate_xy(points: np.ndarray, yaw: float) -> np.ndarray:
    """``points`` [..., D >= 2] with x, y rotated by ``yaw`` (rad, counter-clockwise) about
    (0, 0); other columns kept. A float64 copy."""
    out = np.array(points, np.float64, copy=True)
    c, s = np.cos(yaw), np.sin(yaw)
    out[..., 0] = c * points[..., 0] - s * points[..., 1]
    out[..., 1] = s * points[..., 0] + c * points[..., 1]
    return out


def box_filter(
    pieces: MapPieces, relevant_positions: np.ndarray, frame_yaw: float = 0.0
) -> np.ndarray:
    """[K] bool: pieces inside the enlarged bounding box of the relevant positions.

    Each of the six bounds is tested separately with "some valid node" (docs/model.md §1.6 step 2);
    the margin is max(extent, 500 m) in x and y and max(extent, 6 m) in z. The box is axis-aligned
    in the spec's scene frame (x along ``frame_yaw``), not in the token frame, so that it
    does not depend on the orientation of the file's world frame.

    Args:
        pieces: K pieces.
        relevant_positions: [R, 3] float64, R >= 1, same frame as the pieces.
        frame_yaw: yaw (rad) of the box's x-axis in the pieces' frame.
    """
    rel = rotate_xy(relevant_positions, -frame_yaw)
    pos = rotate_xy(pieces.pos, -frame_yaw)
    lo = rel.min(axis=0)
    hi = rel.max(axis=0)
    floor = np.array([spec.BOX_MIN_EXTENT_XY, spec.BOX_MIN_EXTENT_XY, spec.BOX_MIN_EXTENT_Z])
    margin = np.maximum(hi - lo, floor)
    valid = pieces.valid[..., None]
    above = (valid & (pos > lo - margin)).any(axis=1)
    below = (valid & (pos < hi + margin)).any(axis=1)
    return (above & below).all(axis=1)


def filter_map_pieces(
    pieces: MapPieces, relevant_positions: np.ndarray, cfg: TokenConfig, frame_yaw: float = 0.0
) -> np.ndarray:
    """Rows of the pieces to keep, in their original order (docs/model.md §1.6 map steps 2-4).

    1. Box filter around the relevant positions (axis-aligned in the scene frame of
       ``frame_yaw``), undone if fewer than 10 pieces survive.
    2. Drop pieces with <= 3 valid nodes.
    3. While more than ``cfg.max_map_pieces`` remain: distance pruning on the 3-D distance of
       the first and last node to the relevant positions, r = 500 m halved per pass.

    Args:
        pieces: K unfiltered pieces.
        relevant_positions: [R, 3] float64 valid positions of the relevant agents (history),
            same frame as the pieces. With R = 0 the box filter is skipped and pruning keeps
            the first pieces in index order.
        cfg: ``max_map_pieces``.
        frame_yaw: yaw (rad) of the spec's scene frame in the pieces' frame (the SDC's
            heading, ``scene_yaw``); only the box filter depends on it.

    Returns:
        [k] int64 sorted row indices, k <= cfg.max_map_pieces.
    """
    keep = np.ones(pieces.num_pieces, bool)
    if relevant_positions.shape[0] > 0 and pieces.num_pieces > 0:
        boxed = box_filter(pieces, relevant_positions, frame_yaw)
        if boxed.sum() >= spec.BOX_MIN_SURVIVORS:
            keep = boxed
    keep &= pieces.valid.sum(axis=1) >= spec.MIN_VALID_NODES
    if keep.sum() > cfg.max_map_pieces:
        first = min_distance(pieces.pos[:, 0], relevant_positions)
        last = min_distance(pieces.last_node_pos(), relevant_positions)
        keep = prune_by_distance(
            np.minimum(first, last),
            keep,
            np.zeros_like(keep),
            cfg.max_map_pieces,
            spec.MAP_PRUNE_START_RADIUS,
        )
    return np.flatnonzero(keep)
