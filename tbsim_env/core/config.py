"""Frozen configuration dataclasses. Defaults come from ``tbsim_env.core.constants``."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass

from tbsim_env.core import constants as C


@dataclass(frozen=True)
class TokenConfig:
    """Limits and options of the preprocessing into tokens (docs/model.md §1).

    Attributes:
        max_map_pieces: map pieces kept per scenario (TrafficBots: 1024).
        max_traffic_lights: traffic-light tokens kept (TrafficBots: 128).
        max_agents: simulated agents kept (TrafficBots: 64). The SDC, tracks_to_predict and
            objects_of_interest are never dropped; if they alone exceed the limit, an error says so.
        piece_segments: maximum segments per map piece (20).
        resample_stride: keep every n-th raw polyline point (2, giving ~1 m spacing).
        training: use the training-split agent filters (docs/model.md §1.6 b and e) and full-episode
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


@dataclass(frozen=True)
class RewardConfig:
    """Weights of the per-step reward terms of an externally controlled agent.

    reward = collision * [collided] + offroad * [off road] + progress * (metres gained along
    the logged route this step) + goal * [goal reached this step] + log_divergence * (distance
    to the logged position at this step, metres) + alive * 1, plus the weighted terms a user
    registered (``tbsim_env.env.rewards.register_reward_term``) and listed in ``terms``.

    Attributes:
        collision: weight of the collision indicator (usually negative).
        offroad: weight of the off-road indicator (usually negative).
        progress: weight per metre of progress along the agent's logged route.
        goal: weight of reaching the logged final position (given once).
        log_divergence: weight per metre of distance to the log (usually <= 0).
        alive: constant reward per step.
        goal_radius: m, distance to the logged final position that counts as reached.
        terms: ((name, weight), ...) of registered reward terms beyond the built-ins.
    """

    collision: float = -1.0
    offroad: float = -1.0
    progress: float = 0.05
    goal: float = 1.0
    log_divergence: float = 0.0
    alive: float = 0.0
    goal_radius: float = 2.0
    terms: tuple[tuple[str, float], ...] = ()

    def __post_init__(self) -> None:
        # Stored as a tuple of pairs, so that the config stays hashable and immutable; a
        # mapping is accepted too.
        items = self.terms.items() if isinstance(self.terms, Mapping) else self.terms
        object.__setattr__(self, "terms", tuple((str(n), float(w)) for n, w in items))


@dataclass(frozen=True)
class TerminationConfig:
    """Which events end an externally controlled agent's episode (it then leaves the scene).

    Attributes:
        collision: terminate on collision.
        offroad: terminate on leaving the road.
        goal: terminate on reaching the logged final position.
    """

    collision: bool = True
    offroad: bool = False
    goal: bool = True


@dataclass(frozen=True)
class EnvConfig:
    """Configuration of ``TrafficEnv``.

    The episode length comes from here, not from the log: a scene whose log ends earlier
    (e.g. a WOSAC test-split scene, 11 logged steps) runs the whole episode with its NPCs
    driven by the NPC policy (``tbsim_env.sim.horizon``).

    Attributes:
        start_step: step the episode starts at (the log must hold it; history before it comes
            from the log). It must be every scenario's current step (``current_time_index``,
            10 in WOMD): the environments refuse a scenario whose current step differs
            (``UnusableScenarioError``).
        end_step: last simulated step; None means step 90 (``C.NUM_STEPS - 1``, the end of a
            WOMD episode), whatever the log's length. See ``last_step``.
        reward: reward weights.
        termination: termination events.
        remove_terminated: remove terminated agents from the simulation (otherwise they stay
            as frozen obstacles).
    """

    start_step: int = C.CURRENT_INDEX
    end_step: int | None = None
    reward: RewardConfig = RewardConfig()
    termination: TerminationConfig = TerminationConfig()
    remove_terminated: bool = True

    def __post_init__(self) -> None:
        if self.start_step < 0:
            raise ValueError("EnvConfig.start_step must be >= 0")
        if self.last_step <= self.start_step:
            raise ValueError(
                f"EnvConfig.end_step ({self.last_step}) must be greater than start_step "
                f"({self.start_step})"
            )

    @property
    def last_step(self) -> int:
        """The last simulated step: ``end_step``, or 90 when None."""
        return C.NUM_STEPS - 1 if self.end_step is None else self.end_step
