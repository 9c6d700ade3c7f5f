"""``SceneTokens`` (numpy, one scene) -> ``TokenBatch`` (torch, a padded batch of scenes)."""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from tbsim_env.data.tokens import SceneTokens

_AGENT_FIELDS = ("ag_valid", "ag_pose", "ag_motion", "ag_type", "ag_size", "ag_role", "ag_dest")
_MAP_FIELDS = ("mp_pose", "mp_valid", "mp_cls")
_TL_FIELDS = ("tl_piece", "tl_state", "tl_valid")
"""``TokenBatch`` fields whose axis 1 is the agent (N), map piece (M) or TL token (L) axis."""


@dataclass(frozen=True)
class TokenBatch:
    """Model inputs of B scenes (docs/model.md §1.9 ``sc/*`` and ``gt/*``), scene frame of each
    scene.

    Shapes: B scenes, M map pieces, P nodes, L TL tokens, N agents, T steps.

    Attributes:
        mp_pose: [B, M, P, 3] (x m, y m, segment heading rad) per node.
        mp_valid: [B, M, P] bool.
        mp_cls: [B, M] int64 ``MapClass``, -1 padding.
        mp_boundary: [B, 5] the map's box: (x_min, x_max, y_min, y_max) m in the scene frame
            rotated by the fifth entry, yaw rad (``SceneTokens.frame_yaw``).
        tl_piece: [B, L] int64 map row of the controlled lane piece, -1 padding.
        tl_state: [B, L, T] int64 ``TLState`` (UNKNOWN where invalid).
        tl_valid: [B, L, T] bool.
        ag_valid: [B, N, T] bool.
        ag_pose: [B, N, T, 3] (x m, y m, yaw rad).
        ag_motion: [B, N, T, 3] (signed speed m/s, acceleration m/s^2, yaw rate rad/s).
        ag_type: [B, N] int64 ``ObjectType`` (0 padding).
        ag_size: [B, N, 3] (length, width, height) m.
        ag_role: [B, N, 3] bool (SDC, object of interest, track to predict).
        ag_dest: [B, N] int64 destination map row, -1 none.
        scenario_id: B scenario ids.
        padded_sizes: (N, M) of the arrays this batch was ``trim``-med from, or None if it
            was not; ``TrafficBots.prepare`` draws its random samples at these sizes.
    """

    mp_pose: torch.Tensor
    mp_valid: torch.Tensor
    mp_cls: torch.Tensor
    mp_boundary: torch.Tensor
    tl_piece: torch.Tensor
    tl_state: torch.Tensor
    tl_valid: torch.Tensor
    ag_valid: torch.Tensor
    ag_pose: torch.Tensor
    ag_motion: torch.Tensor
    ag_type: torch.Tensor
    ag_size: torch.Tensor
    ag_role: torch.Tensor
    ag_dest: torch.Tensor
    scenario_id: tuple[str, ...]
    padded_sizes: tuple[int, int] | None = None

    @property
    def n_scenes(self) -> int:
        return int(self.ag_valid.shape[0])

    @property
    def n_steps(self) -> int:
        return int(self.ag_valid.shape[-1])

    @property
    def draw_sizes(self) -> tuple[int, int]:
        """(N, M) at which random per-agent / per-piece samples are drawn: the padded sizes of
        a trimmed batch, else the batch's own, so that trimming changes no sample."""
        return self.padded_sizes or (self.ag_valid.shape[1], self.mp_valid.shape[1])

    @property
    def device(self) -> torch.device:
        return self.ag_pose.device

    def _map(self, fn: Callable[[torch.Tensor], torch.Tensor]) -> TokenBatch:
        changes = {
            f.name: fn(getattr(self, f.name))
            for f in dataclasses.fields(self)
            if isinstance(getattr(self, f.name), torch.Tensor)
        }
        return dataclasses.replace(self, **changes)

    def to(self, device: torch.device | str) -> TokenBatch:
        """Move every tensor to ``device``."""
        return self._map(lambda x: x.to(device))

    def repeat(self, n: int) -> TokenBatch:
        """Repeat every scene ``n`` times along the batch (``repeat_interleave``)."""
        out = self._map(lambda x: x.repeat_interleave(n, dim=0))
        ids = tuple(s for s in self.scenario_id for _ in range(n))
        return dataclasses.replace(out, scenario_id=ids)

    def select(self, rows: torch.Tensor | Sequence[int]) -> TokenBatch:
        """Keep the given batch rows."""
        rows_t = torch.as_tensor(rows, dtype=torch.long, device=self.device)
        out = self._map(lambda x: x[rows_t])
        return dataclasses.replace(out, scenario_id=tuple(self.scenario_id[i] for i in rows_t))

    def trim(self, min_rows: tuple[int, int, int] | None = None) -> TokenBatch:
        """Drop the trailing map pieces, TL tokens and agents that are padding in every scene.

        Preprocessing pads each scene to the token limits (1024 pieces, 128 TL tokens, 64
        agents) so that cached scenes stack; a scene fills a fraction of them (the real
        scenario of ``bench/policy_step.py``: 648, 34 and 55), and every policy step would
        otherwise run its MLPs, KNN and attention over the padding. Padding is masked
        everywhere, so the model computes the same function on the trimmed batch (to float
        rounding), and ``TrafficBots.prepare`` draws its samples at ``padded_sizes``, so the
        samples are the same too. Rows that stay keep their indices.

        Args:
            min_rows: (N, M, L) rows to keep at least (capped at the arrays' sizes). With
                the rows that a whole set of scenes uses (``rows_used``), every batch drawn
                from the set trims to the same shapes.

        Returns:
            The batch with N, M and L cut to the last row used by any scene (at least 1),
            or to ``min_rows`` where that is more.
        """
        n, m, n_tl = self.rows_used()
        if min_rows is not None:
            n, m, n_tl = (max(a, b) for a, b in zip((n, m, n_tl), min_rows, strict=True))
        n = min(n, self.ag_valid.shape[1])
        m = min(m, self.mp_valid.shape[1])
        n_tl = min(n_tl, self.tl_piece.shape[1])
        changes = {}
        for names, size in ((_AGENT_FIELDS, n), (_MAP_FIELDS, m), (_TL_FIELDS, n_tl)):
            changes.update({name: getattr(self, name)[:, :size] for name in names})
        return dataclasses.replace(self, **changes, padded_sizes=self.draw_sizes)

    def rows_used(self) -> tuple[int, int, int]:
        """(N, M, L): 1 + the last agent, map piece and TL token row that any scene uses (a
        piece counts when it is valid, classed, a destination or a TL token's lane)."""
        n = _rows_used(self.ag_valid.any(-1))
        m = _rows_used(self.mp_valid.any(-1) | (self.mp_cls >= 0))
        m = max(m, int(self.ag_dest.max()) + 1, int(self.tl_piece.max()) + 1)
        n_tl = _rows_used((self.tl_piece >= 0) | self.tl_valid.any(-1))
        return n, m, n_tl

    @classmethod
    def from_tokens(
        cls, tokens: SceneTokens | Sequence[SceneTokens], device: torch.device | str = "cpu"
    ) -> TokenBatch:
        """Collate one or several scenes, padding M, L and N to the largest scene.

        Args:
            tokens: one ``SceneTokens`` or a sequence (all with the same number of steps).
            device: target device.

        Returns:
            ``TokenBatch`` with B = number of scenes.
        """
        scenes = [tokens] if isinstance(tokens, SceneTokens) else list(tokens)
        if not scenes:
            raise ValueError("no scenes to collate")
        n_steps = {s.agent_valid.shape[1] for s in scenes}
        if len(n_steps) != 1:
            raise ValueError(f"scenes have different step counts {sorted(n_steps)}")
        fields = [_scene_arrays(s) for s in scenes]
        pad = {"mp_cls": -1, "tl_piece": -1, "ag_dest": -1}
        out = {}
        for name in fields[0]:
            arrays = [f[name] for f in fields]
            size = max(a.shape[0] for a in arrays)
            padded = [_pad0(a, size, pad.get(name, 0)) for a in arrays]
            out[name] = torch.from_numpy(np.stack(padded)).to(device)
        return cls(**out, scenario_id=tuple(s.scenario_id for s in scenes))


