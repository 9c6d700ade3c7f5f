"""Small torch helpers shared by the environment and the benchmarks."""

from __future__ import annotations

import contextlib

import numpy as np
import torch

from tbsim_env.core import constants as C


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


_ARANGE: dict[tuple[int, torch.device, torch.dtype], torch.Tensor] = {}


def cached_arange(
    n: int, device: torch.device | str, dtype: torch.dtype = torch.int64
) -> torch.Tensor:
    """``torch.arange(n)`` on ``device``, built once per (n, device, dtype); never modify it.

    Hot per-step code indexes with it (e.g. the batch index ``cached_arange(B)[:, None]``);
    building it anew costs about as much as the indexing itself. It is made outside
    inference mode so that autograd code may use it too. Under ``torch.compile`` it is a plain
    ``arange`` (free in a graph; a cache lookup would only add guards on the cache).
    """
    if torch.compiler.is_compiling():
        return torch.arange(n, device=device, dtype=dtype)
    key = (n, torch.device(device), dtype)
    out = _ARANGE.get(key)
    if out is None:
        with torch.inference_mode(False):
            out = _ARANGE[key] = torch.arange(n, device=key[1], dtype=dtype)
    return out


_CONST: dict[tuple, torch.Tensor] = {}
_CONST_DTYPES = (torch.float32, torch.float64)


def const(value: float | tuple[float, ...], like: torch.Tensor) -> torch.Tensor | float:
    """``value`` as a cached tensor of ``like``'s dtype and device, for hot arithmetic.

    ``x * 0.5`` wraps the Python float into a new tensor on every call, which costs more than
    the multiplication of a small tensor; ``x * const(0.5, x)`` gives the same bits (a
    Python scalar takes a float32 / float64 operand's dtype) without that. A tuple gives a
    1-d tensor. Other dtypes get ``value`` back unchanged. Never modify the returned tensor.
    Under ``torch.compile`` nothing is cached (a graph holds its constants; a cache lookup
    would only add guards on the cache): a number comes back as is, a tuple as a new tensor.
    """
    dtype = like.dtype
    if dtype not in _CONST_DTYPES:
        return value
    if torch.compiler.is_compiling():
        return (
            torch.tensor(value, dtype=dtype, device=like.device) if type(value) is tuple else value
        )
    key = (value, dtype, like.device)
    out = _CONST.get(key)
    if out is None:
        with torch.inference_mode(False):
            out = _CONST[key] = torch.tensor(value, dtype=dtype, device=like.device)
    return out


_SCALARS: dict[tuple, torch.Tensor] = {}


