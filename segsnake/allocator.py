"""The process's memory allocator: freed volumes go back to the operating system.

A run allocates and frees many volume-sized temporaries (densities, masks, distance maps,
lookups). glibc's malloc maps blocks above a threshold from the OS on their own and unmaps them
when freed, but it raises that threshold to the size of each such block freed (up to 32 MB),
after which every block of up to 32 MB comes from the heap, which returns memory to the OS only
from its top: the freed temporaries stay resident. Measured on the Colin27 brain (181 x 217 x
181): peak resident memory 293 MiB with the adaptive threshold, 255 MiB with the fixed one
(issue 18; docs/benchmarks.md, "Memory"). Fixing the threshold
(``mallopt(M_MMAP_THRESHOLD, ...)``) stops the adaptation.
"""

from __future__ import annotations

import ctypes
import sys

__all__ = ["MMAP_THRESHOLD_BYTES", "return_freed_memory", "trim"]

#: Blocks of at least this size are mapped from the OS on their own and unmapped when freed:
#: every float32 volume of 181 x 217 x 181 voxels or more (27 MiB); smaller blocks (masks,
#: the planes and pieces the loops work on) are reused from the heap, where mapping each would
#: cost page faults. Measured (benchmarks/bench_memory.py): peak on the
#: Colin27 brain 262 / 255 / 255 / 297 MiB at 4 / 8 / 16 / 32 MiB, 293 MiB adaptive; page faults
#: 311k / 200k / 130k / 77k (65k adaptive).
MMAP_THRESHOLD_BYTES = 16 << 20
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3  # glibc's malloc.h


def return_freed_memory(threshold: int = MMAP_THRESHOLD_BYTES) -> bool:
    """Fix glibc's mmap threshold at ``threshold`` bytes for this process; True when set
    (False on another C library or platform, where nothing changes)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        libc = ctypes.CDLL("libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = (ctypes.c_int, ctypes.c_int)
    mallopt.restype = ctypes.c_int
    # The heap keeps up to twice that free at its top, as glibc's adaptive rule does: trimming
    # it at every free (the fixed default, 128 kB) costs a page fault per page of every
    # plane-sized temporary reused after it (measured: 0.9 million faults more on a brain).
    return bool(mallopt(_M_MMAP_THRESHOLD, int(threshold))) and \
        bool(mallopt(_M_TRIM_THRESHOLD, 2 * int(threshold)))


def trim() -> bool:
    """Give the heap's free pages back to the OS (glibc's ``malloc_trim(0)``), for instance
    between a segmentation and the writing of its outputs, whose libraries (matplotlib, VTK)
    load on top of what the segmentation's temporaries left free in the heap. True when
    something was released (False elsewhere than glibc)."""
    if not sys.platform.startswith("linux"):
        return False
    try:
        malloc_trim = ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return False
    malloc_trim.argtypes = (ctypes.c_size_t,)
    malloc_trim.restype = ctypes.c_int
    return bool(malloc_trim(0))
