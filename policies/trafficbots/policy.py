"""``TrafficBotsPolicy``: the network as a ``policies.base.Policy`` for the simulator/env.

The policy drives the (at most 64) agents that preprocessing selects for each scenario
(``SceneTokens.agent_track_index``); every other agent slot gets a zero action, i.e. keeps its
speed and heading (the constant-velocity treatment of non-simulated agents, docs/model.md §7.4).
Externally controlled agents are observed through the ``SimState`` like any other agent, so
their real states feed back into the policy every step.

All per-rollout memory lives in the returned ``TrafficBotsPolicyState`` (history windows, z,
destinations, agent-slot and signal mappings); the policy object itself is stateless.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from tqdm import tqdm

from policies.trafficbots.batch import TokenBatch
from policies.trafficbots.checkpoint import load_checkpoint
from policies.trafficbots.model import RolloutContext, RolloutState, SceneEncoding, TrafficBots
from tbsim_env.core.config import TokenConfig
from tbsim_env.core.torch_utils import gather_rows
from tbsim_env.data.preprocess import preprocess_scenario
from tbsim_env.data.scenario import Scenario
from tbsim_env.data.tokens import SceneTokens
from tbsim_env.observation.rows import cat_rows, take_rows
from tbsim_env.sim.state import SimState


@dataclass(frozen=True)
class TrafficBotsPolicyState:
    """Per-rollout memory of ``TrafficBotsPolicy``.

    Attributes:
        ctx: the model's per-rollout constants (map, TL, z, destinations).
        rollout: the history windows.
        slot: [B, K] int64 sim agent slot of each token agent (-1: none).
        tl_signal: [B, L] int64 ``SimState.signals`` row of each TL token (-1: none).
        offset: [B, 2] token frame = sim frame + offset (metres).
        tl_pred: [B, L] int64 model prediction of the TL state at the current step, used
            where the simulator has no logged signal state.
    """

    ctx: RolloutContext
    rollout: RolloutState
    slot: torch.Tensor
    tl_signal: torch.Tensor
    offset: torch.Tensor
    tl_pred: torch.Tensor


@dataclass
class SceneCache:
    """What a policy keeps of one scenario (it depends on the scene only).

    Attributes:
        scenario: the scenario object (entries are keyed by its ``id``).
        tokens: its preprocessed ``SceneTokens``.
        encoding: the model's ``SceneEncoding`` of it (map, TL precompute, destination
            distribution, attention keys and values of the map), batch 1 (None until its
            first start).
        rows: the (agents, map pieces, TL tokens) token rows ``encoding`` was computed on
            (a trimmed batch's rows depend on the scenes in it).
    """

    scenario: Scenario
    tokens: SceneTokens
    encoding: SceneEncoding | None = None
    rows: tuple[int, int, int] | None = None


def _match(keys: torch.Tensor, table: torch.Tensor) -> torch.Tensor:
    """Row of ``table`` [B, S] equal to each of ``keys`` [B, K] (-1 when absent or key < 0)."""
    eq = (keys[:, :, None] == table[:, None, :]) & (keys[:, :, None] >= 0)
    return torch.where(eq.any(-1), eq.long().argmax(-1), -1)


class TrafficBotsPolicy:
    """TrafficBots V1.5 NPC policy (prior z, sampled destinations, mean actions).

    Args:
        model: the network (put in eval mode here).
        token_config: preprocessing limits (defaults: 64 agents, 1024 pieces, 128 TLs).
        trim: run the model on the batch's used token rows (``TokenBatch.trim``: the same
            function and samples, fewer FLOPs) instead of the padding up to the limits. The
            policy state's shapes then depend on the scenes, which suits callers that start
            every rollout of a batch together (``TrafficEnv`` sets it). Callers that restart
            one batch row at a time into a state of fixed shapes (``BatchedTrafficEnv``) use
            ``for_scenarios``, which fixes the rows to those of their whole scenario set.
        min_rows: (agents, map pieces, TL tokens) rows that a trimmed batch keeps at least.
        scene_cache: what a restart needs of each scenario this policy will start from
            (``for_scenarios`` fills it): ``id(scenario)`` -> ``SceneCache``, so that a restart
            neither preprocesses the scene again nor reruns the network on it (``SceneEncoding``).
        cache_scenes: also keep the entry of every other scenario it starts (``TrafficEnv``,
            which resets into the same scenes again and again): memory grows with the
            scenes started, by about their preprocessed tokens.
    """

    name = "trafficbots"
    exact_replay = False

    def __init__(
        self,
        model: TrafficBots,
        token_config: TokenConfig | None = None,
        trim: bool = False,
        min_rows: tuple[int, int, int] | None = None,
        scene_cache: dict[int, SceneCache] | None = None,
        cache_scenes: bool = False,
    ) -> None:
        self.model = model.eval()
        self.token_config = token_config or TokenConfig()
        self.trim = trim
        self.min_rows = min_rows
        self.scene_cache = scene_cache or {}
        self.cache_scenes = cache_scenes

    def _entry(self, scenario: Scenario) -> SceneCache:
        """The cache entry of this very scenario object; a new one (kept with
        ``cache_scenes``) if there is none."""
        hit = self.scene_cache.get(id(scenario))
        if hit is not None and hit.scenario is scenario:
            return hit
        entry = SceneCache(scenario, preprocess_scenario(scenario, self.token_config))
        if self.cache_scenes:
            self.scene_cache[id(scenario)] = entry
        return entry

    def for_scenarios(self, scenarios: Sequence[Scenario]) -> TrafficBotsPolicy:
        """This policy with state shapes fixed for any batch drawn from ``scenarios``.

        A trimming policy's state has as many token rows as its batch uses, so restarting one
        row of a running batch with another scene could need other shapes. The returned
        policy trims every batch to the rows that the whole set uses (its ``min_rows``), which
        is still far below the padded limits for most sets. A non-trimming policy is returned
        as it is (its shapes are the limits).

        Args:
            scenarios: every scenario the caller will start rollouts from.
        """
        if not self.trim:
            return self
        rows = [0, 0, 0]
        cache = {}
        for sc in tqdm(scenarios, desc="token rows", disable=len(scenarios) < 256, leave=False):
            tokens = preprocess_scenario(sc, self.token_config)
            cache[id(sc)] = SceneCache(sc, tokens)
            used = TokenBatch.from_tokens(tokens).rows_used()
            rows = [max(a, b) for a, b in zip(rows, used, strict=True)]
        return TrafficBotsPolicy(
            self.model,
            self.token_config,
            trim=True,
            min_rows=tuple(rows),
            scene_cache=cache,
            cache_scenes=self.cache_scenes,
        )

    @classmethod
    def from_checkpoint(
        cls, path: str | Path, map_location: str | torch.device = "cpu"
    ) -> TrafficBotsPolicy:
        """Policy from a ``save_checkpoint`` file pair."""
        return cls(load_checkpoint(path, map_location=map_location))

    @torch.no_grad()
    def initial_state(
        self, state: SimState, scenarios: Sequence[Scenario], generator: torch.Generator
    ) -> TrafficBotsPolicyState:
        """Preprocess the scenarios, prepare the model and warm the history from the log.

        The history windows are filled with the logged states of the (up to) 10 steps before
        ``state.step``; the state at ``state.step`` itself is consumed by the first ``act``.
        """
        dev = state.device
        if dev != self.model.device:
            raise ValueError(f"simulator on {dev} but the TrafficBots model on {self.model.device}")
        entries = [self._entry(sc) for sc in scenarios]
        tokens = [e.tokens for e in entries]
        ctx, batch = self._prepare(entries, generator)
        n_ag, n_tl = batch.ag_type.shape[1], batch.tl_piece.shape[1]
        tok_track = np.stack([t.agent_track_index[:n_ag] for t in tokens])  # trimmed rows
        slot = _match(torch.as_tensor(tok_track, device=dev), state.agents.track_index)
        lane_ids = []
        for t in tokens:
            piece = np.asarray(t.tl_piece[:n_tl])
            lane_ids.append(np.where(piece >= 0, t.map_feature_id[np.maximum(piece, 0)], -1))
        tl_signal = _match(torch.as_tensor(np.stack(lane_ids), device=dev), state.signals.lane_id)
        token_origin = torch.as_tensor(np.stack([t.origin for t in tokens]), device=dev)
        offset = (state.origin.to(torch.float64) - token_origin).to(torch.float32)
        rollout = self.model.initial_state(ctx)
        n_warm = self.model.cfg.n_history - 1
        for k in range(n_warm, 0, -1):
            t = state.step - k  # [B]
            ok = t >= 0
            ti = t.clamp(min=0)
            pose, speed, valid = self._log_agents(state, slot, offset, ti)
            sig = self._log_signals(state, tl_signal, ti, torch.zeros_like(tl_signal))
            rollout = self.model.observe(
                rollout, pose, speed, valid & ok[:, None], sig, tl_present=ok
            )
        tl_pred = torch.zeros_like(tl_signal)
        return TrafficBotsPolicyState(ctx, rollout, slot, tl_signal, offset, tl_pred)

    def _prepare(
        self, entries: list[SceneCache], generator: torch.Generator
    ) -> tuple[RolloutContext, TokenBatch]:
        """The model's context of the entries' scenes (their cached encodings when all were
        computed on these token rows; otherwise computed and cached) and their token batch."""
        batch = TokenBatch.from_tokens([e.tokens for e in entries], device=self.model.device)
        if self.trim:
            batch = batch.trim(self.min_rows)
        rows = (batch.ag_type.shape[1], batch.mp_valid.shape[1], batch.tl_piece.shape[1])
        scene = None
        if all(e.encoding is not None and e.rows == rows for e in entries):
            scene = cat_rows([e.encoding for e in entries])
        ctx = self.model.prepare(batch, 1, generator, scene=scene)
        if scene is None:
            encoding = ctx.per_scene()
            for i, e in enumerate(entries):
                if self.scene_cache.get(id(e.scenario)) is e:  # kept: worth a copy of its row
                    e.encoding = take_rows(encoding, torch.tensor([i], device=batch.device))
                    e.rows = rows
        return ctx, batch

    @staticmethod
    def _log_agents(state: SimState, slot: torch.Tensor, offset: torch.Tensor, t: torch.Tensor):
        """Logged (pose, speed, valid) of the token agents at per-scene steps t [B]."""
        log, rows, tt = state.log, slot.clamp(min=0), t[:, None]
        pose = log.of_slots("pose", rows, tt)  # a gathered copy
        pose[..., :2] += offset[:, None]
        valid = log.of_slots("valid", rows, tt) & (slot >= 0)
        return pose * valid[..., None], log.of_slots("speed", rows, tt) * valid, valid

    @staticmethod
    def _log_signals(
        state: SimState, tl_signal: torch.Tensor, t: torch.Tensor, fallback: torch.Tensor
    ) -> torch.Tensor:
        """Logged TL state per TL token at steps t [B], ``fallback`` where none is logged."""
        b = torch.arange(tl_signal.shape[0], device=tl_signal.device)[:, None]
        rows = tl_signal.clamp(min=0)
        logged = state.signals.state[b, rows, t[:, None]]
        ok = state.signals.valid[b, rows, t[:, None]] & (tl_signal >= 0)
        return torch.where(ok, logged, fallback)

    @torch.no_grad()
    def act(
        self, state: SimState, policy_state: TrafficBotsPolicyState, generator: torch.Generator
    ) -> tuple[torch.Tensor, TrafficBotsPolicyState]:
        """Actions [B, N, 2] for every agent slot (zero for slots the model does not drive)."""
        del generator  # z and destinations were drawn in ``initial_state``.
        ps = policy_state
        rows = ps.slot.clamp(min=0)  # -1 (no slot) reads row 0, masked by ``valid``
        pose = gather_rows(state.pose, rows)  # a new tensor: safe to shift in place
        pose[..., :2] += ps.offset[:, None]
        valid = gather_rows(state.valid, rows) & (ps.slot >= 0)
        speed = gather_rows(state.speed, rows) * valid
        tl = self._log_signals(state, ps.tl_signal, state.step, ps.tl_pred)
        out, rollout = self.model.step(
            ps.ctx, ps.rollout, pose * valid[..., None], speed, valid, tl
        )
        action = torch.zeros(*state.pose.shape[:2], 2, device=state.device)
        b = torch.arange(action.shape[0], device=action.device)[:, None].expand_as(ps.slot)
        driven = ps.slot >= 0
        action[b[driven], ps.slot[driven]] = out.action[driven].to(action.dtype)
        new = dataclasses.replace(ps, rollout=rollout, tl_pred=out.tl_logits.argmax(-1))
        return action, new
