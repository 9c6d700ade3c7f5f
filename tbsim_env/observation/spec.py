"""What one agent's observation holds: every key with its shape, bounds and meaning, once.

``OBS_KEYS`` is the single declaration; the observation space (``observation_space``), the
shapes (``observation_shapes``), the dense observation's keys (``observation.densify`` is
tested against it) and the table of docs/environments.md (``observation_table``) are all built
from it.

Shapes use symbols that ``ObsConfig`` sets: H (history steps, the current one included), Ka,
Km, Kt (nearest agents, map pieces and traffic lights observed) and P (nodes per map piece).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from tbsim_env.core import constants as C
from tbsim_env.core.config import TokenConfig


@dataclass(frozen=True)
class ObsConfig:
    """Observation sizes.

    Attributes:
        history: steps of history per agent (current included).
        num_agents: nearest other agents observed.
        num_map: nearest map pieces observed.
        num_traffic_lights: nearest traffic-light tokens observed.
        agent_radius: m, agents farther away are masked.
        map_radius: m, map pieces whose start is farther away are masked.
        traffic_light_radius: m.
        tokens: limits of the map / traffic-light preprocessing.
    """

    history: int = C.NUM_HISTORY
    num_agents: int = C.DEFAULT_OBS_AGENTS
    num_map: int = C.DEFAULT_OBS_MAP_PIECES
    num_traffic_lights: int = C.DEFAULT_OBS_TRAFFIC_LIGHTS
    agent_radius: float = 100.0
    map_radius: float = 200.0
    traffic_light_radius: float = 200.0
    tokens: TokenConfig = TokenConfig()

    def __post_init__(self) -> None:
        for f in ("history", "num_agents", "num_map", "num_traffic_lights"):
            if getattr(self, f) < 1:
                raise ValueError(f"ObsConfig.{f} must be >= 1")


NUM_TYPE_FEATURES = 4
"""Type one-hot over (vehicle, pedestrian, cyclist, other)."""
HISTORY_FEATURES = 5
"""Per history step: x, y, cos(yaw), sin(yaw), speed."""
ATTRIBUTE_FEATURES = 2 + NUM_TYPE_FEATURES + 1
"""length, width, type one-hot, speed."""
NODE_FEATURES = 4
"""Per map node: x, y, cos, sin of the segment direction, in the piece frame."""


@dataclass(frozen=True)
class ObsKey:
    """One key of an agent's observation.

    Attributes:
        name: the key.
        dims: the shape, symbols (``"H"``, ``"Ka"``, ``"Km"``, ``"Kt"``, ``"P"``) or sizes.
        low, high: bounds of every value (inclusive).
        doc: what it holds (units, frame).
    """

    name: str
    dims: tuple[str | int, ...]
    low: float
    high: float
    doc: str


_INF = math.inf
OBS_KEYS: tuple[ObsKey, ...] = (
    ObsKey("ego_history", ("H", HISTORY_FEATURES), -_INF, _INF,
           "its last H states in its current frame: x m, y m, cos yaw, sin yaw, speed m/s"),
    ObsKey("ego_history_mask", ("H",), 0.0, 1.0, "1 where the history step is valid"),
    ObsKey("ego_attributes", (ATTRIBUTE_FEATURES,), -_INF, _INF,
           "length m, width m, type one-hot (vehicle, pedestrian, cyclist, other), speed m/s"),
    ObsKey("agents", ("Ka", "H", HISTORY_FEATURES), -_INF, _INF,
           "the Ka nearest other agents, each history in that agent's own current frame"),
    ObsKey("agents_history_mask", ("Ka", "H"), 0.0, 1.0, "1 where their history step is valid"),
    ObsKey("agents_attributes", ("Ka", ATTRIBUTE_FEATURES), -_INF, _INF,
           "their attributes, as ego_attributes"),
    ObsKey("agents_pose", ("Ka", 3), -_INF, _INF,
           "their pose in the observer's frame: dx m, dy m, dyaw rad in [-pi, pi)"),
    ObsKey("agents_mask", ("Ka",), 0.0, 1.0, "1 for an agent within the agent radius"),
    ObsKey("map", ("Km", "P", NODE_FEATURES), -_INF, _INF,
           "the Km nearest map pieces, nodes in the piece frame: x m, y m, cos, sin of the "
           "segment direction"),
    ObsKey("map_nodes_mask", ("Km", "P"), 0.0, 1.0, "1 where a piece has the node"),
    ObsKey("map_class", ("Km", C.NUM_MAP_CLASSES), 0.0, 1.0, "piece class one-hot"),
    ObsKey("map_pose", ("Km", 3), -_INF, _INF, "piece pose in the observer's frame"),
    ObsKey("map_mask", ("Km",), 0.0, 1.0, "1 for a piece starting within the map radius"),
    ObsKey("traffic_lights", ("Kt", C.NUM_TL_STATES), 0.0, 1.0,
           "the Kt nearest traffic lights: state one-hot"),
    ObsKey("traffic_lights_pose", ("Kt", 3), -_INF, _INF,
           "pose of the controlled lane piece in the observer's frame"),
    ObsKey("traffic_lights_mask", ("Kt",), 0.0, 1.0, "1 for a light within its radius"),
)  # fmt: skip
"""Every key of an agent's observation, in the order of ``densify``'s dict (a Gymnasium ``Dict``
space sorts them)."""


def _sizes(cfg: ObsConfig) -> dict[str, int]:
    return {
        "H": cfg.history,
        "Ka": cfg.num_agents,
        "Km": cfg.num_map,
        "Kt": cfg.num_traffic_lights,
        "P": cfg.tokens.piece_segments,
    }


def observation_shapes(cfg: ObsConfig) -> dict[str, tuple[int, ...]]:
    """Per-agent shape of every observation key."""
    sizes = _sizes(cfg)
    return {k.name: tuple(sizes[d] if isinstance(d, str) else d for d in k.dims) for k in OBS_KEYS}


def observation_space(cfg: ObsConfig) -> gym.spaces.Dict:
    """The fixed-shape ``Dict`` of ``Box`` es of one agent's observation."""
    shapes = observation_shapes(cfg)
    return gym.spaces.Dict(
        {k.name: gym.spaces.Box(k.low, k.high, shapes[k.name], np.float32) for k in OBS_KEYS}
    )


def observation_table() -> str:
    """A Markdown table of ``OBS_KEYS`` (the one in docs/environments.md)."""
    rows = ["| key | shape | range | holds |", "|---|---|---|---|"]
    for k in OBS_KEYS:
        shape = ", ".join(str(d) for d in k.dims)
        lo = "-inf" if k.low == -_INF else f"{k.low:g}"
        hi = "inf" if k.high == _INF else f"{k.high:g}"
        rows.append(f"| `{k.name}` | [{shape}] | [{lo}, {hi}] | {k.doc} |")
    return "\n".join(rows)


__all__ = [
    "ATTRIBUTE_FEATURES",
    "HISTORY_FEATURES",
    "NODE_FEATURES",
    "NUM_TYPE_FEATURES",
    "OBS_KEYS",
    "ObsKey",
    "observation_shapes",
    "observation_space",
    "observation_table",
]
