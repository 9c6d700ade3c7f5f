"""Checkpoints: ``<path>.safetensors`` (weights) + ``<path>.json`` (config). Never pickle.

Loading checks every key and shape against a freshly built model and raises
``CheckpointError`` naming the missing, unexpected and mismatched keys.
"""

from __future__ import annotations

import json
from pathlib import Path

import torch
from safetensors import SafetensorError
from safetensors.torch import load_file, save_file

from policies.trafficbots.config import TrafficBotsConfig
from policies.trafficbots.model import TrafficBots
from tbsim_env.core.errors import CheckpointError

FORMAT = "tbsim.trafficbots"
VERSION = 1


def _paths(path: str | Path) -> tuple[Path, Path]:
    p = Path(path)
    if p.suffix in (".safetensors", ".json"):
        p = p.with_suffix("")
    return p.with_name(p.name + ".safetensors"), p.with_name(p.name + ".json")


def save_checkpoint(model: TrafficBots, path: str | Path) -> tuple[Path, Path]:
    """Write the weights and the config.

    Args:
        model: the network.
        path: base path; ``.safetensors`` and ``.json`` are appended.

    Returns:
        (weights path, config path).
    """
    w_path, c_path = _paths(path)
    w_path.parent.mkdir(parents=True, exist_ok=True)
    state = {k: v.detach().cpu().contiguous() for k, v in model.state_dict().items()}
    save_file(state, str(w_path), metadata={"format": FORMAT, "version": str(VERSION)})
    meta = {"format": FORMAT, "version": VERSION, "config": model.cfg.to_dict()}
    c_path.write_text(json.dumps(meta, indent=2, sort_keys=True))
    return w_path, c_path


def load_state_into(model: TrafficBots, path: str | Path) -> TrafficBots:
    """Load weights into ``model`` after checking every key and shape.

    Args:
        model: a model built with the intended config.
        path: base path of the checkpoint.

    Returns:
        ``model`` with the weights loaded.

    Raises:
        CheckpointError: unreadable file, missing / unexpected keys or shape / dtype mismatch.
    """
    w_path, _ = _paths(path)
    try:
        loaded = load_file(str(w_path))
    except (OSError, SafetensorError) as exc:
        raise CheckpointError(f"{w_path}: cannot read weights ({exc})") from exc
    expected = model.state_dict()
    missing = sorted(set(expected) - set(loaded))
    unexpected = sorted(set(loaded) - set(expected))
    mismatched = sorted(
        f"{k}: checkpoint {tuple(loaded[k].shape)} {loaded[k].dtype}, "
        f"model {tuple(expected[k].shape)} {expected[k].dtype}"
        for k in set(expected) & set(loaded)
        if loaded[k].shape != expected[k].shape or loaded[k].dtype != expected[k].dtype
    )
    if missing or unexpected or mismatched:
        parts = []
        if missing:
            parts.append(f"missing keys {missing}")
        if unexpected:
            parts.append(f"unexpected keys {unexpected}")
        if mismatched:
            parts.append(f"mismatched keys {mismatched}")
        raise CheckpointError(f"{w_path} does not match the model: " + "; ".join(parts))
    with torch.no_grad():
        for k, v in expected.items():
            v.copy_(loaded[k])
    return model


def load_checkpoint(
    path: str | Path,
    config: TrafficBotsConfig | None = None,
    map_location: torch.device | str = "cpu",
) -> TrafficBots:
    """Build a model and load a checkpoint into it.

    Args:
        path: base path (or either file) of the checkpoint.
        config: build the model with this config instead of the stored one; any key or shape
            difference then raises.
        map_location: device of the returned model.

    Returns:
        The model, in eval mode.

    Raises:
        CheckpointError: bad config file, missing / unexpected / mismatched keys.
    """
    _, c_path = _paths(path)
    if config is None:
        try:
            meta = json.loads(c_path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise CheckpointError(f"{c_path}: cannot read config ({exc})") from exc
        if meta.get("format") != FORMAT or meta.get("version") != VERSION:
            raise CheckpointError(
                f"{c_path}: format {meta.get('format')!r} version {meta.get('version')!r}, "
                f"expected {FORMAT!r} version {VERSION}"
            )
        try:
            config = TrafficBotsConfig.from_dict(meta["config"])
        except (KeyError, TypeError, ValueError) as exc:
            raise CheckpointError(f"{c_path}: invalid config ({exc})") from exc
    model = TrafficBots(config)
    load_state_into(model, path)
    return model.to(map_location).eval()


def average_checkpoints(paths: list[str | Path], out: str | Path) -> tuple[Path, Path]:
    """Write the element-wise mean of the weights of several checkpoints of one config.

    Averaging checkpoints of one training run (stochastic weight averaging) evens out the
    noise of small-batch updates between them.

    Args:
        paths: base paths of two or more checkpoints (same config).
        out: base path of the averaged checkpoint.

    Returns:
        (weights path, config path) written.

    Raises:
        CheckpointError: fewer than two checkpoints, an unreadable or mismatched one, configs
            that differ, or non-float tensors (buffers) that differ between checkpoints.
    """
    if len(paths) < 2:
        raise CheckpointError(f"averaging needs two or more checkpoints, got {len(paths)}")
    models = [load_checkpoint(p) for p in paths]
    first = models[0].cfg.to_dict()
    for p, m in zip(paths[1:], models[1:], strict=True):
        if m.cfg.to_dict() != first:
            diff = sorted(k for k, v in m.cfg.to_dict().items() if first.get(k) != v)
            raise CheckpointError(f"{p}: config differs from {paths[0]} in {diff}")
    states = [m.state_dict() for m in models]
    mean = {}
    for key, ref in states[0].items():
        if ref.is_floating_point():
            mean[key] = torch.stack([s[key] for s in states]).mean(0)
        elif all(torch.equal(s[key], ref) for s in states[1:]):
            mean[key] = ref
        else:
            raise CheckpointError(f"non-float tensor {key!r} differs between the checkpoints")
    model = models[0]
    model.load_state_dict(mean)
    return save_checkpoint(model, out)
