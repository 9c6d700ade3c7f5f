"""WOSAC metric configurations (2024 and 2025 sim-agents challenges) as frozen dataclasses.

All numbers are those of docs/metrics.md: histogram ranges and bins ("Histograms", the same in
2024 and 2025), pseudocounts ("Estimators"), feature weights and bucket groups ("Meta-metric and
buckets"). The bin edges are the exact float32 values the official TensorFlow code computes with
``tf.linspace``; for the 11-bin features they differ from a numpy float32 linspace by a few ulps,
so they are written out.
"""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass

import numpy as np

from tbsim_env.core.errors import TbsimError


class WosacConfigError(TbsimError, ValueError):
    """An unknown metric version or an inconsistent metric configuration."""


class MetricVersion(str, enum.Enum):
    """Which challenge's metric to compute."""

    WOSAC2024 = "wosac2024"
    WOSAC2025 = "wosac2025"


DEFAULT_VERSION = MetricVersion.WOSAC2025

NUM_ROLLOUTS = 32
"""Joint rollouts per scenario in a submission."""

# Geometry literals of the official feature code (docs/metrics.md, "Interactive features" and
# "Map-based features").
BOX_ROUNDING_FACTOR = 0.7
"""Corner radius of the rounded boxes is ``0.7 * min(length, width) / 2``."""
CYCLIC_POLYLINE_MAX_GAP_SQ = 1.0
"""A road edge is cyclic if its first and last points are closer than 1 m (squared metres)."""
ROAD_EDGE_Z_STRETCH = 3.0
"""z is scaled by 3 when choosing the closest road-edge segment."""
NO_PARTNER_DISTANCE = 1e10
"""Distance to nearest object without a valid partner (m); road-edge distance uses the negative."""
TTC_MAX_SECONDS = 5.0
"""Time to collision saturates at 5 s."""
TTC_MAX_HEADING_DIFF = math.radians(75.0)
"""Largest raw |heading difference| of a followed object (rad)."""
TTC_SMALL_HEADING_DIFF = math.radians(10.0)
"""Heading difference under which a merely touching lateral overlap counts (rad)."""
TTC_MIN_LATERAL_OVERLAP = 0.5
"""Lateral overlap (m) above which a followed object counts at any heading difference."""


def parse_version(version: MetricVersion | str) -> MetricVersion:
    """Validate a metric version given as an Enum or its string value ("wosac2024"/"wosac2025").

    Raises:
        WosacConfigError: for any other value.
    """
    if isinstance(version, MetricVersion):
        return version
    try:
        return MetricVersion(str(version).lower())
    except ValueError:
        valid = ", ".join(repr(v.value) for v in MetricVersion)
        raise WosacConfigError(
            f"unknown WOSAC metric version {version!r}; use one of {valid}"
        ) from None


@dataclass(frozen=True)
class HistogramSpec:
    """A histogram feature: ``num_bins`` bins on exact float32 edges over [min_val, max_val].

    Bins are [e_k, e_{k+1}) with the last one closed; NaN falls into the last bin.

    Attributes:
        min_val: lower clip bound (float32 value), in the feature's unit.
        max_val: upper clip bound (float32 value).
        num_bins: number of bins.
        edges: num_bins + 1 float32-exact edges, increasing, from min_val to max_val.
    """

    min_val: float
    max_val: float
    num_bins: int
    edges: tuple[float, ...]

    def __post_init__(self) -> None:
        if len(self.edges) != self.num_bins + 1:
            raise WosacConfigError(f"{len(self.edges)} edges for {self.num_bins} bins")
        if any(b <= a for a, b in zip(self.edges[:-1], self.edges[1:])):
            raise WosacConfigError(f"histogram edges not increasing: {self.edges}")
        if self.edges[0] != self.min_val or self.edges[-1] != self.max_val:
            raise WosacConfigError("first/last edge must equal min_val/max_val")

    @staticmethod
    def from_strings(edges: tuple[str, ...]) -> HistogramSpec:
        """Build from decimal float32 representations of the edges."""
        vals = tuple(float(np.float32(e)) for e in edges)
        return HistogramSpec(min_val=vals[0], max_val=vals[-1], num_bins=len(vals) - 1, edges=vals)


def _even_edges(lo: float, hi: float, num_bins: int) -> tuple[str, ...]:
    """Edges of a range whose float32 linspace is exact (every edge representable)."""
    edges = np.linspace(np.float32(lo), np.float32(hi), num_bins + 1, dtype=np.float32)
    return tuple(repr(float(e)) for e in edges)


@dataclass(frozen=True)
class HistogramSpecs:
    """The seven histogram features (docs/metrics.md, "Histograms"); units m/s, m/s^2, rad/s, ..."""

    linear_speed: HistogramSpec
    linear_acceleration: HistogramSpec
    angular_speed: HistogramSpec
    angular_acceleration: HistogramSpec
    distance_to_nearest_object: HistogramSpec
    distance_to_road_edge: HistogramSpec
    time_to_collision: HistogramSpec


