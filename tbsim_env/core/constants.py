"""Every literal of tbsim in one place: time grid, object types, map classes, limits.

Units: metres, seconds, radians. Array shapes are given where a constant sizes one.
"""

from __future__ import annotations

import enum

# --------------------------------------------------------------------------- time
DT = 0.1
"""Simulation step in seconds (WOMD is logged at 10 Hz)."""
NUM_STEPS = 91
"""Steps in a standard WOMD scenario (0.0 .. 9.0 s)."""
CURRENT_INDEX = 10
"""Index of the "current" step: steps 0..10 are history, 11..90 the future."""
NUM_HISTORY = 11
"""History window length, current step included."""
NUM_FUTURE = 80
"""Future steps simulated after the current one."""


# --------------------------------------------------------------------------- objects
class ObjectType(enum.IntEnum):
    """WOMD ``Track.ObjectType`` values (kept numerically identical)."""

    UNSET = 0
    VEHICLE = 1
    PEDESTRIAN = 2
    CYCLIST = 3
    OTHER = 4


NUM_OBJECT_TYPES = 5

# Unicycle limits per object type, indexed by ``ObjectType`` value.
# Vehicle 5 m/s^2 and 1.5 rad/s, cyclist 6 and 3, pedestrian 7 and 7 (TrafficBots V1.5,
# docs/model.md §4). UNSET and OTHER get the vehicle limits (the spec has no slot for them).
MAX_ACCEL = (5.0, 5.0, 7.0, 6.0, 5.0)
"""Maximum |acceleration| in m/s^2 per ``ObjectType``."""
MAX_YAW_RATE = (1.5, 1.5, 7.0, 3.0, 1.5)
"""Maximum |yaw rate| in rad/s per ``ObjectType``."""

# --------------------------------------------------------------------------- plausibility
# The bounds of what a scene or a submission may hold: ``Scenario.validate`` (every reader,
# and the environments for scenarios given as objects) and the submission validator refuse
# anything beyond them with one error naming the file, record, object, step and field. Real
# WOMD data stays far inside (the shared samples: speeds <= 87 m/s, boxes <= 17 m, scenes
# <= 0.62 km across, stored headings <= 17.3 rad), and within them float32 arithmetic after
# recentering on the scene (``SimState.origin``) cannot overflow: no squared speed, distance
# or arc length comes near float32's 3.4e38.
MAX_ABS_COORDINATE = 1.0e7
"""Metres. Largest |x|, |y|, |z| a scene or a submission may hold: 10,000 km, beyond any local
metric frame on Earth. Readers and the submission validator refuse larger values (a corrupt
exponent would otherwise reach the geometry code, e.g. densifying a 1e30 m polyline)."""
MAX_SCENE_EXTENT = 2.0e3
"""Metres. Largest width (x) and height (y) of the box holding a scene's valid track positions
and map points: what is simulated lies within it of the scene's origin, where float32 keeps
0.1 mm, and the road-edge grid of the off-road check (``EDGE_GRID_CELL`` cells over the edges'
box) stays below about a million cells."""
MAX_SPEED = 500.0
"""m/s. Largest |velocity| of a valid track state (1,800 km/h: nothing on a road; WOMD's worst
glitches stay below 100 m/s)."""
MAX_BOX_SIZE = 100.0
"""Metres. Largest length, width or height of a valid track state's box; the smallest is any
positive size (a box of size 0 or less is refused)."""
MAX_ABS_HEADING = 1.0e3
"""Radians. Largest |heading| as stored, of a track state or a submitted trajectory (WOMD stores
headings off by whole turns, up to ~17 rad in the samples; a rollout that integrates yaw rates
unwrapped reaches ~70 rad). float32 keeps 1e-4 rad at this bound."""
MAX_TRACK_ID = 2**31 - 1
"""Largest track id (``Track.id``, also ``objects_of_interest``: int32 in scenario.proto); track
ids are non-negative (-1 marks padding)."""
MAX_FEATURE_ID = 2**63 - 1
"""Largest map feature id (``MapFeature.id``, signal lane ids: int64 in scenario.proto); they
are non-negative (-1 marks padding) and unique within a scene."""
NUM_DIFFICULTY_LEVELS = 3
"""``RequiredPrediction.DifficultyLevel`` values: NONE, LEVEL_1, LEVEL_2 (0-2)."""


