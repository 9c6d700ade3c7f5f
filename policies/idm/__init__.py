"""``idm``: rule-based reactive traffic on real maps.

Every agent follows a route (``route="log"``: its logged path, then the lane graph;
``route="lanes"``: a lane-graph path whose fork branches follow the logged future where there
is one; pedestrians and cyclists their logged path) at the speed of the Intelligent Driver
Model: toward its desired speed (from its history and the lane's speed limit, drawn per
rollout), slower in bends, keeping its gap to the nearest agent of any controller in its
corridor, stopping for red and yellow signals, stop signs (a full stop, then go when the
junction is clear) and pedestrians on a crosswalk ahead. Pure pursuit turns the route into a
yaw rate. Parameters and their sources: ``policies.idm.params``.

The same controller plans for an agent a script drives itself: ``examples/idm_planner.py``.

Modules: ``params`` (settings), ``lanes`` (lane graph, inferred links), ``routes`` (paths),
``stops`` (stop lines and crosswalks along routes), ``plan`` (per-scene precomputation),
``tracking`` (progress, pure pursuit), ``leaders`` (corridor test), ``yielding`` (signals,
stop signs, crosswalks), ``policy`` (``IDMPolicy``).
"""

from __future__ import annotations

from policies.idm.params import CYCLIST, PEDESTRIAN, VEHICLE, IDMConfig, Route, TypeParams
from policies.idm.policy import IDMPolicy, IDMState

__all__ = [
    "CYCLIST",
    "PEDESTRIAN",
    "VEHICLE",
    "IDMConfig",
    "IDMPolicy",
    "IDMState",
    "Route",
    "TypeParams",
]
