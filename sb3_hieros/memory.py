"""Process-wide memory-allocator settings that change CPU training speed, never results.

A world-model update allocates and frees many activation tensors of a megabyte or more. glibc's ``malloc`` serves
blocks above its mmap threshold (128 KiB at start, raised adaptively) with fresh ``mmap`` calls and returns free
memory at the top of its heap to the operating system (trimming). Either way the next update's tensors land on pages
the kernel must fault in and zero again, once per 4 KiB page. On the virtual machines this project measures on, those
faults cost several milliseconds per small-preset S5WM update (``python -m benchmarks.world_model --parts b``
prints the faults per call). :func:`retain_freed_memory` makes ``malloc`` keep such memory for reuse instead.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import sys
from collections.abc import Callable

__all__ = ["MAX_MMAP_THRESHOLD", "retain_freed_memory"]

# mallopt parameter numbers from glibc's <malloc.h>
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3

#: The largest mmap threshold glibc accepts on 64-bit systems (``HEAP_MAX_SIZE / 2``, 32 MiB).
MAX_MMAP_THRESHOLD = 32 * 1024 * 1024


def _mallopt() -> Callable[[int, int], int] | None:
    """glibc's ``mallopt``, or None where the C library has none (macOS, Windows, musl)."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return None
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return mallopt


def retain_freed_memory(mmap_threshold: int = MAX_MMAP_THRESHOLD, trim_threshold: int = 1 << 30) -> bool:
    """Keep freed memory in the process for reuse instead of returning it to the operating system (glibc only).

    Sets glibc's ``M_MMAP_THRESHOLD`` (blocks up to this size come from the heap, not from ``mmap``) and
    ``M_TRIM_THRESHOLD`` (up to this much free memory at the top of the heap is kept), the same as the environment
    variables ``MALLOC_MMAP_THRESHOLD_`` and ``MALLOC_TRIM_THRESHOLD_``. It affects the whole process from the call
    on and turns off glibc's adaptive thresholds; the process then holds on to its peak heap size. Results do not
    change, only the time spent in page faults. Call it once at the start of a training script.

    :param mmap_threshold: bytes; blocks larger than this still use ``mmap`` (at most :data:`MAX_MMAP_THRESHOLD`)
    :param trim_threshold: bytes of free heap top kept before memory is given back
    :return: True when both settings were applied; False where the C library is not glibc (nothing changes)
    """
    for name, value, upper in (
        ("mmap_threshold", mmap_threshold, MAX_MMAP_THRESHOLD),
        ("trim_threshold", trim_threshold, 2**31 - 1),
    ):
        if isinstance(value, bool) or not isinstance(value, int) or not 0 < value <= upper:
            raise ValueError(f"{name} must be an int in [1, {upper}] bytes, got {value!r}")
    mallopt = _mallopt()
    if mallopt is None:
        return False
    return bool(mallopt(_M_MMAP_THRESHOLD, mmap_threshold)) and bool(mallopt(_M_TRIM_THRESHOLD, trim_threshold))
