"""Shared timing protocol for the benchmarks.

Every variant of one table runs in the same process, interleaved round-robin after warm-ups, and the table
reports min and median wall time. Compare ratios, never absolute times across machines.
"""

from __future__ import annotations

import os
import platform
import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch


@dataclass(frozen=True)
class Timing:
    """Wall-clock statistics of one variant, in seconds."""

    min: float
    median: float
    reps: int
    total: float = float("nan")  #: sum over the timed calls


def time_interleaved(
    variants: dict[str, Callable[[], object]],
    warmup: int = 3,
    reps: int = 20,
) -> dict[str, Timing]:
    """Time every variant round-robin in one process.

    :param variants: name -> zero-argument callable doing one unit of work
    :param warmup: untimed calls of each variant before timing starts
    :param reps: timed calls of each variant (interleaved: v1, v2, ..., v1, v2, ...)
    :return: name -> ``Timing`` (min and median over ``reps`` calls)
    """
    if warmup < 0 or reps < 1:
        raise ValueError(f"need warmup >= 0 and reps >= 1, got warmup={warmup}, reps={reps}")
    for fn in variants.values():
        for _ in range(warmup):
            fn()
    samples: dict[str, list[float]] = {name: [] for name in variants}
    for _ in range(reps):
        for name, fn in variants.items():
            start = time.perf_counter()
            fn()
            samples[name].append(time.perf_counter() - start)
    return {name: Timing(min(s), statistics.median(s), len(s), sum(s)) for name, s in samples.items()}


def environment_header() -> str:
    """One paragraph naming what the figures depend on: threads, versions, CPU flags and load."""
    flags = ""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    present = set(line.split(":", 1)[1].split())
                    flags = " ".join(sorted(present & {"avx2", "avx512f", "avx512_bf16", "amx_bf16", "amx_tile"}))
                    break
    except OSError:
        pass
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    return (
        f"torch {torch.__version__}, threads {torch.get_num_threads()}, python {platform.python_version()}, "
        f"cpu flags [{flags}], load(1 min) {load:.2f}"
    )


def format_ms(t: Timing) -> str:
    """``'min / median ms'`` of a timing."""
    return f"{t.min * 1e3:8.2f} / {t.median * 1e3:8.2f} ms"
