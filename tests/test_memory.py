import subprocess
import sys

import pytest

from sb3_hieros.memory import MAX_MMAP_THRESHOLD, _mallopt, retain_freed_memory

# Allocates and frees 30 blocks of 1 MiB (the size of a small-preset activation tensor) ten times and prints the minor
# page faults per cycle. In a fresh process, so that the allocator settings of the test process stay untouched.
_CYCLES = """
import ctypes, resource, sys
from sb3_hieros.memory import retain_freed_memory
libc = ctypes.CDLL("libc.so.6")
libc.malloc.restype, libc.malloc.argtypes, libc.free.argtypes = ctypes.c_void_p, [ctypes.c_size_t], [ctypes.c_void_p]
if sys.argv[1] == "retain":
    assert retain_freed_memory()
def cycle():
    blocks = [libc.malloc(1 << 20) for _ in range(30)]
    for block in blocks:
        ctypes.memset(block, 1, 1 << 20)
    for block in blocks:
        libc.free(block)
for _ in range(3):
    cycle()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for _ in range(10):
    cycle()
print((resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before) / 10)
"""


def _faults_per_cycle(mode: str) -> float:
    out = subprocess.run([sys.executable, "-c", _CYCLES, mode], capture_output=True, text=True, check=True)
    return float(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(_mallopt() is None, reason="needs glibc's mallopt")
def test_retain_freed_memory_stops_refaulting_freed_blocks():
    pages_per_cycle = 30 * (1 << 20) // 4096
    assert _faults_per_cycle("default") > pages_per_cycle / 2  # glibc gives the blocks back and faults them in again
    assert _faults_per_cycle("retain") < pages_per_cycle / 20


@pytest.mark.parametrize(
    "kwargs",
    [
        {"mmap_threshold": 0},
        {"mmap_threshold": -1},
        {"mmap_threshold": MAX_MMAP_THRESHOLD + 1},
        {"mmap_threshold": 1.5},
        {"mmap_threshold": True},
        {"trim_threshold": 0},
        {"trim_threshold": 2**31},
        {"trim_threshold": "1G"},
    ],
)
def test_retain_freed_memory_rejects_bad_thresholds(kwargs):
    name = next(iter(kwargs))
    with pytest.raises(ValueError, match=name):
        retain_freed_memory(**kwargs)
