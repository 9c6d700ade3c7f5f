"""Training loop of TrafficBots V1.5 (docs/model.md §6): plain PyTorch, DDP through torchrun.

Usage (also ``tbsim train``)::

    tbsim preprocess generated:intersection,merge:0-999 --out cache/gen
    tbsim train --data cache/gen --out runs/small --model small --steps 3000
    torchrun --nproc-per-node 4 -m policies.trafficbots.train --data cache/womd --model paper ...

One optimiser step = one batch of ``batch_size`` scenes per process, a full closed-loop rollout
with back-propagation through time (``losses.training_step``). Teacher forcing decays linearly
from ``teacher_forcing_start`` to ``teacher_forcing_end`` over the run (the spec's 0.3, 0.2, 0.1,
0 per epoch, made continuous), and 10% of batches roll out with the prior personality.
AdamW (2e-4, weight decay 0.1, betas 0.9 / 0.95), gradient clipping 5, mixed precision on CUDA.

Checkpoints (``<out>/last.safetensors`` + ``last.json`` for the model,
``optimizer.safetensors`` + ``optimizer.json`` for the optimiser state and the step) are written
every ``ckpt_every`` steps and at the end; a run restarted with the same ``--out`` resumes.
Scalars go to ``<out>/metrics.jsonl`` and, when ``tensorboard`` is installed, to TensorBoard.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import torch
from safetensors.torch import load_file, save_file
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn
from torch.utils.data import DataLoader, DistributedSampler, RandomSampler
from tqdm import tqdm

from policies.trafficbots.batch import TokenBatch
from policies.trafficbots.checkpoint import load_state_into, save_checkpoint
from policies.trafficbots.config import TrafficBotsConfig
from policies.trafficbots.losses import training_step
from policies.trafficbots.model import TrafficBots
from policies.trafficbots.validate import validation_loss
from tbsim_env.core.config_cli import config_parser, parse_config
from tbsim_env.core.errors import CheckpointError
from tbsim_env.data.cache import open_training_data


@dataclass(frozen=True)
class TrainConfig:
    """Everything a training run depends on (saved as ``<out>/train_config.json``).

    Attributes:
        data: token cache folder (``tbsim preprocess``), or several comma-separated, each
            optionally ``FOLDER*N`` to draw its scenes N times as often.
        out: run folder (checkpoints, metrics).
        model: ``"small"`` or ``"paper"`` preset (``TrafficBotsConfig``).
        steps: optimiser steps.
        batch_size: scenes per process and step.
        lr: AdamW learning rate.
        weight_decay: AdamW weight decay (all parameters, as the spec).
        beta1: AdamW beta 1.
        beta2: AdamW beta 2.
        grad_clip: gradient-norm clip.
        teacher_forcing_start: per-agent teacher-forcing probability at step 0.
        teacher_forcing_end: ... at the last step (linear in between).
        prior_prob: probability of a prior-latent batch.
        amp: float16 autocast with a grad scaler on CUDA (ignored on CPU).
        seed: base seed (each process adds its rank).
        workers: DataLoader worker processes.
        log_every: steps between logged scalars.
        ckpt_every: steps between checkpoints.
        device: ``"auto"`` (CUDA if available), ``"cpu"`` or ``"cuda"``.
        threads: torch intra-op threads on CPU (None: leave torch's default).
        stop_at: end this run at this step (None: at ``steps``); the schedules still span
            ``steps``, so a run cut into segments (preemptible or time-limited machines) follows
            the same schedule as one uninterrupted run.
        cache_shards: cache shards kept in memory per folder (0: all; a random sampler over a
            cache larger than this re-reads a shard for most items).
        rollout_steps: simulate only log steps 0 .. rollout_steps-1 per batch (None: all 91).
            A CPU budget knob (the spec trains on full episodes): 51 = 4 s of closed loop.
        init: start from this checkpoint's weights (base path of ``.safetensors`` + ``.json``,
            e.g. the shipped ``policies/trafficbots/weights/trafficbots_small``) with a fresh
            optimiser at step 0: fine-tuning. Its config must match ``model``. Ignored when
            ``out`` already holds a run to resume.
        warmup_steps: the learning rate rises linearly from ``lr / warmup_steps`` to ``lr`` over
            the first ``warmup_steps`` steps (0: none). A fresh AdamW's first updates are about
            ``lr`` times the sign of the gradient for every weight, so a fine-tune without
            warm-up starts by shaking every weight by ``lr``.
        ema_decay: also keep an exponential moving average of the weights with this decay per
            step (None: none), saved beside ``last`` as ``<out>/ema.safetensors`` + ``.json``.
            With the small batches of a CPU run, single checkpoints move a lot from one to the
            next; the average evens that out (its horizon is about ``1 / (1 - ema_decay)``
            steps).
        val_data: token cache(s) of validation scenes (same syntax as ``data``): the
            validation loss (``policies.trafficbots.validate``) is logged as ``val_*`` every
            ``val_every`` steps and at the end (and at step 0 for the starting weights), and the
            weights (the EMA's when there is one) with the lowest so far are kept as
            ``<out>/best.safetensors`` + ``.json``, their step and scores in ``best_step.json``.
        val_every: steps between validations (0: only at the end).
        time_budget_s: end the run (checkpoint and validation included) once this many seconds
            of training have passed, whatever the step (None: no limit). For a lent machine
            with a fixed wall time; the schedules still span ``steps``.
    """

    data: str
    out: str
    model: str = "small"
    steps: int = 2000
    batch_size: int = 2
    lr: float = 2e-4
    weight_decay: float = 0.1
    beta1: float = 0.9
    beta2: float = 0.95
    grad_clip: float = 5.0
    teacher_forcing_start: float = 0.3
    teacher_forcing_end: float = 0.0
    prior_prob: float = 0.1
    amp: bool = True
    seed: int = 2023
    workers: int = 1
    log_every: int = 10
    ckpt_every: int = 200
    device: str = "auto"
    threads: int | None = None
    rollout_steps: int | None = None
    cache_shards: int = 0
    stop_at: int | None = None
    init: str | None = None
    warmup_steps: int = 0
    ema_decay: float | None = None
    val_data: str | None = None
    val_every: int = 0
    time_budget_s: float | None = None

    def model_config(self) -> TrafficBotsConfig:
        if self.model == "small":
            return TrafficBotsConfig.small()
        if self.model == "paper":
            return TrafficBotsConfig.paper()
        raise ValueError(f"unknown model preset {self.model!r}; use 'small' or 'paper'")

    def teacher_forcing(self, step: int) -> float:
        frac = step / max(self.steps - 1, 1)
        return self.teacher_forcing_start + frac * (
            self.teacher_forcing_end - self.teacher_forcing_start
        )

    def lr_at(self, step: int) -> float:
        """Learning rate of optimiser step ``step`` (0-based): linear warm-up, then constant."""
        if step < self.warmup_steps:
            return self.lr * (step + 1) / self.warmup_steps
        return self.lr


def _collate(items: list) -> list:
    return items


class TrainingObjective(torch.nn.Module):
    """``forward`` = one training rollout and its loss, so ``DistributedDataParallel`` can wrap
    it: DDP synchronises the gradients of whatever its wrapped ``forward`` uses."""

    def __init__(self, model: TrafficBots) -> None:
        super().__init__()
        self.model = model

    def forward(
        self,
        batch: TokenBatch,
        prior_prob: float,
        teacher_forcing_p: float,
        generator: torch.Generator,
        n_steps: int | None,
    ) -> tuple[torch.Tensor, dict[str, float]]:
        return training_step(
            self.model,
            batch,
            prior_prob=prior_prob,
            teacher_forcing_p=teacher_forcing_p,
            generator=generator,
            n_steps=n_steps,
        )


def _optimizer_state_to_files(opt: torch.optim.Optimizer, step: int, path: Path) -> None:
    """Optimiser state as ``<path>.safetensors`` (tensors) + ``<path>.json``. No pickle."""
    sd = opt.state_dict()
    tensors, scalars = {}, {}
    for pid, st in sd["state"].items():
        for k, v in st.items():
            if isinstance(v, torch.Tensor):
                tensors[f"{pid}.{k}"] = v.detach().cpu().contiguous()
            else:
                scalars[f"{pid}.{k}"] = v
    save_file(tensors, f"{path}.safetensors")
    meta = {"step": step, "param_groups": sd["param_groups"], "scalars": scalars}
    Path(f"{path}.json").write_text(json.dumps(meta))


def _optimizer_state_from_files(opt: torch.optim.Optimizer, path: Path) -> int:
    meta = json.loads(Path(f"{path}.json").read_text())
    tensors = load_file(f"{path}.safetensors")
    state: dict[int, dict] = {}
    for key, v in tensors.items():
        pid, name = key.split(".", 1)
        state.setdefault(int(pid), {})[name] = v
    for key, v in meta["scalars"].items():
        pid, name = key.split(".", 1)
        state.setdefault(int(pid), {})[name] = v
    n_params = sum(len(g["params"]) for g in opt.state_dict()["param_groups"])
    if any(pid >= n_params for pid in state):
        raise CheckpointError(f"{path}: optimiser state does not match the model's parameters")
    opt.load_state_dict({"state": state, "param_groups": meta["param_groups"]})
    return int(meta["step"])


class _Logger:
    def __init__(self, out: Path, enabled: bool) -> None:
        self.enabled = enabled
        self.file = open(out / "metrics.jsonl", "a") if enabled else None  # noqa: SIM115
        self.tb = None
        if enabled:
            try:
                from torch.utils.tensorboard import SummaryWriter

                self.tb = SummaryWriter(str(out / "tensorboard"))
            except ImportError:  # tensorboard is optional
                self.tb = None

    def log(self, step: int, scalars: dict[str, float]) -> None:
        if not self.enabled:
            return
        self.file.write(json.dumps({"step": step, **scalars}) + "\n")
        self.file.flush()
        if self.tb is not None:
            for k, v in scalars.items():
                self.tb.add_scalar(f"train/{k}", v, step)

    def close(self) -> None:
        if self.file:
            self.file.close()
        if self.tb is not None:
            self.tb.close()


@dataclass(frozen=True)
class _Process:
    """This process's place in a (possibly distributed) run."""

    world: int
    rank: int
    device: torch.device

    @property
    def main(self) -> bool:
        return self.rank == 0


def _start_process(cfg: TrainConfig) -> _Process:
    """The device, threads and process group of this process (``torchrun`` sets the env)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    if cfg.device == "auto":
        device = torch.device(f"cuda:{local_rank}" if torch.cuda.is_available() else "cpu")
    else:
        device = torch.device(cfg.device if cfg.device != "cuda" else f"cuda:{local_rank}")
    if device.type == "cpu" and cfg.threads:
        torch.set_num_threads(cfg.threads)
    if world > 1 and not torch.distributed.is_initialized():
        backend = "nccl" if device.type == "cuda" else "gloo"
        torch.distributed.init_process_group(backend=backend)
    if device.type == "cuda":
        torch.cuda.set_device(device)
    return _Process(world, rank, device)


def _model_and_optimizer(
    cfg: TrainConfig, proc: _Process, out: Path
) -> tuple[TrafficBots, torch.optim.Optimizer, AveragedModel | None, int]:
    """(model, optimizer, EMA or None, first step): resumed from ``out``, fine-tuned from
    ``cfg.init``, or new."""
    torch.manual_seed(cfg.seed + proc.rank)
    model = TrafficBots(cfg.model_config()).to(proc.device)
    opt = torch.optim.AdamW(
        model.parameters(),
        lr=cfg.lr,
        weight_decay=cfg.weight_decay,
        betas=(cfg.beta1, cfg.beta2),
    )
    start = 0
    if (out / "last.safetensors").exists() and (out / "optimizer.json").exists():
        load_state_into(model, out / "last")
        start = _optimizer_state_from_files(opt, out / "optimizer")
        if proc.main:
            print(f"resuming {out} from step {start}")
    elif cfg.init:
        load_state_into(model, cfg.init)  # CheckpointError names the file and the mismatch
        if proc.main:
            print(f"fine-tuning from {cfg.init}")
    ema = None
    if cfg.ema_decay is not None:
        if not 0.0 < cfg.ema_decay < 1.0:
            raise ValueError(f"ema_decay must lie in (0, 1), got {cfg.ema_decay}")
        ema = AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(cfg.ema_decay))
        if (out / "ema.safetensors").exists() and start > 0:
            load_state_into(ema.module, out / "ema")
            ema.n_averaged.fill_(start)
    return model, opt, ema, start


def _loader(cfg: TrainConfig, proc: _Process, start: int) -> tuple[DataLoader, Any]:
    """(data loader, its sampler) over the token cache: random with replacement on one
    process, a ``DistributedSampler`` over several."""
    data = open_training_data(cfg.data, max_shards=cfg.cache_shards or None)
    if len(data) == 0:
        raise ValueError(f"token cache {cfg.data} is empty")
    gen = torch.Generator().manual_seed(cfg.seed + 1000 * proc.rank + start)
    if proc.world > 1:
        sampler = DistributedSampler(data, num_replicas=proc.world, rank=proc.rank, seed=cfg.seed)
    else:
        sampler = RandomSampler(data, replacement=True, num_samples=10**9, generator=gen)
    loader = DataLoader(
        data,
        batch_size=cfg.batch_size,
        sampler=sampler,
        collate_fn=_collate,
        num_workers=cfg.workers,
        persistent_workers=cfg.workers > 0,
        drop_last=True,
    )
    if proc.world > 1 and len(loader) == 0:
        raise ValueError(
            f"{len(data)} scenes cannot fill one batch of {cfg.batch_size} on each of "
            f"{proc.world} processes; lower --batch-size or add data"
        )
    return loader, sampler


def _batches(loader: DataLoader, sampler: Any):
    """Batches forever (a ``DistributedSampler`` gets the next epoch after each pass)."""
    epoch = 0
    while True:
        yield from loader
        epoch += 1
        if isinstance(sampler, DistributedSampler):
            sampler.set_epoch(epoch)


def _check_replicas(model: TrafficBots, world: int, scalars: dict[str, float]) -> dict:
    """Compare a parameter checksum across the ranks (replicas must be identical), then
    close the process group; ``scalars`` with the checksum."""
    checksum = torch.stack([p.detach().double().sum() for p in model.parameters()]).sum()
    sums = [torch.zeros_like(checksum) for _ in range(world)]
    torch.distributed.all_gather(sums, checksum)
    if any(abs(float(x) - float(sums[0])) > 1e-6 * (1 + abs(float(sums[0]))) for x in sums):
        raise RuntimeError(f"DDP replicas diverged: parameter checksums {sums}")
    torch.distributed.barrier()
    torch.distributed.destroy_process_group()
    return {**scalars, "param_checksum": float(checksum)}


@dataclass
class _Run:
    """What the loop of one process carries between steps."""

    cfg: TrainConfig
    proc: _Process
    out: Path
    model: TrafficBots
    opt: torch.optim.Optimizer
    ema: AveragedModel | None
    val: Any = None
    best: float = math.inf

    def weights(self) -> TrafficBots:
        """The weights to evaluate and keep as ``best``: the EMA's when there is one."""
        return self.ema.module if self.ema is not None else self.model

    def checkpoint(self, step: int) -> None:
        save_checkpoint(self.model, self.out / "last")
        if self.ema is not None:
            save_checkpoint(self.ema.module, self.out / "ema")
        _optimizer_state_to_files(self.opt, step, self.out / "optimizer")

    def validate(self, step: int) -> dict[str, float]:
        """``val_*`` scalars of the weights at ``step``; saves ``best`` on a new low."""
        scores = validation_loss(
            self.weights(), self.val, batch_size=self.cfg.batch_size, device=self.proc.device
        )
        if scores["loss"] < self.best:
            self.best = scores["loss"]
            save_checkpoint(self.weights(), self.out / "best")
            (self.out / "best_step.json").write_text(json.dumps({"step": step, **scores}))
        return {f"val_{k}": v for k, v in scores.items() if k != "scenes"}


def _optimiser_step(run: _Run, loss: torch.Tensor, scaler: Any, step: int) -> float:
    """Backward, clip, step (and the EMA); returns the gradient norm."""
    run.opt.zero_grad(set_to_none=True)
    for group in run.opt.param_groups:
        group["lr"] = run.cfg.lr_at(step - 1)
    scaler.scale(loss).backward()
    scaler.unscale_(run.opt)
    grad_norm = float(torch.nn.utils.clip_grad_norm_(run.model.parameters(), run.cfg.grad_clip))
    scaler.step(run.opt)
    scaler.update()
    if run.ema is not None:
        run.ema.update_parameters(run.model)
    return grad_norm


def _setup(cfg: TrainConfig) -> tuple[_Run, torch.nn.Module, int]:
    """(run state, the objective to call (DDP-wrapped over several processes), first step)."""
    proc = _start_process(cfg)
    out = Path(cfg.out)
    if proc.main:
        out.mkdir(parents=True, exist_ok=True)
        (out / "train_config.json").write_text(json.dumps(dataclasses.asdict(cfg), indent=1))
    model, opt, ema, start = _model_and_optimizer(cfg, proc, out)
    run = _Run(cfg, proc, out, model, opt, ema)
    if cfg.val_data and proc.main:
        run.val = open_training_data(cfg.val_data, max_shards=None)
        best = out / "best_step.json"
        run.best = json.loads(best.read_text())["loss"] if best.exists() and start else math.inf
    objective: torch.nn.Module = TrainingObjective(model)
    if proc.world > 1:
        # Prior-latent batches leave the posterior encoders unused: find_unused_parameters.
        # device_ids=None: the module lives on one device, and DDP must not try to scatter
        # the TokenBatch input.
        objective = torch.nn.parallel.DistributedDataParallel(
            objective, device_ids=None, find_unused_parameters=True
        )
    return run, objective, start


def train(cfg: TrainConfig, *, progress: bool = True) -> dict[str, float]:
    """Train (or resume) a TrafficBots model; returns the last logged scalars.

    Runs distributed when launched by ``torchrun`` (``WORLD_SIZE`` > 1): one process per GPU
    (NCCL) or per CPU worker (Gloo), gradients averaged by ``DistributedDataParallel``.
    """
    run, objective, start = _setup(cfg)
    proc, model = run.proc, run.model
    loader, sampler = _loader(cfg, proc, start)
    use_amp = cfg.amp and proc.device.type == "cuda"
    scaler = torch.amp.GradScaler("cuda", enabled=use_amp)
    logger = _Logger(run.out, proc.main)
    if run.val is not None and start == 0:  # the starting weights are the first "best"
        logger.log(0, run.validate(0))
    roll_gen = torch.Generator(device=proc.device).manual_seed(cfg.seed + 7919 * proc.rank + start)
    model.train()
    end = cfg.steps if cfg.stop_at is None else min(cfg.stop_at, cfg.steps)
    shown = progress and proc.main
    bar = tqdm(total=end, initial=start, desc="train", unit="step", disable=not shown)
    scalars: dict[str, float] = {}
    t0, seen = time.perf_counter(), 0
    batches = _batches(loader, sampler)
    for step in range(start + 1, end + 1):
        items = next(batches)
        # The batch's used rows only (same draws and losses as the padded batch, fewer FLOPs).
        batch = TokenBatch.from_tokens(items, device=proc.device).trim()
        with torch.autocast(device_type=proc.device.type, dtype=torch.float16, enabled=use_amp):
            tf = cfg.teacher_forcing(step - 1)
            loss, logs = objective(batch, cfg.prior_prob, tf, roll_gen, cfg.rollout_steps)
        if not math.isfinite(float(loss.detach())):
            raise FloatingPointError(f"non-finite loss at step {step - 1}: {logs}")
        grad_norm = _optimiser_step(run, loss, scaler, step)
        seen += len(items) * proc.world
        bar.update(1)
        out_of_time = _out_of_time(cfg, t0, proc)
        last = step == end or out_of_time
        if step % cfg.log_every == 0 or last:
            rate = seen / (time.perf_counter() - t0)
            scalars = {**logs, "grad_norm": grad_norm, "scenarios_per_s": rate}
            scalars.update(teacher_forcing=tf, lr=cfg.lr_at(step - 1))
            if run.val is not None and (last or (cfg.val_every and step % cfg.val_every == 0)):
                scalars.update(run.validate(step))
            logger.log(step, scalars)
            bar.set_postfix(loss=f"{logs['loss']:.3f}", il=f"{logs['imitation']:.3f}")
        if proc.main and (step % cfg.ckpt_every == 0 or last):
            run.checkpoint(step)
        if out_of_time:
            break
    bar.close()
    logger.close()
    return _check_replicas(model, proc.world, scalars) if proc.world > 1 else scalars


def _out_of_time(cfg: TrainConfig, t0: float, proc: _Process) -> bool:
    """Whether ``cfg.time_budget_s`` has passed (decided by rank 0 for every process)."""
    if cfg.time_budget_s is None:
        return False
    over = torch.tensor(float(time.perf_counter() - t0 >= cfg.time_budget_s))
    if proc.world > 1:
        over = over.to(proc.device)
        torch.distributed.broadcast(over, src=0)
    return bool(over.item())


def build_parser() -> argparse.ArgumentParser:
    """``tbsim train``'s parser: one option per ``TrainConfig`` field, its help from the
    docstring (``tbsim_env.core.config_cli``)."""
    p = config_parser(TrainConfig, prog="tbsim train")
    p.description = (
        "Train TrafficBots V1.5 on a token cache (``tbsim preprocess``); resumes when --out "
        "already holds a run."
    )
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    train(parse_config(TrainConfig, args))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
