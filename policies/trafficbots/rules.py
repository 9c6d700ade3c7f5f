"""Inference-side rules around the TrafficBots network, each a measured deviation from the spec.

The shipped small model, trained mostly on generated scenes, moves vehicles that stand parked
in real WOMD logs (it creeps them forward and turns them on the spot) and does not yield to
the traffic ahead of it (docs/MODEL_CARD.md, "Why it leaves real roads"). These rules, applied
in eval mode only (``TrafficBots.training`` False), act on the network's actions without
retraining (the first two are shipped):

* **Hold parked vehicles.** A vehicle that is *parked* by the spec's own test (docs/model.md §1.6,
  filters c and d: still over the history, i.e. the speed summed over the valid history steps
  times 0.1 s below 0.5 m, and no vehicle-lane node, classes 0-2, within 3 m whose direction
  points along its heading) gets the action that stops it and keeps its heading. The spec
  drops such vehicles from the simulation when a scene has more than 64 agents and then moves
  them at constant velocity, which for a still vehicle is holding it; here the rule applies to
  every scene, and the held vehicle stays a token the other agents see. Unlike the spec's
  filter it also holds relevant vehicles (the held vehicle is scored as any other). A vehicle
  queued in a lane is not parked by this test and stays driven by the network.
* **Keep a gap** (``gap_keeping_cap``, ``keep_gap``). A vehicle's acceleration is capped by
  the Intelligent Driver Model's interaction term with the agent ahead of it in its straight
  corridor, so it brakes for slower or standing traffic; the yaw rate stays the network's.
* **No turning on the spot** (off in the shipped config: no measurable gain). A vehicle's yaw
  rate is limited to ``vehicle_max_curvature`` times its speed over the step (plus
  ``vehicle_yaw_rate_slack``): the unicycle (docs/model.md §4) lets a standing vehicle turn, which a
  car cannot.
* **History motion inside the action limits** (``clip_history_motion``, off).

``InferenceConfig.spec()`` switches every rule off (the spec's behaviour, for comparison).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from tbsim_env.core import constants as C
from tbsim_env.sim.dynamics import action_limits
from tbsim_env.sim.geometry import to_local_xy
from tbsim_env.sim.idm import IDMTerms, interaction

if TYPE_CHECKING:
    from policies.trafficbots.config import GapKeeping

_VEHICLE_LANE_CLASSES = (
    int(C.MapClass.FREEWAY),
    int(C.MapClass.SURFACE_STREET),
    int(C.MapClass.STOP_SIGN),
)
"""Map classes that count as a vehicle lane in the parked test.