# --------------------------------------------------------------------------- raw map
class MapFeatureType(enum.IntEnum):
    """Which member of ``MapFeature.feature_data`` is set."""

    LANE = 0
    ROAD_LINE = 1
    ROAD_EDGE = 2
    STOP_SIGN = 3
    CROSSWALK = 4
    SPEED_BUMP = 5
    DRIVEWAY = 6


class LaneType(enum.IntEnum):
    """WOMD ``LaneCenter.LaneType``."""

    UNDEFINED = 0
    FREEWAY = 1
    SURFACE_STREET = 2
    BIKE_LANE = 3


class RoadLineType(enum.IntEnum):
    """WOMD ``RoadLine.RoadLineType``."""

    UNKNOWN = 0
    BROKEN_SINGLE_WHITE = 1
    SOLID_SINGLE_WHITE = 2
    SOLID_DOUBLE_WHITE = 3
    BROKEN_SINGLE_YELLOW = 4
    BROKEN_DOUBLE_YELLOW = 5
    SOLID_SINGLE_YELLOW = 6
    SOLID_DOUBLE_YELLOW = 7
    PASSING_DOUBLE_YELLOW = 8


class RoadEdgeType(enum.IntEnum):
    """WOMD ``RoadEdge.RoadEdgeType``."""

    UNKNOWN = 0
    BOUNDARY = 1
    MEDIAN = 2


class SignalState(enum.IntEnum):
    """WOMD ``TrafficSignalLaneState.State`` (raw, 9 values)."""

    UNKNOWN = 0
    ARROW_STOP = 1
    ARROW_CAUTION = 2
    ARROW_GO = 3
    STOP = 4
    CAUTION = 5
    GO = 6
    FLASHING_STOP = 7
    FLASHING_CAUTION = 8


# --------------------------------------------------------------------------- tokens
class MapClass(enum.IntEnum):
    """The 11 map-piece classes of TrafficBots V1.5 (docs/model.md §1.2)."""

    FREEWAY = 0
    SURFACE_STREET = 1
    STOP_SIGN = 2
    BIKE_LANE = 3
    ROAD_EDGE_BOUNDARY = 4
    ROAD_EDGE_MEDIAN = 5
    BROKEN = 6
    SOLID_SINGLE = 7
    DOUBLE = 8
    SPEED_BUMP = 9
    CROSSWALK = 10


NUM_MAP_CLASSES = 11


class TLState(enum.IntEnum):
    """The 5 traffic-light classes of TrafficBots V1.5 (docs/model.md §1.3)."""

    UNKNOWN = 0
    STOP = 1
    CAUTION = 2
    GO = 3
    FLASHING = 4


NUM_TL_STATES = 5

# Raw WOMD signal state -> TLState, indexed by ``SignalState`` value.
SIGNAL_TO_TL_STATE = (0, 1, 2, 3, 1, 2, 3, 4, 4)

MAP_PIECE_SEGMENTS = 20
"""Maximum segments (nodes) per map piece."""
MAP_RESAMPLE_STRIDE = 2
"""Keep every 2nd WOMD polyline point (~0.5 m apart) to get ~1 m spacing."""

# Default token limits (configuration, see ``tbsim_env.core.config``).
DEFAULT_MAX_MAP_PIECES = 1024
DEFAULT_MAX_TRAFFIC_LIGHTS = 128
DEFAULT_MAX_AGENTS = 64

# Default observation neighbour counts.
DEFAULT_OBS_MAP_PIECES = 64
DEFAULT_OBS_TRAFFIC_LIGHTS = 25
DEFAULT_OBS_AGENTS = 25

MPH_TO_MPS = 0.44704

GEOMETRY_TIE_TOLERANCE = 1e-6
"""Metres. Preprocessing compares lengths with this slack where a choice is discrete (how many
1 m points a crosswalk side gets, which side is the longer one): generated maps have exact
integer and equal lengths, whose float rounding differs between world frames, and an exact
comparison would then give a moved copy of the scene other map tokens."""
KNN_DISTANCE_RESOLUTION = 0.01
"""Metres. TrafficBots' K-nearest-neighbour selection ranks distances in buckets of this width,
ties broken by the lower row, so that distances equal but for the float rounding of the scene
frame (symmetric maps) select the same neighbours in every frame."""
KNN_BUCKET_OFFSET = 0.3819660112501051
"""Fraction of ``KNN_DISTANCE_RESOLUTION`` added before rounding down (2 minus the golden
ratio): bucket edges fall between round distances (a lane width of 3.5 m, a node 10 m away),
which generated maps have exactly and rounding would put on either side of an edge."""

