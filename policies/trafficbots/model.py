"""The TrafficBots V1.5 network and its explicit-state single-step API (docs/model.md §3, §5).

``prepare`` runs everything that is computed once per scenario (``encode_scene``: map
encoding, TL precompute, destination distribution, the encoders' attention keys and values of
the map; the posterior) and draws the per-rollout samples (z, destinations);
``step`` consumes the current simulator state of every agent, updates the 11-step history held
in an explicit ``RolloutState`` and returns physical actions. Nothing is cached on the module,
so one model can drive any number of rollouts.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Literal

import torch
from torch import nn

from policies.trafficbots.action_head import ActionHead
from policies.trafficbots.agent_encoder import AgentContext, AgentEncoder, agent_attributes
from policies.trafficbots.batch import TokenBatch
from policies.trafficbots.config import InferenceConfig, TrafficBotsConfig
from policies.trafficbots.destination import (
    DestinationEncoder,
    DestinationPredictor,
    destination_reached,
)
from policies.trafficbots.latent import AddNaviLatent, Posterior
from policies.trafficbots.map_encoder import MapEncoder, MapTokens
from policies.trafficbots.road_keeping import keep_on_road
from policies.trafficbots.rules import (
    clip_history_motion,
    hold_action,
    keep_gap,
    limit_vehicle_curvature,
    parked_vehicles,
    smooth_yaw_rate,
)
from policies.trafficbots.tl_encoder import TLContext, TLEncoder, TLStateHead, tl_context
from tbsim_env.core import constants as C
from tbsim_env.observation.map_knn import PieceClusters, build_piece_clusters, clusters_pay
from tbsim_env.observation.rows import take_rows
from tbsim_env.sim.dynamics import squash_action
from tbsim_env.sim.geometry import wrap_angle


def randn(
    shape: tuple[int, ...], generator: torch.Generator | None, device: torch.device
) -> torch.Tensor:
    """Standard normal samples drawn on the generator's device, then moved (device-agnostic
    seeding: a CPU generator gives the same numbers whatever device the model is on)."""
    gen_device = generator.device if generator is not None else torch.device("cpu")
    return torch.randn(shape, generator=generator, device=gen_device).to(device)


def rand(
    shape: tuple[int, ...], generator: torch.Generator | None, device: torch.device
) -> torch.Tensor:
    """Uniform [0, 1) samples, drawn like ``randn``."""
    gen_device = generator.device if generator is not None else torch.device("cpu")
    return torch.rand(shape, generator=generator, device=gen_device).to(device)


def _repeat(scene: SceneEncoding, n: int) -> SceneEncoding:
    """Each row of ``scene`` ``n`` times in a row (scene-major rollouts)."""
    if n == 1:
        return scene
    b = scene.dest_logits.shape[0]
    return take_rows(scene, torch.arange(b, device=scene.dest_logits.device).repeat_interleave(n))


@dataclass(frozen=True)
class PrepareMode:
    """How ``TrafficBots.prepare`` draws a rollout's latent and destinations.

    Attributes:
        latent: z from the N(0, I) prior, a posterior sample or the posterior mean.
        dest: sample destinations from the predictor or use the ground-truth labels.
        tl_valid_from: TL token validity from history steps (inference) or all steps.
        with_posterior: compute the posterior even when z comes from the prior (for KL).
        input_dropout_p: training-mode input dropout of docs/model.md §1.9 (``dropout_p_history``):
            map nodes 1..P-1 are hidden from the map encoder and history steps 0..9 from the
            destination predictor, each with this probability. Ignored in eval mode.
    """

    latent: Literal["prior", "posterior", "posterior_mean"] = "prior"
    dest: Literal["sample", "gt"] = "sample"
    tl_valid_from: Literal["history", "full"] = "history"
    with_posterior: bool = False
    input_dropout_p: float = 0.0


INFERENCE = PrepareMode()
"""Spec inference: z from the prior, sampled destinations, TL validity from the history."""


@dataclass(frozen=True)
class SceneEncoding:
    """What ``prepare`` derives from the scenes alone, batch B (one row per scene).

    In eval mode it is a function of the scene (and the ``PrepareMode``'s TL validity rule),
    so callers that start many rollouts from a fixed set of scenes compute it once per scene
    and pass it back to ``prepare`` (``TrafficBotsPolicy``'s restart cache).

    Attributes:
        mp: encoded map.
        tl: static TL tensors.
        dest_logits: [B, N, M] destination logits.
        dest_usable: [B, N] bool.
        ag_map_kv: the agent encoder's keys and values of the map, [B, M, 2d] per layer.
        tl_map_kv: the TL encoder's, likewise.
        map_clusters: the map pieces' ``PieceClusters`` for the agents' nearest-piece search
            (eval mode on the CPU, maps large enough for it to pay), else None.
    """

    mp: MapTokens
    tl: TLContext
    dest_logits: torch.Tensor
    dest_usable: torch.Tensor
    ag_map_kv: tuple[torch.Tensor, ...]
    tl_map_kv: tuple[torch.Tensor, ...]
    map_clusters: PieceClusters | None


@dataclass(frozen=True)
class RolloutContext:
    """Per-rollout constants, batch B' = B scenes * n_rollouts (scene-major).

    Attributes:
        scene: the scenes' ``SceneEncoding``, each row repeated for its rollouts.
        ag_type: [B', N] ``ObjectType``.
        ag_attr: [B', N, 6].
        z: [B', N, Z] personality latent.
        z_valid: [B', N] bool.
        dest: [B', N] int64 destination map rows.
        dest_valid: [B', N] bool.
        n_rollouts: rollouts per scene.
        post_mean: [B, N, Z] posterior mean, or None if the posterior was not computed.
        post_log_std: [B, N, Z] or None.
        post_valid: [B, N] bool or None.
        hold: [B', N] bool agents held at rest (``InferenceConfig.hold_parked``), or None.
        action_eps: [B', N, S, 2] standard normal draws of the action noise
            (``InferenceConfig.action_sigma``; S = ``n_steps``, step t uses row t mod S), or
            None for mean actions.
    """

    scene: SceneEncoding
    ag_type: torch.Tensor
    ag_attr: torch.Tensor
    z: torch.Tensor
    z_valid: torch.Tensor
    dest: torch.Tensor
    dest_valid: torch.Tensor
    n_rollouts: int
    post_mean: torch.Tensor | None = None
    post_log_std: torch.Tensor | None = None
    post_valid: torch.Tensor | None = None
    hold: torch.Tensor | None = None
    action_eps: torch.Tensor | None = None

    @property
    def mp(self) -> MapTokens:
        """The encoded map of every rollout."""
        return self.scene.mp

    @property
    def tl(self) -> TLContext:
        """The static TL tensors of every rollout."""
        return self.scene.tl

    def per_scene(self) -> SceneEncoding:
        """The ``SceneEncoding`` of these rollouts' scenes (row i: scene i)."""
        n = self.n_rollouts
        if n == 1:
            return self.scene
        rows = torch.arange(0, self.ag_type.shape[0], n, device=self.ag_type.device)
        return take_rows(self.scene, rows)


@dataclass(frozen=True)
class RolloutState:
    """Everything the policy remembers between steps (the history windows), batch B'.

    The windows are right-aligned: slot W-1 is the newest step; slots never filled are invalid.

    Attributes:
        step: number of simulator states consumed so far.
        hist_valid: [B', N, W] bool.
        hist_pose: [B', N, W, 3] (x, y, yaw).
        hist_motion: [B', N, W, 3] (speed, acceleration, yaw rate).
        hist_tl_state: [B', L, W] int64 ``TLState``.
        hist_tl_present: [B', L, W] bool, the window slot holds a step.
        dest_reached: [B', N] bool, destination conditioning switched off.
        tl_feat: [B', L, d] the TL encoder's features of the last ``step`` (0 before).
        tl_known: [B'] bool, ``tl_feat`` holds the features of the current TL window; False
            until a ``step`` and wherever ``observe`` changed the window since.
    """

    step: int
    hist_valid: torch.Tensor
    hist_pose: torch.Tensor
    hist_motion: torch.Tensor
    hist_tl_state: torch.Tensor
    hist_tl_present: torch.Tensor
    dest_reached: torch.Tensor
    tl_feat: torch.Tensor
    tl_known: torch.Tensor

    def replace(self, **changes) -> RolloutState:
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True)
class StepOutput:
    """Outputs of one policy step.

    Attributes:
        action: [B', N, 2] physical (acceleration m/s^2, yaw rate rad/s), 0 for invalid agents.
        raw_action: [B', N, 2] unbounded action mean before ``squash_action``.
        tl_logits: [B', L, 5] clamped logits of the TL state at the next step.
    """

    action: torch.Tensor
    raw_action: torch.Tensor
    tl_logits: torch.Tensor


def _push(window: torch.Tensor, new: torch.Tensor) -> torch.Tensor:
    """Drop the oldest slot of ``window`` [B, X, W, ...] and append ``new`` [B, X, ...]."""
    return torch.cat([window[:, :, 1:], new[:, :, None]], dim=2)


class TrafficBots(nn.Module):
    """TrafficBots V1.5 (docs/model.md §3), prior encoders and action log-sigma not built.

    Args:
        cfg: network configuration.
        inference: rules applied around the network in eval mode (default: the shipped ones;
            ``InferenceConfig.spec()`` for none). Not part of the checkpoint.
    """

    def __init__(self, cfg: TrafficBotsConfig, inference: InferenceConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg
        self.inference = inference or InferenceConfig()
        d = cfg.hidden_dim
        self.map_encoder = MapEncoder(cfg)
        self.tl_encoder = TLEncoder(cfg, cfg.n_history)
        self.tl_head = TLStateHead(cfg)
        self.agent_encoder = AgentEncoder(cfg, cfg.n_history)
        self.dest_predictor = DestinationPredictor(cfg)
        self.dest_encoder = DestinationEncoder(cfg)
        self.posterior = Posterior(cfg)
        self.add_navi = AddNaviLatent(d, d, cfg.mlp_layers, cfg.dropout)
        self.add_latent = AddNaviLatent(cfg.latent_dim, d, cfg.mlp_layers, cfg.dropout)
        self.action_head = ActionHead(cfg)

    @property
    def device(self) -> torch.device:
        return next(self.parameters()).device

    def num_parameters(self) -> int:
        """Parameter count (every parameter of this module is used)."""
        return sum(p.numel() for p in self.parameters())

    # ------------------------------------------------------------------ once per scenario
    def prepare(
        self,
        batch: TokenBatch,
        n_rollouts: int = 1,
        generator: torch.Generator | None = None,
        mode: PrepareMode = INFERENCE,
        scene: SceneEncoding | None = None,
    ) -> RolloutContext:
        """Per-scenario precomputation and per-rollout sampling (docs/model.md §5.1, §6.1, §7.1).

        Args:
            batch: B scenes.
            n_rollouts: rollouts per scene; map/TL tensors are repeated (scene-major).
            generator: random source for z and destination samples.
            mode: how the latent and destinations are drawn (``PrepareMode``).
            scene: these scenes' ``SceneEncoding``, computed before in eval mode with the
                same ``mode`` (``RolloutContext.scene``): skips the map encoder, the TL
                precompute and the destination predictor, all of ``prepare``'s network work
                at inference. Ignored in training mode.

        Returns:
            ``RolloutContext`` with batch B * n_rollouts.
        """
        if scene is None or self.training:
            scene = self.encode_scene(batch, generator, mode)
        mp, tl = scene.mp, scene.tl
        attr = agent_attributes(batch.ag_type, batch.ag_size)
        post_mean = post_log_std = post_valid = None
        if mode.latent != "prior" or mode.with_posterior:
            post_mean, post_log_std, post_valid = self.posterior(
                batch.ag_valid, batch.ag_pose, batch.ag_motion, attr, batch.tl_state, mp, tl
            )
        n = n_rollouts
        h_valid = batch.ag_valid[..., : self.cfg.n_history]
        post = (post_mean, post_log_std, post_valid)
        z, z_valid = self._sample_latent(batch, n, generator, mode.latent, post, h_valid)
        if mode.dest == "gt":
            dest_idx = batch.ag_dest.repeat_interleave(n, 0)
            dest_valid = (batch.ag_valid.any(-1) & (batch.ag_dest >= 0)).repeat_interleave(n, 0)
        else:
            dest_idx = self._sample_destinations(batch, n, generator, scene.dest_logits)
            dest_valid = scene.dest_usable.repeat_interleave(n, 0)
        return RolloutContext(
            scene=_repeat(scene, n),
            ag_type=batch.ag_type.repeat_interleave(n, 0),
            ag_attr=attr.repeat_interleave(n, 0),
            z=z,
            z_valid=z_valid,
            dest=dest_idx,
            dest_valid=dest_valid,
            n_rollouts=n,
            post_mean=post_mean,
            post_log_std=post_log_std,
            post_valid=post_valid,
            hold=self._hold_mask(batch, n),
            action_eps=self._action_noise(batch, n, generator),
        )

    def encode_scene(
        self,
        batch: TokenBatch,
        generator: torch.Generator | None = None,
        mode: PrepareMode = INFERENCE,
    ) -> SceneEncoding:
        """Map encoder, TL precompute and destination predictor on B scenes (docs/model.md §5.1),
        with ``mode``'s input dropout in training (drawn from ``generator``)."""
        n_hist = self.cfg.n_history
        enc_node_valid, dest_hist_valid = batch.mp_valid, batch.ag_valid[..., :n_hist]
        if self.training and mode.input_dropout_p > 0.0:
            enc_node_valid, dest_hist_valid = self._input_dropout(
                batch, generator, mode.input_dropout_p
            )
        mp = self.map_encoder(batch.mp_pose, enc_node_valid, batch.mp_cls)
        mp = dataclasses.replace(mp, node_valid=batch.mp_valid)  # true nodes for the rules
        tl_src = batch.tl_valid if mode.tl_valid_from == "full" else batch.tl_valid[..., :n_hist]
        tl = tl_context(self.cfg, batch.tl_piece, tl_src.any(-1), mp)
        attr = agent_attributes(batch.ag_type, batch.ag_size)
        dest_logits, dest_usable = self._predict_destinations(batch, dest_hist_valid, attr, mp)
        ag_map_kv = self.agent_encoder.map_kv(mp.feat)
        tl_map_kv = self.tl_encoder.map_kv(mp.feat)
        clusters = None
        if not self.training and mp.pose.device.type == "cpu" and clusters_pay(mp.pose.shape[1]):
            # Fixed shapes, so that single scenes' encodings join into batches (restarts).
            clusters = build_piece_clusters(mp.pose[..., :2], mp.valid, fixed_shape=True)
        return SceneEncoding(mp, tl, dest_logits, dest_usable, ag_map_kv, tl_map_kv, clusters)

    def _input_dropout(
        self, batch: TokenBatch, generator: torch.Generator | None, p: float
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(map node validity for the encoder, history validity for the destination
        predictor) with each map node 1..P-1 and history step 0..9 hidden with probability
        ``p`` (docs/model.md §1.9)."""
        dev, n_hist = batch.device, self.cfg.n_history
        n_sc, n_ag = batch.ag_type.shape
        n_mp, n_node = batch.mp_valid.shape[1:]
        n_ag_pad, n_mp_pad = batch.draw_sizes  # draws are cut to the (trimmed) sizes
        keep = rand((n_sc, n_mp_pad, n_node), generator, dev)[:, :n_mp] >= p
        keep[..., 0] = True  # node 0 (the token pose) is never dropped
        enc_node_valid = batch.mp_valid & keep
        keep = rand((n_sc, n_ag_pad, n_hist), generator, dev)[:, :n_ag] >= p
        keep[..., -1] = True  # the current step is never dropped
        return enc_node_valid, batch.ag_valid[..., :n_hist] & keep

    def _sample_latent(
        self,
        batch: TokenBatch,
        n: int,
        generator: torch.Generator | None,
        latent: str,
        posterior: tuple,
        h_valid: torch.Tensor,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """(z [B * n, N, D], z_valid [B * n, N]): from the N(0, I) prior, a posterior sample
        or the posterior mean (``posterior`` = (mean, log std, valid))."""
        n_sc, n_ag = batch.ag_type.shape
        shape = (n_sc * n, batch.draw_sizes[0], self.cfg.latent_dim)
        if latent == "prior":
            z = randn(shape, generator, batch.device)[:, :n_ag]
            if not self.training and self.inference.latent_temperature != 1.0:
                z = z * self.inference.latent_temperature
            return z, h_valid.any(-1).repeat_interleave(n, 0)
        post_mean, post_log_std, post_valid = posterior
        z = post_mean.repeat_interleave(n, 0)
        if latent == "posterior":
            eps = randn(shape, generator, batch.device)[:, :n_ag]
            z = z + post_log_std.exp().repeat_interleave(n, 0) * eps
        return z, post_valid.repeat_interleave(n, 0)

    def _predict_destinations(
        self, batch: TokenBatch, hist_valid: torch.Tensor, attr: torch.Tensor, mp: MapTokens
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The destination predictor on the history (``hist_valid`` [B, N, n_history]):
        (logits [B, N, M], usable [B, N])."""
        h = self.cfg.n_history
        pose, motion = batch.ag_pose[..., :h, :], batch.ag_motion[..., :h, :]
        return self.dest_predictor(hist_valid, pose, motion, attr, batch.ag_type, mp)

    def _sample_destinations(
        self,
        batch: TokenBatch,
        n: int,
        generator: torch.Generator | None,
        dest_logits: torch.Tensor,
    ) -> torch.Tensor:
        """[B * n, N] destination pieces sampled from the predictor by Gumbel-max
        (reproducible from the generator alone; tempered in eval mode)."""
        n_sc, n_ag = batch.ag_type.shape
        n_mp = batch.mp_valid.shape[1]
        n_ag_pad, n_mp_pad = batch.draw_sizes
        logits = dest_logits.detach().repeat_interleave(n, 0)
        if not self.training:
            logits = logits / self.inference.dest_temperature
        u = rand((n_sc * n, n_ag_pad, n_mp_pad), generator, batch.device)[:, :n_ag, :n_mp]
        u = u.clamp(1e-12, 1.0 - 1e-7)
        return (logits - torch.log(-torch.log(u))).argmax(-1)

    def _action_noise(
        self, batch: TokenBatch, n: int, generator: torch.Generator | None
    ) -> torch.Tensor | None:
        """[B * n, N, n_steps, 2] standard normal draws of the action noise in eval mode with
        ``InferenceConfig.action_sigma`` > 0 (drawn after z and the destinations, so those
        are the same with or without it), else None."""
        if self.training or self.inference.action_sigma <= 0.0:
            return None
        n_sc, n_ag = batch.ag_type.shape
        shape = (n_sc * n, batch.draw_sizes[0], self.cfg.n_steps, 2)
        return randn(shape, generator, batch.device)[:, :n_ag]

    def _hold_mask(self, batch: TokenBatch, n: int) -> torch.Tensor | None:
        """[B * n, N] agents held at rest in eval mode (``rules.parked_vehicles``), or None."""
        rules, h = self.inference, self.cfg.n_history
        if self.training or not rules.hold_parked:
            return None
        parked = parked_vehicles(
            batch.ag_valid[..., :h],
            batch.ag_pose[..., :h, :],
            batch.ag_motion[..., :h, 0],
            batch.ag_type,
            (batch.mp_pose, batch.mp_valid, batch.mp_cls),
            rules.still_displacement,
            rules.parked_lane_radius,
        )
        return parked.repeat_interleave(n, 0)

    def _apply_rules(
        self,
        ctx: RolloutContext,
        action: torch.Tensor,
        speed: torch.Tensor,
        now: tuple[torch.Tensor, torch.Tensor],
        state: RolloutState,
    ) -> torch.Tensor:
        """Eval-mode rules of ``InferenceConfig`` on physical actions [B', N, 2]; ``now`` =
        (pose [B', N, 3], valid [B', N]) of the agents at this step, ``state`` the history
        windows with this step appended."""
        rules = self.inference
        size = ctx.ag_attr[..., :2]  # (length, width)
        if rules.yaw_rate_smoothing > 0.0:
            last_ok = state.hist_valid[..., -1] & state.hist_valid[..., -2]
            action = smooth_yaw_rate(
                action, state.hist_motion[..., -1, 2], last_ok, rules.yaw_rate_smoothing
            )
        if rules.gap_keeping is not None:
            action = keep_gap(action, speed, now, (ctx.ag_type, size), rules.gap_keeping)
        if rules.road_keeping is not None:
            agents = (ctx.ag_type, size, ctx.mp)
            action = keep_on_road(action, speed, now, agents, rules.road_keeping)
        if rules.vehicle_max_curvature is not None:
            action = limit_vehicle_curvature(
                action,
                speed,
                ctx.ag_type,
                rules.vehicle_max_curvature,
                rules.vehicle_yaw_rate_slack,
            )
        if ctx.hold is not None:
            action = torch.where(ctx.hold[..., None], hold_action(speed, ctx.ag_type), action)
        return action

    def initial_state(self, ctx: RolloutContext) -> RolloutState:
        """Empty history windows for the rollouts of ``ctx``."""
        n_b, n_ag = ctx.ag_type.shape
        n_tl = ctx.tl.valid.shape[1]
        w, dev = self.cfg.n_history, ctx.ag_type.device
        return RolloutState(
            step=0,
            hist_valid=torch.zeros(n_b, n_ag, w, dtype=torch.bool, device=dev),
            hist_pose=torch.zeros(n_b, n_ag, w, 3, device=dev),
            hist_motion=torch.zeros(n_b, n_ag, w, 3, device=dev),
            hist_tl_state=torch.zeros(n_b, n_tl, w, dtype=torch.long, device=dev),
            hist_tl_present=torch.zeros(n_b, n_tl, w, dtype=torch.bool, device=dev),
            dest_reached=torch.zeros(n_b, n_ag, dtype=torch.bool, device=dev),
            tl_feat=torch.zeros(n_b, n_tl, self.cfg.hidden_dim, device=dev),
            tl_known=torch.zeros(n_b, dtype=torch.bool, device=dev),
        )

    # ------------------------------------------------------------------ every step
    def observe(
        self,
        state: RolloutState,
        ag_pose: torch.Tensor,
        ag_speed: torch.Tensor,
        ag_valid: torch.Tensor,
        tl_state: torch.Tensor,
        tl_present: torch.Tensor | None = None,
    ) -> RolloutState:
        """Append one simulator state to the history windows (no network call).

        Acceleration and yaw rate of the history are finite differences of consecutive valid
        states (what the unicycle produces, and how the ground-truth motion is defined in
        docs/model.md §1.4). Inputs are detached (docs/model.md §6.4).

        Args:
            state: the rollout state.
            ag_pose: [B', N, 3] current (x, y, yaw).
            ag_speed: [B', N] current signed speed m/s.
            ag_valid: [B', N] bool, agent present now.
            tl_state: [B', L] int64 current ``TLState``.
            tl_present: [B'] bool, this step exists for the scene (default all True); used
                when warming up scenes that start at different steps.

        Returns:
            The next ``RolloutState`` (``step`` incremented).
        """
        ag_pose, ag_speed = ag_pose.detach(), ag_speed.detach()
        prev_ok = state.hist_valid[..., -1] & ag_valid
        prev_pose, prev_speed = state.hist_pose[..., -1, :], state.hist_motion[..., -1, 0]
        acc = torch.where(prev_ok, (ag_speed - prev_speed) / C.DT, 0.0)
        yaw_rate = torch.where(prev_ok, wrap_angle(ag_pose[..., 2] - prev_pose[..., 2]) / C.DT, 0.0)
        vmask = ag_valid[..., None].to(ag_pose.dtype)
        motion = torch.stack([ag_speed, acc, yaw_rate], dim=-1) * vmask
        present = torch.ones_like(tl_state, dtype=torch.bool)
        if tl_present is not None:
            present = present & tl_present[:, None]
        tl_window = _push(state.hist_tl_state, tl_state.long())
        tl_window_present = _push(state.hist_tl_present, present)
        # The window is unchanged where every light held its state through it: [B'] bool.
        unchanged = (tl_window == state.hist_tl_state).flatten(1).all(-1)
        unchanged &= (tl_window_present == state.hist_tl_present).flatten(1).all(-1)
        return state.replace(
            step=state.step + 1,
            hist_valid=_push(state.hist_valid, ag_valid),
            hist_pose=_push(state.hist_pose, ag_pose * vmask),
            hist_motion=_push(state.hist_motion, motion),
            hist_tl_state=tl_window,
            hist_tl_present=tl_window_present,
            tl_known=state.tl_known & unchanged,
        )

    def step(
        self,
        ctx: RolloutContext,
        state: RolloutState,
        ag_pose: torch.Tensor,
        ag_speed: torch.Tensor,
        ag_valid: torch.Tensor,
        tl_state: torch.Tensor,
    ) -> tuple[StepOutput, RolloutState]:
        """Append the current simulator state to the history and act (docs/model.md §5.2 steps 1-4).

        Externally controlled agents simply report their real states here, so the policy
        sees them exactly as it sees its own agents.

        Args:
            ctx: from ``prepare``.
            state: from ``initial_state`` or the previous ``step``.
            ag_pose: [B', N, 3] current (x, y, yaw); detached here (docs/model.md §6.4).
            ag_speed: [B', N] current signed speed m/s.
            ag_valid: [B', N] bool, agent present now.
            tl_state: [B', L] int64 current ``TLState``.

        Returns:
            (``StepOutput``, next ``RolloutState``).
        """
        cfg = self.cfg
        state = self.observe(state, ag_pose, ag_speed, ag_valid, tl_state)
        ag_pose = ag_pose.detach()
        vmask = ag_valid[..., None].to(ag_pose.dtype)
        # A scene whose lights all held their state through the window keeps last step's TL
        # features (the encoder's inputs are the same): encoding costs only after a change.
        previous = None if self.training else (state.tl_known, state.tl_feat)
        tl_feat = self.tl_encoder(
            state.hist_tl_state, state.hist_tl_present, ctx.tl, ctx.scene.tl_map_kv, previous
        )
        tl_logits = self.tl_head(tl_feat)
        motion = state.hist_motion
        if not self.training and self.inference.clip_history_motion:
            motion = clip_history_motion(motion, ctx.ag_type)
        feat, tok_pose, tok_valid = self.agent_encoder(
            state.hist_valid,
            state.hist_pose,
            motion,
            ctx.ag_attr,
            AgentContext(
                ctx.mp,
                ctx.scene.ag_map_kv,
                tl_feat,
                ctx.tl.pose,
                ctx.tl.valid,
                ctx.scene.map_clusters,
            ),
        )
        reached = state.dest_reached | (
            destination_reached(ag_pose, ctx.dest, ctx.mp, cfg) & ctx.dest_valid & ag_valid
        )
        navi_valid = ctx.dest_valid & ~reached & tok_valid
        x = self.add_navi(feat, self.dest_encoder(tok_pose, ctx.dest, ctx.mp), navi_valid)
        x = self.add_latent(x, ctx.z, ctx.z_valid & tok_valid)
        raw = self.action_head(x, ctx.ag_type)
        sample = raw
        if not self.training and ctx.action_eps is not None:
            eps = ctx.action_eps[:, :, (state.step - 1) % ctx.action_eps.shape[2]]
            sample = raw + self.inference.action_sigma * eps
        action = squash_action(sample, ctx.ag_type)
        if not self.training:
            action = self._apply_rules(ctx, action, ag_speed, (ag_pose, ag_valid), state)
        action = action * vmask
        known = torch.ones_like(state.tl_known)
        nxt = state.replace(dest_reached=reached, tl_feat=tl_feat.detach(), tl_known=known)
        return StepOutput(action, raw, tl_logits), nxt
