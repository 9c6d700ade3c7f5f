"""Small torch helpers shared by the environment and the benchmarks."""

from __future__ import annotations

import contextlib

import torch


@contextlib.contextmanager
def torch_threads(n: int | None):
    """Run the block with ``n`` intra-op threads (None: leave the setting alone), then restore.

    A batch-of-one environment step is hundreds of tiny tensor operations; letting torch
    parallelise them only adds thread wake-ups (milliseconds each when another process holds
    the other cores), so ``TrafficEnv`` steps single-threaded by default.
    """
    if n is None or n == torch.get_num_threads():
        yield
        return
    before = torch.get_num_threads()
    torch.set_num_threads(n)
    try:
        yield
    finally:
        torch.set_num_threads(before)