MAP_KNN_CLUSTER_SIZE = 16
"""Map pieces per cluster at most (``tbsim_env.observation.map_knn``: TrafficBots' agents
search nearby clusters)."""
MAP_KNN_CLUSTERS = 16
"""Clusters searched per observer for its nearest map pieces (256 candidates at most)."""
MAP_KNN_MARGIN = 0.05
"""m: a narrowed map search (grid or clusters) holds when its k-th distance is this far below
the bound on every piece left out (5 buckets of ``KNN_DISTANCE_RESOLUTION``, far above float32
rounding)."""
MAP_KNN_MIN_OBSERVERS = 8
"""Observers per row from which the clustered search pays (fewer: every piece is measured,
in fewer tensor operations)."""
MAP_KNN_RADIUS_PAD = 0.01
"""m added to a cluster's radius (float32 rounding of its centre and members)."""
MAP_GRID_CELL = 5.0
"""m, cell size of the observations' map-piece grid (``map_knn.PieceGrid``): with
``MAP_GRID_CANDIDATES`` listed, every observer of the real samples is vouched for (4 m cells
and 80 listed: 2%, 5 m and 80: 7%, each searched again over every piece)."""
MAP_GRID_CANDIDATES = 96
"""Map pieces listed per grid cell, nearest to its centre first (1.5x the default 64 seen)."""
MAP_GRID_MARGIN = 20.0
"""m the map-piece grid extends beyond the pieces' bounding box."""
MAP_GRID_MIN_WORK = 24_000
"""Observer-piece distances (observers x pieces) of a call from which the grid search pays
over measuring every piece: it costs ~110 us more per call, and saves ~5 ns per distance (on
the real samples from ~18 observers of 1,024 pieces, ~31 of 648, ~71 of 362)."""

# --------------------------------------------------------------------------- compute
# Elements (float32) of the largest per-call intermediate of KNARPE attention on a CPU; larger
# batches run in chunks of rows so that the working set stays in the caches (2 MiB).
CPU_ATTENTION_CHUNK_ELEMENTS = 1 << 19
BANK_METRICS_CHUNK = 256
"""Scenarios per chunk when an episode bank computes its first metrics (their agent
distances are [S, Q, N])."""
FIRST_OBS_BANK_MAX_BYTES = 256 * 2**20
"""``BatchedTrafficEnv`` keeps every bank row's first observation (observed once) when they
take at most this many bytes: a restarted slot then gathers its first observation instead of
copying its new episode's rows and observing them."""
COMPONENT_MERGE_MIN_SLOTS = 1536
"""``sim.core.step`` and ``merge_actions`` merge [B, N, K] poses and actions by [B, N] masks a
component at a time from this many slots (B N) on (``torch_utils.where_into``; a [B, N, 1]
mask broadcast over [B, N, 3] costs 141 against 3 x 16 us at 16,384 slots, 18 against 13 at
2,048), and by [B, N, 1] masks below (fewer operations: 2.5 against 10 us at 64 slots)."""
COMPONENT_POSES_MIN = 3072
"""Relative poses (``geometry.relative_pose``) and agent tokens (``observation.tokens``) are
computed a component at a time (x, y and yaw as [...] planes, written into the result) from
this many poses (targets, or agent rows x history steps) on: no [..., 1, 2] or [..., 1]
operand broadcast over a trailing dim, 2.3x faster for the agent tokens of [64, 257]
slots; below, on [..., 2] / [..., 3] tensors (fewer operations)."""
COLUMN_GATHER_MIN = 16384
"""Road-edge segment columns (``edge_grid``) are gathered a column at a time from this many
segment indices on (0.60 against 1.08 ms for 284,000: no [5, ...] int64 index is built), in
one gather below (fewer operations: 21 against 31 us for 1,000)."""
DENSE_DYNAMICS_MAX_SLOTS = 4096
"""``sim.core.step`` integrates every slot of a batch up to this many slots (B N): a few
operations on [B, N] cost less than gathering the moving agents; beyond, with the movers known
(the external agents when the NPCs replay the log), only those integrate."""
VALID_FIRST_MIN_QUERIES = 8
"""Query agents per row from which their agent pairs are measured over each row's valid slots
(``torch_utils.valid_first``) instead of every slot."""
MALLOC_MMAP_THRESHOLD = 32 << 20
"""Bytes: glibc serves blocks up to this from the heap instead of fresh mmaps
(``tbsim_env.core.malloc``; glibc's largest allowed value on 64-bit systems)."""
MALLOC_TRIM_THRESHOLD = 256 << 20
"""Bytes of free memory at the top of the heap that glibc keeps instead of returning it to
the operating system (``tbsim_env.core.malloc``)."""