def _rows_used(used: torch.Tensor) -> int:
    """1 + the last row index used by any scene of ``used`` [B, X] (at least 1)."""
    rows = used.any(0).nonzero()
    return int(rows[-1, 0]) + 1 if len(rows) else 1


def _pad0(a: np.ndarray, size: int, fill: float | int) -> np.ndarray:
    """Pad the first axis of ``a`` to ``size`` with ``fill``."""
    if a.shape[0] == size:
        return a
    tail = np.full((size - a.shape[0],) + a.shape[1:], fill, dtype=a.dtype)
    return np.concatenate([a, tail], axis=0)


def _scene_arrays(t: SceneTokens) -> dict[str, np.ndarray]:
    """Model arrays of one scene (numpy, unbatched)."""
    map_valid = np.asarray(t.map_valid, dtype=bool)
    heading = np.arctan2(t.map_dir[..., 1], t.map_dir[..., 0])
    mp_pose = np.concatenate([t.map_pos[..., :2], heading[..., None]], axis=-1)
    mp_pose = np.where(map_valid[..., None], mp_pose, 0.0).astype(np.float32)
    ag_valid = np.asarray(t.agent_valid, dtype=bool)
    ag_pose = np.concatenate([t.agent_pos[..., :2], t.agent_yaw[..., None]], axis=-1)
    ag_motion = np.stack([t.agent_speed, t.agent_accel, t.agent_yaw_rate], axis=-1)
    tl_valid = np.asarray(t.tl_valid, dtype=bool)
    return {
        "mp_pose": mp_pose,
        "mp_valid": map_valid,
        "mp_cls": np.asarray(t.map_class, dtype=np.int64),
        "mp_boundary": np.append(t.map_boundary, t.frame_yaw).astype(np.float32),
        "tl_piece": np.asarray(t.tl_piece, dtype=np.int64),
        "tl_state": np.where(tl_valid, t.tl_state, 0).astype(np.int64),
        "tl_valid": tl_valid,
        "ag_valid": ag_valid,
        "ag_pose": np.where(ag_valid[..., None], ag_pose, 0.0).astype(np.float32),
        "ag_motion": np.where(ag_valid[..., None], ag_motion, 0.0).astype(np.float32),
        "ag_type": np.asarray(t.agent_type, dtype=np.int64),
        "ag_size": np.asarray(t.agent_size, dtype=np.float32),
        "ag_role": np.asarray(t.agent_role, dtype=bool),
        "ag_dest": np.asarray(t.agent_dest, dtype=np.int64),
    }
