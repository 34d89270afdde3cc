"""The allocator setting of the segsnake program (segsnake.allocator): a freed volume-sized
array goes back to the system instead of staying resident in the heap."""

import os
import subprocess
import sys

import pytest

PROBE = """
import sys, numpy as np
from segsnake.allocator import return_freed_memory
if sys.argv[1] == "fixed":
    assert return_freed_memory()
def rss():
    return int(open("/proc/self/statm").read().split()[1]) * 4096 / 2**20
base = rss()
for _ in range(3):
    a = np.ones(20 << 20, np.uint8)  # a 20 MB temporary
    small = [np.ones(1000) for _ in range(100)]  # small blocks above it in the heap
    del a
print(rss() - base)
"""


def _resident_after_frees(mode: str) -> float:
    out = subprocess.run([sys.executable, "-c", PROBE, mode], capture_output=True, text=True,
                         check=True)
    return float(out.stdout)


def _glibc() -> bool:
    try:
        return sys.platform.startswith("linux") and "glibc" in os.confstr("CS_GNU_LIBC_VERSION")
    except (ValueError, OSError):
        return False


@pytest.mark.skipif(not _glibc(), reason="glibc's mallopt only")
def test_freed_temporaries_leave_the_resident_set():
    # glibc's adaptive threshold puts the second 20 MB block in the heap, where it stays
    # resident once freed; with the fixed threshold each one is unmapped.
    assert _resident_after_frees("dynamic") > 15.0
    assert _resident_after_frees("fixed") < 5.0


TRIM_PROBE = """
import sys, numpy as np
from segsnake.allocator import return_freed_memory, trim
assert return_freed_memory()
def rss():
    return int(open("/proc/self/statm").read().split()[1]) * 4096 / 2**20
blocks = [np.ones(1 << 20) for _ in range(40)]  # 40 x 8 MB, under the threshold: the heap's
keep = np.ones(1 << 17)  # a 1 MB block above them holds the heap's top
base = rss()
del blocks
freed = rss()
released = trim() if sys.argv[1] == "trim" else False
print(base - freed, base - rss(), released)
"""


@pytest.mark.skipif(not _glibc(), reason="glibc's malloc_trim only")
def test_trim_gives_the_heaps_free_pages_back():
    # 320 MB of heap blocks freed under a live one stay resident until trim() releases them.
    def run(mode):
        out = subprocess.run([sys.executable, "-c", TRIM_PROBE, mode], capture_output=True,
                             text=True, check=True).stdout.split()
        return float(out[0]), float(out[1]), out[2] == "True"
    kept, _, released = run("keep")
    assert kept < 50.0 and not released  # freed, but resident
    _, after, released = run("trim")
    assert released and after > 250.0