docs/model.md §1.6 d: classes 0-2."""


def still_agents(ag_valid: torch.Tensor, ag_speed: torch.Tensor, threshold: float) -> torch.Tensor:
    """Agents still over the history: sum over valid steps of |speed| * DT below ``threshold``.

    Args:
        ag_valid: [B, N, H] bool history validity.
        ag_speed: [B, N, H] signed speed m/s.
        threshold: metres (docs/model.md §1.6 c at validation / test: 0.5 m).

    Returns:
        [B, N] bool, True only for agents valid at the last history step.
    """
    travelled = (ag_speed.abs() * ag_valid).sum(-1) * C.DT
    return (travelled < threshold) & ag_valid[..., -1]


def aligned_lane_nearby(
    pose: torch.Tensor,
    mp_pose: torch.Tensor,
    mp_valid: torch.Tensor,
    mp_cls: torch.Tensor,
    radius: float,
) -> torch.Tensor:
    """Whether a vehicle-lane node lies within ``radius`` whose direction points along the pose.

    Computed one scene at a time (the node distances of a scene are [N, M, P]).

    Args:
        pose: [B, N, 3] (x m, y m, yaw rad) at the current step.
        mp_pose: [B, M, P, 3] map nodes (x m, y m, segment heading rad).
        mp_valid: [B, M, P] bool.
        mp_cls: [B, M] int64 ``MapClass``.
        radius: metres (docs/model.md §1.6 d: 3 m).

    Returns:
        [B, N] bool.
    """
    lane = torch.zeros_like(mp_cls, dtype=torch.bool)
    for c in _VEHICLE_LANE_CLASSES:
        lane |= mp_cls == c
    node_ok = (mp_valid & lane[..., None]).flatten(1)  # [B, M*P]
    nodes = mp_pose.flatten(1, 2)  # [B, M*P, 3]
    out = []
    for b in range(pose.shape[0]):
        pts = nodes[b][node_ok[b]]  # [K, 3]
        d2 = ((pose[b, :, None, :2] - pts[None, :, :2]) ** 2).sum(-1)  # [N, K]
        aligned = torch.cos(pts[None, :, 2] - pose[b, :, None, 2]) > 0.0
        out.append(((d2 < radius**2) & aligned).any(-1))
    return torch.stack(out)


def parked_vehicles(
    ag_valid: torch.Tensor,
    ag_pose: torch.Tensor,
    ag_speed: torch.Tensor,
    ag_type: torch.Tensor,
    map_nodes: tuple[torch.Tensor, torch.Tensor, torch.Tensor],
    still_threshold: float,
    lane_radius: float,
) -> torch.Tensor:
    """Vehicles parked by the spec's test (docs/model.md §1.6 c + d) over the history window.

    Args:
        ag_valid: [B, N, H] bool history validity (H = the 11 history steps).
        ag_pose: [B, N, H, 3] history poses.
        ag_speed: [B, N, H] signed speeds m/s.
        ag_type: [B, N] ``ObjectType``.
        map_nodes: (mp_pose [B, M, P, 3], mp_valid [B, M, P], mp_cls [B, M]).
        still_threshold: metres travelled over the history below which an agent is still.
        lane_radius: metres; a still vehicle with an aligned lane node this near is queued.

    Returns:
        [B, N] bool.
    """
    still = still_agents(ag_valid, ag_speed, still_threshold)
    vehicle = ag_type == int(C.ObjectType.VEHICLE)
    candidate = still & vehicle
    if not bool(candidate.any()):
        return candidate
    mp_pose, mp_valid, mp_cls = map_nodes
    on_lane = aligned_lane_nearby(ag_pose[..., -1, :], mp_pose, mp_valid, mp_cls, lane_radius)
    return candidate & ~on_lane


def hold_action(speed: torch.Tensor, ag_type: torch.Tensor) -> torch.Tensor:
    """The action that brings an agent to rest in one step and keeps its heading.

    Args:
        speed: [B, N] signed speed m/s.
        ag_type: [B, N] ``ObjectType`` (acceleration limited to the type's maximum).

    Returns:
        [B, N, 2] (acceleration m/s^2, yaw rate 0 rad/s).
    """
    max_acc = action_limits(ag_type)[0].to(speed.dtype)
    acc = torch.maximum(torch.minimum(-speed / C.DT, max_acc), -max_acc)
    return torch.stack([acc, torch.zeros_like(acc)], dim=-1)


def limit_vehicle_curvature(
    action: torch.Tensor,
    speed: torch.Tensor,
    ag_type: torch.Tensor,
    max_curvature: float,
    slack: float,
) -> torch.Tensor:
    """Vehicle yaw rates limited to ``max_curvature`` * |mean speed over the step| + ``slack``.

    The mean speed is the unicycle's midpoint speed, v + DT / 2 * acceleration (docs/model.md §4).

    Args:
        action: [B, N, 2] (acceleration m/s^2, yaw rate rad/s).
        speed: [B, N] signed speed m/s at the start of the step.
        ag_type: [B, N] ``ObjectType``; other types are returned unchanged.
        max_curvature: 1/m.
        slack: rad/s allowed whatever the speed.

    Returns:
        [B, N, 2] the limited action.
    """
    mid = (speed + 0.5 * C.DT * action[..., 0]).abs()
    cap = max_curvature * mid + slack
    yaw = torch.maximum(torch.minimum(action[..., 1], cap), -cap)
    vehicle = ag_type == int(C.ObjectType.VEHICLE)
    return torch.stack([action[..., 0], torch.where(vehicle, yaw, action[..., 1])], dim=-1)


def gap_keeping_cap(
    pose: torch.Tensor,
    speed: torch.Tensor,
    valid: torch.Tensor,
    size: torch.Tensor,
    gap: GapKeeping,
) -> torch.Tensor:
    """The acceleration above which each agent would close on the agent ahead of it (IDM).

    Agent j is *ahead* of agent i when its box reaches into i's straight corridor (i's width
    plus ``gap.lateral_margin`` on each side) in front of i, within ``gap.horizon`` metres.
    With s the bumper gap to the nearest such agent (at least ``gap.min_gap``), v = i's speed
    and dv = v minus j's velocity along i's heading, the Intelligent Driver Model's
    interaction term gives the cap

        a_max (1 - (s* / s)^2),  s* = s0 + max(0, v T + v dv / (2 sqrt(a_max b)))

    with a_max = ``gap.max_accel``, b = ``gap.comfort_decel``, T = ``gap.time_headway``,
    s0 = ``gap.standstill_gap`` (Treiber, Hennecke & Helbing 2000; ``tbsim_env.sim.idm``, the
    one IDM implementation, shared with the ``idm`` policy). +inf where nothing is ahead.

    Args:
        pose: [B, N, 3] (x m, y m, yaw rad) now.
        speed: [B, N] signed speed m/s.
        valid: [B, N] bool.
        size: [B, N, 2] (length, width) m.
        gap: the rule's parameters.

    Returns:
        [B, N] m/s^2.
    """
    yaw = pose[..., 2]
    # j's centre in i's frame, [B, i, j]: along (ahead) and across i's heading.
    ahead, side = to_local_xy(pose[:, None, :, 0], pose[:, None, :, 1], pose[:, :, None])
    rel = yaw[:, None, :] - yaw[:, :, None]
    cos_rel = torch.cos(rel)
    rc, rs = cos_rel.abs(), torch.sin(rel).abs()
    length, width = size[..., 0], size[..., 1]
    # Half extents of j's box along and across i's heading.
    j_along = 0.5 * (length[:, None, :] * rc + width[:, None, :] * rs)
    j_across = 0.5 * (length[:, None, :] * rs + width[:, None, :] * rc)
    bumper = ahead - 0.5 * length[..., None] - j_along
    in_lane = side.abs() < 0.5 * width[..., None] + j_across + gap.lateral_margin
    # An agent is not ahead of itself: its own ``ahead`` is 0.
    pair = valid[:, :, None] & valid[:, None, :]
    blocked = pair & in_lane & (ahead > 0) & (bumper < gap.horizon)
    s_gap, lead = torch.where(blocked, bumper, float("inf")).min(-1)  # [B, N] each
    lead_speed = (speed[:, None, :] * cos_rel).gather(-1, lead[..., None])[..., 0]
    terms = IDMTerms(gap.max_accel, gap.comfort_decel, gap.time_headway, gap.standstill_gap)
    return interaction(speed, s_gap, lead_speed, terms, gap.min_gap)


def keep_gap(
    action: torch.Tensor,
    speed: torch.Tensor,
    now: tuple[torch.Tensor, torch.Tensor],
    agents: tuple[torch.Tensor, torch.Tensor],
    gap: GapKeeping,
) -> torch.Tensor:
    """Vehicle accelerations capped by ``gap_keeping_cap`` (never below the type's braking
    limit); other agents' actions and every yaw rate unchanged.

    Args:
        action: [B, N, 2] (acceleration m/s^2, yaw rate rad/s).
        speed: [B, N] signed speed m/s.
        now: (pose [B, N, 3], valid [B, N] bool) of every agent at this step.
        agents: (``ObjectType`` [B, N], (length, width) [B, N, 2] m).
        gap: the rule's parameters.

    Returns:
        [B, N, 2].
    """
    ag_type, size = agents
    cap = gap_keeping_cap(now[0], speed, now[1], size, gap)
    max_acc = action_limits(ag_type)[0].to(action.dtype)
    capped = torch.maximum(torch.minimum(action[..., 0], cap), -max_acc)
    vehicle = ag_type == int(C.ObjectType.VEHICLE)
    return torch.stack([torch.where(vehicle, capped, action[..., 0]), action[..., 1]], dim=-1)


def smooth_yaw_rate(
    action: torch.Tensor, last_yaw_rate: torch.Tensor, last_ok: torch.Tensor, weight: float
) -> torch.Tensor:
    """Yaw rates mixed with the last step's: (1 - weight) * action's + weight * last.

    The shipped network, driving in closed loop, answers its own last yaw rate with one of the
    opposite sign: moving vehicles zigzag step to step (docs/model_card/kinematics.md).
    Mixing in the last step's yaw rate (a first-order low-pass of the applied yaw rate) damps
    that period-2 mode and leaves a steady turn as it is.

    Args:
        action: [B, N, 2] (acceleration m/s^2, yaw rate rad/s).
        last_yaw_rate: [B, N] rad/s, the yaw rate of the step that led to the current state.
        last_ok: [B, N] bool, that step exists (the agent was valid before and now).
        weight: in [0, 1).

    Returns:
        [B, N, 2]; the acceleration unchanged, the yaw rate unchanged where not ``last_ok``.
    """
    mixed = (1.0 - weight) * action[..., 1] + weight * last_yaw_rate.to(action.dtype)
    yaw = torch.where(last_ok, mixed, action[..., 1])
    return torch.stack([action[..., 0], yaw], dim=-1)


def clip_history_motion(motion: torch.Tensor, ag_type: torch.Tensor) -> torch.Tensor:
    """History (speed, acceleration, yaw rate) with the last two inside the type's action limits.

    The history's acceleration and yaw rate are finite differences of the logged states
    (docs/model.md §1.4); on real logs they exceed what the unicycle can do (|acc| > 5 m/s^2 in
    about 1% of vehicle steps), which no closed-loop step of the policy ever produces.

    Args:
        motion: [B, N, W, 3] (speed m/s, acceleration m/s^2, yaw rate rad/s).
        ag_type: [B, N] ``ObjectType``.

    Returns:
        [B, N, W, 3].
    """
    max_acc, max_yaw = (x.to(motion.dtype)[..., None] for x in action_limits(ag_type))
    acc = torch.maximum(torch.minimum(motion[..., 1], max_acc), -max_acc)
    yaw = torch.maximum(torch.minimum(motion[..., 2], max_yaw), -max_yaw)
    return torch.stack([motion[..., 0], acc, yaw], dim=-1)
