"""Frozen configuration dataclasses. Defaults come from ``tbsim_env.constants``."""

from __future__ import annotations

from dataclasses import dataclass

from tbsim_env import constants as C


@dataclass(frozen=True)
class TokenConfig:
    """Limits and options of the preprocessing into tokens (spec section 1).

    Attributes:
        max_map_pieces: map pieces kept per scenario (TrafficBots: 1024).
        max_traffic_lights: traffic-light tokens kept (TrafficBots: 128).
        max_agents: simulated agents kept (TrafficBots: 64). The SDC, tracks_to_predict and
            objects_of_interest are never dropped; if they alone exceed the limit, an error says so.
        piece_segments: maximum segments per map piece (20).
        resample_stride: keep every n-th raw polyline point (2, giving ~1 m spacing).
        training: use the training-split agent filters (spec 1.6 b and e) and full-episode
            relevant positions; False for validation/test behaviour (history only).
    """

    max_map_pieces: int = C.DEFAULT_MAX_MAP_PIECES
    max_traffic_lights: int = C.DEFAULT_MAX_TRAFFIC_LIGHTS
    max_agents: int = C.DEFAULT_MAX_AGENTS
    piece_segments: int = C.MAP_PIECE_SEGMENTS
    resample_stride: int = C.MAP_RESAMPLE_STRIDE
    training: bool = False

    def __post_init__(self) -> None:
        for name in ("max_map_pieces", "max_traffic_lights", "max_agents", "piece_segments"):
            if getattr(self, name) < 1:
                raise ValueError(f"TokenConfig.{name} must be >= 1, got {getattr(self, name)}")
        if self.resample_stride < 1:
            raise ValueError("TokenConfig.resample_stride must be >= 1")
