"""Row operations on trees of batched tensors (dataclasses, dicts, lists, tuples of [B, ...]).

The environments keep an episode as a frozen dataclass of ``[B, ...]`` tensors; starting new
episodes in some rows is ``with_rows(state, rows, fresh)`` and looking at some rows is
``take_rows(state, rows)``; ``cat_rows(trees)`` stacks the rows of several trees (per-scene
caches into a batch). All three return new trees and modify nothing, except where a caller
asks for writes into trees it alone holds (``take_rows``' ``out``, ``with_rows``' ``in_place``).
``sim.state.Shared`` tables (per-scenario tables that rows read through a row map) pass
through both unchanged.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import Any, NamedTuple

import torch

from tbsim_env.sim.state import Shared


def take_rows(tree: Any, rows: torch.Tensor, out: Any = None) -> Any:
    """Gather rows (leading batch dimension) of every tensor of a dataclass / dict / tuple tree.

    Args:
        tree: a tensor, None, or a (frozen) dataclass, dict, list or tuple of those.
        rows: [R] int64 row indices.
        out: optional tree of the same structure whose tensors receive the rows where they
            can (each that owns its whole storage and has the result's shape and dtype; the
            others are left alone and a new tensor is made): restarting every row of a batch
            then reuses the batch's memory, where new tensors of that size would be mapped
            and faulted in page by page again. Only for a tree whose owner alone holds its
            tensors (the batched env's own episode); they are overwritten.

    Returns:
        The same structure with every tensor ``x`` replaced by ``x[rows]`` (a copy; in
        ``out``'s tensor where it was written there).

    Raises:
        TypeError: a leaf is neither a tensor nor None.
    """
    if tree is None or isinstance(tree, Shared):
        return tree
    if isinstance(tree, torch.Tensor):
        if _can_receive(out, tree, rows):
            return torch.index_select(tree, 0, rows, out=out)
        return tree.index_select(0, rows)
    if dataclasses.is_dataclass(tree) and not isinstance(tree, type):
        fields = {
            f.name: take_rows(getattr(tree, f.name), rows, _part(out, tree, f.name))
            for f in dataclasses.fields(tree)
        }
        return dataclasses.replace(tree, **fields)
    if isinstance(tree, dict):
        return {k: take_rows(v, rows, _part(out, tree, k)) for k, v in tree.items()}
    if isinstance(tree, (list, tuple)):
        parts = out if type(out) is type(tree) and len(out) == len(tree) else [None] * len(tree)
        return _rebuild(tree, [take_rows(v, rows, o) for v, o in zip(tree, parts, strict=True)])
    raise TypeError(f"cannot take rows of {type(tree).__name__}; use tensors and dataclasses")


def _part(out: Any, tree: Any, key: str) -> Any:
    """``out``'s field or entry ``key`` when ``out`` has ``tree``'s type, else None."""
    if type(out) is not type(tree):
        return None
    return out.get(key) if isinstance(out, dict) else getattr(out, key)


def _can_receive(out: Any, x: torch.Tensor, rows: torch.Tensor) -> bool:
    """``out`` is a tensor that ``x[rows]`` can be written into, touching nothing else."""
    return (
        isinstance(out, torch.Tensor)
        and out.shape == (rows.shape[0], *x.shape[1:])
        and out.dtype == x.dtype
        and out.device == x.device
        and _owns_storage(out)
    )


def cat_rows(trees: Sequence[Any]) -> Any:
    """One tree of the same structure whose tensors are the trees' tensors concatenated along
    the leading batch dimension, in order (e.g. cached per-scene tensors into a batch).

    Args:
        trees: one or more trees of the same structure (as ``take_rows``'s).

    Raises:
        ValueError: no trees.
        TypeError: a leaf is neither a tensor nor None, or the structures differ.
    """
    if not trees:
        raise ValueError("cat_rows needs at least one tree")
    first = trees[0]
    if isinstance(first, Shared):
        if any(not isinstance(t, Shared) or t.value is not first.value for t in trees):
            raise ValueError("cat_rows: the trees do not share their tables (another bank)")
        return first
    if first is None:
        return first
    if isinstance(first, torch.Tensor):
        return torch.cat(list(trees))
    if any(type(t) is not type(first) for t in trees):
        raise TypeError(f"cat_rows: trees of types {sorted({type(t).__name__ for t in trees})}")
    if dataclasses.is_dataclass(first) and not isinstance(first, type):
        return dataclasses.replace(
            first,
            **{
                f.name: cat_rows([getattr(t, f.name) for t in trees])
                for f in dataclasses.fields(first)
            },
        )
    if isinstance(first, dict):
        return {k: cat_rows([t[k] for t in trees]) for k in first}
    if isinstance(first, (list, tuple)):
        return _rebuild(first, [cat_rows(list(items)) for items in zip(*trees, strict=True)])
    raise TypeError(f"cannot concatenate rows of {type(first).__name__}")


def with_rows(
    dst: Any,
    rows: torch.Tensor,
    src: Any,
    strict: bool = True,
    in_place: bool = False,
    src_rows: torch.Tensor | None = None,
) -> Any:
    """``dst`` with the rows ``rows`` of every tensor replaced by ``src``'s (a new tree).

    Args:
        dst: tree (tensor, dataclass, dict, list, tuple) whose tensors have a leading batch.
        rows: [R] int64 rows of ``dst`` to replace.
        src: the same structure with R rows, or any number of rows with ``src_rows``.
        strict: raise on non-tensor leaves (other than None); when False they are kept as
            in ``dst`` (batch-wide metadata such as a policy's step counter).
        in_place: write the rows into ``dst``'s tensors (each that owns its whole storage;
            any other is copied) instead of copying every tensor: the cost of the R rows, not
            of the batch. Only for a tree whose owner alone holds its tensors (the batched
            env's own episode, whose restart would otherwise copy every table of the batch).
        src_rows: optional [R] int64, the rows of ``src`` that go into ``rows`` (a bank's
            rows, say): read straight from ``src``, with no R-row copy of it made first
            (in place and for a few rows, row by row: ``ROW_COPY_MAX``).

    Raises:
        ValueError: a tensor's trailing shape differs between the trees.
        TypeError: the structures differ, or a non-tensor leaf with ``strict``.
    """
    pairs = None
    if src_rows is not None and in_place and rows.numel() <= ROW_COPY_MAX:
        pairs = tuple(zip(rows.tolist(), src_rows.tolist(), strict=True))
    return _with(dst, _Rows(rows, src_rows, pairs), src, strict, in_place)


class _Rows(NamedTuple):
    """Where ``with_rows`` writes: ``dst`` [R] rows of the destination, ``src`` [R] rows of
    the source (None: all of it, in order), ``pairs`` the (dst, src) row numbers when the
    rows are copied one at a time (``ROW_COPY_MAX``)."""

    dst: torch.Tensor
    src: torch.Tensor | None
    pairs: tuple[tuple[int, int], ...] | None


def _with(dst: Any, rows: _Rows, src: Any, strict: bool, in_place: bool) -> Any:
    """``with_rows``' recursion over the trees."""
    if dst is None and src is None:
        return None
    if isinstance(dst, Shared):
        if not isinstance(src, Shared) or src.value is not dst.value:
            raise ValueError("with_rows: the trees do not share their tables (another bank)")
        return dst
    if isinstance(dst, torch.Tensor):
        if not isinstance(src, torch.Tensor) or dst.shape[1:] != src.shape[1:]:
            got = tuple(src.shape) if isinstance(src, torch.Tensor) else type(src).__name__
            raise ValueError(f"with_rows: {tuple(dst.shape)} rows cannot take {got}")
        if src.dtype != dst.dtype:
            src = src.to(dst.dtype)
        return _put_rows(dst, rows, src, in_place and _owns_storage(dst))
    again = lambda a, b: _with(a, rows, b, strict, in_place)  # noqa: E731
    if dataclasses.is_dataclass(dst) and not isinstance(dst, type):
        if type(src) is not type(dst):
            raise TypeError(f"with_rows: {type(dst).__name__} vs {type(src).__name__}")
        fields = {
            f.name: again(getattr(dst, f.name), getattr(src, f.name))
            for f in dataclasses.fields(dst)
        }
        return dataclasses.replace(dst, **fields)
    if isinstance(dst, dict):
        return {k: again(dst[k], src[k]) for k in dst}
    if isinstance(dst, (list, tuple)):
        return _rebuild(dst, [again(a, b) for a, b in zip(dst, src, strict=True)])
    if not strict and type(src) is type(dst):
        return dst
    raise TypeError(f"cannot put rows into {type(dst).__name__}; use tensors and dataclasses")


ROW_COPY_MAX = 4
"""``with_rows`` with ``src_rows`` writes in place up to this many rows a row at a time (one
``copy_`` of a row view each: no gathered copy of the rows is allocated and faulted in);
more rows in one gather and one ``index_copy_``."""


def _put_rows(dst: torch.Tensor, rows: _Rows, src: torch.Tensor, in_place: bool) -> torch.Tensor:
    """``dst`` with its rows ``rows.dst`` from ``src`` (its rows ``rows.src``, or all of it),
    written into ``dst`` when ``in_place``, else into a copy."""
    if in_place and rows.pairs is not None:
        for r, k in rows.pairs:
            dst.select(0, r).copy_(src.select(0, k))
        return dst
    part = src if rows.src is None else src.index_select(0, rows.src)
    return dst.index_copy_(0, rows.dst, part) if in_place else dst.index_copy(0, rows.dst, part)


def _owns_storage(x: torch.Tensor) -> bool:
    """``x`` is its storage's only tensor shape: contiguous, from offset 0, to the end (not a
    view into a larger tensor, not an expanded one), so writing into it touches nothing else."""
    whole = x.numel() * x.element_size() == x.untyped_storage().nbytes()
    return whole and x.storage_offset() == 0 and x.is_contiguous()


def _rebuild(seq: list | tuple, items: list) -> list | tuple:
    """A list or tuple of ``seq``'s type (a named tuple included) holding ``items``."""
    return type(seq)(*items) if hasattr(seq, "_fields") else type(seq)(items)


__all__ = ["cat_rows", "take_rows", "with_rows"]