def scalar(value: int | float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """A cached 0-dim tensor of ``value`` (any dtype, integers included; ``const`` keeps to
    floats): an in-place operation with it records one ATen operation where a Python number
    is first wrapped into a tensor (several). Never modify it. Under ``torch.compile`` a new
    tensor (a graph holds its constants)."""
    if torch.compiler.is_compiling():
        return torch.tensor(value, dtype=dtype, device=device)
    key = (value, dtype, torch.device(device))
    out = _SCALARS.get(key)
    if out is None:
        with torch.inference_mode(False):
            out = _SCALARS[key] = torch.tensor(value, dtype=dtype, device=device)
    return out


def cast(x: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``x.to(dtype)`` (a new tensor, the same values; floats to integers truncate) as an
    empty tensor and a ``copy_``: two ATen operations where ``to`` records four."""
    return torch.empty(x.shape, dtype=dtype, device=x.device).copy_(x)


_BUILT: dict[tuple, object] = {}


def cached(key: tuple, build):
    """``build()`` (index tensors, constants of a shape) made once per ``key`` outside inference
    mode and kept; never modify what it returns. Under ``torch.compile`` it is built anew
    (free in a graph; a cache lookup would only add guards). The one cache behind
    ``row_offsets`` and the observations' index tables."""
    if torch.compiler.is_compiling():
        return build()
    out = _BUILT.get(key)
    if out is None:
        with torch.inference_mode(False):
            out = _BUILT[key] = build()
    return out


def row_offsets(b: int, n: int, dim: int, device: torch.device) -> torch.Tensor:
    """``arange(b) * n`` shaped [b, 1, ...] (``dim`` dims) to add to a row index, cached
    (``cached``)."""
    shape = (b,) + (1,) * (dim - 1)
    return cached(
        ("row_offsets", b, n, dim, device),
        lambda: (torch.arange(b, device=device) * n).view(shape),
    )


def gather_columns(
    x: torch.Tensor, index: torch.Tensor, rows: torch.Tensor
) -> tuple[torch.Tensor, ...]:
    """The C columns of a table ``x`` [K, C, E] at ``index`` [B, ...] (int, in [0, E)) of the
    table rows ``rows`` [B] int64: C tensors [B, ...], ``x[rows[b], c, index[b, ...]]``.

    Each column comes out contiguous (what elementwise code reads fastest) from one flat
    index shared by all; ``gather_rows`` of each column would compute that index C times.
    """
    _, c, e = x.shape
    flat = (index + (rows * (c * e)).view(-1, *([1] * (index.dim() - 1)))).reshape(1, -1)
    flat = (flat + cached_arange(c, index.device).view(c, 1) * e).reshape(-1)  # [C * n]
    return x.reshape(-1).index_select(0, flat).view(c, *index.shape).unbind(0)


def gather_rows(
    x: torch.Tensor, index: torch.Tensor, rows: torch.Tensor | None = None
) -> torch.Tensor:
    """``x[b, index[b, ...]]`` for every batch row b: ``x`` [B, N, ...], ``index`` [B, ...]
    int64 in [0, N) -> [B, ..., ...] (``index``'s shape, then ``x``'s trailing dims).

    With ``rows`` [B] int64, ``x`` is a table of K rows that batch row b reads at row
    ``rows[b]`` instead: ``x[rows[b], index[b, ...]]`` (``sim.state.Shared`` tables).

    The same values as the advanced indexing ``x[arange(B)[:, None, ...], index]``, by one
    ``index_select`` on the flattened rows: on the CPU a third of its cost (5 vs 15 us for
    64 rows), which matters in a per-step path of a few hundred small operations. Flattening
    is a ``view`` where the layout allows it (one ATen operation; ``flatten`` and ``reshape``
    record two).
    """
    b, n = x.shape[:2]
    if rows is not None:
        offsets = (rows * n).view(-1, *([1] * (index.dim() - 1)))
        flat = _flat(index + offsets, -1)
    elif b == 1:
        flat = _flat(index, -1)
    else:
        flat = _flat(index + row_offsets(b, n, index.dim(), x.device), -1)
    return select_rows(x, flat).view(*index.shape, *x.shape[2:])


def select_rows(x: torch.Tensor, flat: torch.Tensor) -> torch.Tensor:
    """``x.flatten(0, 1)[flat]``: the rows ``flat`` [R] (int64 in [0, B N)) of ``x`` [B, N, ...]
    with its first two dims merged, as [R] for a 2-d ``x``, else [1, R, ...] (view it).

    A table of more than two dims is read along dim 1 of a [1, B N, ...] view: CPU
    ``index_select`` along dim 0 of such a table records several operations more (the
    profiler counts them) than along dim 1.
    """
    b, n = x.shape[:2]
    if x.dim() == 2:
        return _flat(x, b * n).index_select(0, flat)
    if b > 1:
        shape = (1, b * n, *x.shape[2:])
        x = x.view(shape) if x.is_contiguous() else x.reshape(shape)
    return x.index_select(1, flat)


def _flat(x: torch.Tensor, rows: int) -> torch.Tensor:
    """``x`` as [rows, trailing dims after the first two] (``rows`` -1: ``x`` flattened to
    one dim): a view where ``x`` is contiguous, else a copy (``reshape``)."""
    shape = (rows,) if rows == -1 else (rows, *x.shape[2:])
    return x.view(shape) if x.is_contiguous() else x.reshape(shape)


def where_into(out: torch.Tensor, cond: torch.Tensor, a: torch.Tensor, b: torch.Tensor) -> None:
    """``out[...] = torch.where(cond, a, b)``, written into ``out``: e.g. one component
    ``x[..., k]`` of an interleaved [..., K] tensor, merged a component at a time (a [B, N]
    mask against [B, N, K] values broadcasts over the trailing dim, several times slower on
    the CPU: 130 vs 3 x 16 us for [64, 257, 3]). Eagerly ``where`` writes it directly; under
    ``torch.compile``, which takes no strided ``out=``, a copy (the graph fuses it)."""
    if torch.compiler.is_compiling():
        out.copy_(torch.where(cond, a, b))
    else:
        torch.where(cond, a, b, out=out)


def true_index(mask: torch.Tensor) -> torch.Tensor:
    """[K] int64 flat (row-major) indices of the True entries of ``mask`` (any shape), in
    order: ``mask.flatten().nonzero()[:, 0]``.

    On the CPU, eagerly, numpy's ``flatnonzero`` on the same memory: 2-5x faster than ATen's
    ``nonzero`` on one thread (0.14 vs 0.75 ms for a [64, 57, 153] mask of leader candidates,
    17 vs 49 us for 30,000 entries). Elsewhere (a GPU, a compiled graph) ATen's.
    """
    if mask.device.type != "cpu" or torch.compiler.is_compiling():
        return mask.reshape(-1).nonzero()[:, 0]
    return torch.from_numpy(np.flatnonzero(mask.numpy()))


def below_zero(x: torch.Tensor) -> torch.Tensor:
    """``x < 0`` (bool, ``x``'s shape) for a large float tensor.

    On the CPU, eagerly, numpy's comparison on the same memory: ~5x faster than ATen's on one
    thread (0.05 vs 0.25 ms for 558,000 float32, the leader search's disc test). Elsewhere
    (a GPU, a compiled graph, a tensor that needs its gradient) ATen's.
    """
    if x.device.type != "cpu" or torch.compiler.is_compiling() or x.requires_grad:
        return x < 0
    return torch.from_numpy(np.less(x.numpy(), 0))


def valid_order(valid: torch.Tensor) -> torch.Tensor:
    """[B, C] int64 slots: each row's valid slots in order, then its others, C the most valid
    slots of any row (at least 1; eager only: C depends on the data). Columns past a row's
    count hold its invalid slots."""
    b, n = valid.shape
    if b == 0 or n == 0:
        return torch.zeros(b, min(n, 1), dtype=torch.long, device=valid.device)
    before = valid.cumsum(1, dtype=torch.int32)  # valid slots up to and including each slot
    total = before[:, -1:]
    count = max(int(total.max()), 1)
    # A valid slot goes to its rank among the valid ones, an invalid one after all of them.
    slot = cached_arange(n, valid.device, torch.int32)
    place = torch.where(valid, before - 1, total + slot - before).long()
    order = torch.empty(b, n, dtype=torch.long, device=valid.device)
    return order.scatter_(1, place, cached_arange(n, valid.device).expand(b, n))[:, :count]


def valid_first(valid: torch.Tensor, queries: int) -> torch.Tensor | None:
    """``valid_order(valid)`` where measuring ``queries`` query agents per row against those
    columns instead of every slot pays; None (every slot) elsewhere.

    Real scenes keep a slot for every track of the log, most of them absent at any one step
    (257 slots, at most 114 valid in the real samples): [B, Q, C] agent pairs instead of
    [B, Q, N] cost less than half. It pays eagerly on the CPU (``listed``'s rule) from
    ``VALID_FIRST_MIN_QUERIES`` queries per row: with fewer (the SDC alone), its fixed cost
    is larger than the [B, Q, N] work it saves.
    """
    if valid.device.type != "cpu" or torch.compiler.is_compiling():
        return None
    return valid_order(valid) if queries >= C.VALID_FIRST_MIN_QUERIES else None


def listed(mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor] | None:
    """(rows, cols) of the True entries of ``mask`` [B, Q] when computing on those alone pays:
    eagerly on the CPU and some entry is False. None otherwise: use the dense [B, Q] layout.

    With every agent controlled, agents that have left the scene would otherwise cost as much
    as those still driving. On a GPU they cost idle lanes rather than time, while listing the
    others costs a host sync; a compiled graph cannot size tensors by data.
    """
    if mask.device.type != "cpu" or torch.compiler.is_compiling() or bool(mask.all()):
        return None
    flat = true_index(mask)
    return flat // mask.shape[1], flat % mask.shape[1]


def aten_op_count(fn, calls: int = 1) -> float:
    """ATen operations per call of ``fn()`` over ``calls`` calls, as the torch profiler records
    them (every ``aten::`` event, nested ones included: a view, a copy inside ``.to``). The
    count of a step does not depend on the machine, while its time per operation does; a
    step of many small operations costs about its count times one tiny operation."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(calls):
            fn()
    return sum(e.name.startswith("aten::") for e in prof.events()) / calls
