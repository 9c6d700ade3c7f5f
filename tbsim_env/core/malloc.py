"""Keep the memory a step frees in the process, so that the next step does not page-fault it.

A batched step allocates and frees tens of megabytes of temporaries ([B, Q, N] distances,
[B, Q, K] tokens and their gathers). With glibc's defaults, blocks above a (dynamically
raised) threshold are fresh ``mmap`` s and free memory at the top of the heap goes back to the
operating system, so every step touches new pages and the kernel zero-fills them: on the 2-core
machine, all agents controlled at B = 64, that was ~10-20% of the step.

``keep_freed_memory()`` fixes glibc's ``M_MMAP_THRESHOLD`` at ``MALLOC_MMAP_THRESHOLD`` (blocks
up to it come from the heap) and raises ``M_TRIM_THRESHOLD`` to ``MALLOC_TRIM_THRESHOLD`` (that
much free memory stays with the process). The process's resident memory then stays near its
peak instead of shrinking between steps. Both environments call it when they run on the CPU;
``TBSIM_KEEP_FREED_MEMORY=0`` in the environment turns it off. It does nothing outside glibc.
"""

from __future__ import annotations

import ctypes
import os
import platform

from tbsim_env.core import constants as C

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
"""glibc's ``mallopt`` parameter numbers (malloc.h)."""

_done: bool | None = None


def keep_freed_memory() -> bool:
    """Set glibc's malloc thresholds once per process (see the module docstring).

    Returns:
        Whether they are set: False outside glibc, when ``mallopt`` refuses them, or when
        ``TBSIM_KEEP_FREED_MEMORY`` is ``0``.
    """
    global _done
    if _done is None:
        _done = os.environ.get("TBSIM_KEEP_FREED_MEMORY", "1") != "0" and _set_thresholds()
    return _done


def _set_thresholds() -> bool:
    if platform.system() != "Linux" or platform.libc_ver()[0] != "glibc":
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    ok = mallopt(_M_MMAP_THRESHOLD, C.MALLOC_MMAP_THRESHOLD) == 1
    return ok and mallopt(_M_TRIM_THRESHOLD, C.MALLOC_TRIM_THRESHOLD) == 1


__all__ = ["keep_freed_memory"]
