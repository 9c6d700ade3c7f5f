"""All WOSAC per-step features of a set of trajectories, sliced to the future steps.

One function serves the log (R = 1, logged validity) and the simulations (R rollouts) alike, as
the official ``compute_metric_features`` does (docs/metrics.md, "Trajectories").
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from tbsim_env.metrics.wosac.features_interactive import (
    distance_to_nearest_object,
    time_to_collision,
)
from tbsim_env.metrics.wosac.features_kinematic import kinematic_features
from tbsim_env.metrics.wosac.features_map import (
    RoadEdgeSegments,
    TrafficLightMap,
    distance_to_road_edge,
    traffic_light_violation,
)
from tbsim_env.metrics.wosac.trajectories import ObjectTrajectories


@dataclass(frozen=True)
class MetricFeatures:
    """Per-step features of the evaluated objects over the future steps, [R, E, F] each.

    Attributes:
        linear_speed: m/s.
        linear_acceleration: m/s^2.
        angular_speed: rad/s.
        angular_acceleration: rad/s^2.
        distance_to_nearest_object: m (1e10 without a valid partner).
        collision_per_step: bool, distance < 0.
        time_to_collision: s.
        distance_to_road_edge: m (-1e10 for invalid objects).
        offroad_per_step: bool, distance > 0.
        traffic_light_violation_per_step: bool.
    """

    linear_speed: torch.Tensor
    linear_acceleration: torch.Tensor
    angular_speed: torch.Tensor
    angular_acceleration: torch.Tensor
    distance_to_nearest_object: torch.Tensor
    collision_per_step: torch.Tensor
    time_to_collision: torch.Tensor
    distance_to_road_edge: torch.Tensor
    offroad_per_step: torch.Tensor
    traffic_light_violation_per_step: torch.Tensor


def compute_metric_features(
    traj: ObjectTrajectories,
    road_edges: RoadEdgeSegments,
    traffic_lights: TrafficLightMap,
    first_future_step: int,
) -> MetricFeatures:
    """Compute every feature on the whole trajectories, then keep steps from the first future one.

    Args:
        traj: [R, N, T] trajectories (history + future), evaluated first.
        road_edges: the scenario's road edges.
        traffic_lights: the scenario's lanes and signals.
        first_future_step: current_index + 1 (11 in WOMD).
    """
    ev = slice(0, traj.num_eval)
    fut = slice(first_future_step, None)
    kin = kinematic_features(traj.x[:, ev], traj.y[:, ev], traj.z[:, ev], traj.heading[:, ev])
    # Only the future steps are needed for the pairwise features; the speeds of TTC use one
    # step of history, so it gets the step before the future too.
    future_traj = slice_steps(traj, slice(first_future_step - 1, None))
    dist_obj = distance_to_nearest_object(slice_steps(traj, fut))
    ttc = time_to_collision(future_traj)[:, :, 1:]
    dist_edge = distance_to_road_edge(slice_steps(traj, fut), road_edges)
    tl = traffic_light_violation(traj, traffic_lights)[:, :, fut]
    return MetricFeatures(
        linear_speed=kin.linear_speed[..., fut],
        linear_acceleration=kin.linear_acceleration[..., fut],
        angular_speed=kin.angular_speed[..., fut],
        angular_acceleration=kin.angular_acceleration[..., fut],
        distance_to_nearest_object=dist_obj,
        collision_per_step=dist_obj < 0.0,
        time_to_collision=ttc,
        distance_to_road_edge=dist_edge,
        offroad_per_step=dist_edge > 0.0,
        traffic_light_violation_per_step=tl,
    )


def slice_steps(traj: ObjectTrajectories, steps: slice) -> ObjectTrajectories:
    """The same objects over a slice of the steps."""
    return ObjectTrajectories(
        x=traj.x[..., steps],
        y=traj.y[..., steps],
        z=traj.z[..., steps],
        heading=traj.heading[..., steps],
        valid=traj.valid[..., steps],
        length=traj.length,
        width=traj.width,
        height=traj.height,
        object_type=traj.object_type,
        num_eval=traj.num_eval,
    )