# Off-road check of the environment (tbsim_env.sim.edge_grid).
EDGE_GRID_CELL = 2.0
"""m, cell size of the per-scenario road-edge grid: about 0.2% of the box corners of real
scenes fall where a cell's list cannot vouch for them (4 m: 3.5%); 1-2 MB per real scene."""
EDGE_GRID_CANDIDATES = 16
"""Road-edge segments listed per grid cell (nearest to the cell centre first)."""
EDGE_GRID_MARGIN = 20.0
"""m the grid extends beyond the road edges' bounding box (points beyond use the border cell,
and are recomputed over every segment when its list cannot vouch for them)."""
EDGE_GRID_CACHE_SCENES = 32
"""Per-scenario grids kept (by their segments' bytes; least recently used dropped first): an
environment built again on the same scenes (another traffic mode of the benchmark, another
env in a test session) reuses them (~50 ms each for a real scene)."""
EDGE_SIMPLIFY_TOLERANCE = 0.02
"""m, road-edge polylines are simplified (Douglas-Peucker) to within this distance for the
environment's off-road check (about 10x fewer segments; the WOSAC metric uses them as logged)."""
COMPILE_CPU_MAX_BATCH = 64
"""Scenarios per batch up to which ``compile=True`` steps through the ``torch.compile`` graph on
the CPU (and ``COMPILE_CPU_MAX_OBSERVERS`` controlled agents at most); larger batches step
eagerly (``compile="always"`` forces the graph). The graph cannot take the eager step's
shortcuts (near pairs, valid slots, the grid's map pieces), so it wins only where per-operation
overhead dominates. Compiled / eager agent steps/s on the 2-core AMD EPYC machine (one thread,
log replay, indexed observations; ``bench/vector_env.py --compile``), SDC controlled, real
samples: 2.52x at B = 1, 2.28x at B = 16, 1.36x at B = 64, 0.90x at B = 256 (generated: 2.94x,
1.80x, 1.32x, 0.89x); all agents controlled (~50 a scene, real) 1.13x at B = 1, 0.51x at
B = 16, 0.42x at B = 64."""
COMPILE_CPU_MAX_OBSERVERS = 64
"""Controlled agents of a batch up to which ``compile=True`` takes the graph on the CPU (see
``COMPILE_CPU_MAX_BATCH``)."""
OFFROAD_RECOMPUTE_BUDGET = 256
"""Box corners per step a compiled graph recomputes at most over every road-edge segment when
the grid cannot vouch for them (eagerly: all of them); a step with more is redone eagerly.
Below that, one corner in ``OFFROAD_RECOMPUTE_SHARE`` and at least ``OFFROAD_RECOMPUTE_MIN``:
the grid vouches for all but a few (eagerly, 200 steps of B = 64: at most 37 of 21,504 corners
with every agent controlled, 22 of 256 with the SDC; none on the real samples with the SDC),
and each recomputed corner costs every segment of its scene (a fixed budget of 256 was half of
a compiled SDC step at B = 64 on the real samples)."""
OFFROAD_RECOMPUTE_SHARE = 8
"""See ``OFFROAD_RECOMPUTE_BUDGET``."""
OFFROAD_RECOMPUTE_MIN = 32
"""See ``OFFROAD_RECOMPUTE_BUDGET``."""
NO_EDGE_DISTANCE = -1.0e10
"""m, off-road distance reported when a scenario has no road edge (always on-road)."""