HISTOGRAMS = HistogramSpecs(
    linear_speed=HistogramSpec.from_strings(_even_edges(0.0, 25.0, 10)),
    linear_acceleration=HistogramSpec.from_strings(
        ("-12", "-9.818182", "-7.6363635", "-5.454545", "-3.272727", "-1.090909")
        + ("1.09091", "3.272728", "5.454546", "7.636364", "9.818182", "12")
    ),
    angular_speed=HistogramSpec.from_strings(
        ("-0.628", "-0.5138182", "-0.3996364", "-0.28545454", "-0.17127272", "-0.05709088")
        + ("0.057090938", "0.17127275", "0.28545457", "0.3996364", "0.51381826", "0.628")
    ),
    angular_acceleration=HistogramSpec.from_strings(
        ("-3.14", "-2.569091", "-1.9981819", "-1.4272728", "-0.8563638", "-0.28545475")
        + ("0.2854545", "0.85636353", "1.4272726", "1.9981816", "2.5690906", "3.14")
    ),
    distance_to_nearest_object=HistogramSpec.from_strings(_even_edges(-5.0, 40.0, 10)),
    distance_to_road_edge=HistogramSpec.from_strings(_even_edges(-20.0, 40.0, 10)),
    time_to_collision=HistogramSpec.from_strings(_even_edges(0.0, 5.0, 10)),
)


@dataclass(frozen=True)
class FeatureWeights:
    """Meta-metric weight of every likelihood (docs/metrics.md, "Meta-metric and buckets")."""

    linear_speed: float
    linear_acceleration: float
    angular_speed: float
    angular_acceleration: float
    distance_to_nearest_object: float
    collision_indication: float
    time_to_collision: float
    distance_to_road_edge: float
    offroad_indication: float
    traffic_light_violation: float

    def as_dict(self) -> dict[str, float]:
        return dataclasses.asdict(self)

    def total(self) -> float:
        return math.fsum(self.as_dict().values())


BUCKETS: dict[str, tuple[str, ...]] = {
    "kinematic": ("linear_speed", "linear_acceleration", "angular_speed", "angular_acceleration"),
    "interactive": ("distance_to_nearest_object", "collision_indication", "time_to_collision"),
    "map_based": ("distance_to_road_edge", "offroad_indication", "traffic_light_violation"),
}
"""Leaderboard buckets: weighted averages of these likelihoods, normalised by their weights."""


@dataclass(frozen=True)
class WosacConfig:
    """Everything that differs between metric versions, plus the shared estimator settings.

    Attributes:
        version: which challenge.
        histograms: bins of the continuous features.
        weights: meta-metric weights (sum 1).
        histogram_pseudocount: added to every histogram bin (0.1).
        bernoulli_pseudocount: added to both Bernoulli bins (0.001).
        ttc_vehicles_only: 2025 scores time to collision on vehicles only.
    """

    version: MetricVersion
    histograms: HistogramSpecs
    weights: FeatureWeights
    histogram_pseudocount: float
    bernoulli_pseudocount: float
    ttc_vehicles_only: bool

    def __post_init__(self) -> None:
        if abs(self.weights.total() - 1.0) > 1e-9:
            raise WosacConfigError(f"{self.version.value}: weights sum to {self.weights.total()}")

    def bucket_weight(self, bucket: str) -> float:
        """Sum of the weights of one bucket's likelihoods."""
        w = self.weights.as_dict()
        return math.fsum(w[name] for name in BUCKETS[bucket])


WOSAC_2024 = WosacConfig(
    version=MetricVersion.WOSAC2024,
    histograms=HISTOGRAMS,
    weights=FeatureWeights(
        linear_speed=0.05,
        linear_acceleration=0.05,
        angular_speed=0.05,
        angular_acceleration=0.05,
        distance_to_nearest_object=0.10,
        collision_indication=0.25,
        time_to_collision=0.10,
        distance_to_road_edge=0.10,
        offroad_indication=0.25,
        traffic_light_violation=0.0,
    ),
    histogram_pseudocount=0.1,
    bernoulli_pseudocount=0.001,
    ttc_vehicles_only=False,
)

WOSAC_2025 = WosacConfig(
    version=MetricVersion.WOSAC2025,
    histograms=HISTOGRAMS,
    weights=FeatureWeights(
        linear_speed=0.05,
        linear_acceleration=0.05,
        angular_speed=0.05,
        angular_acceleration=0.05,
        distance_to_nearest_object=0.10,
        collision_indication=0.25,
        time_to_collision=0.10,
        distance_to_road_edge=0.05,
        offroad_indication=0.25,
        traffic_light_violation=0.05,
    ),
    histogram_pseudocount=0.1,
    bernoulli_pseudocount=0.001,
    ttc_vehicles_only=True,
)


def get_config(version: MetricVersion | str = DEFAULT_VERSION) -> WosacConfig:
    """The configuration of a metric version (validated, see ``parse_version``)."""
    v = parse_version(version)
    return WOSAC_2024 if v is MetricVersion.WOSAC2024 else WOSAC_2025
