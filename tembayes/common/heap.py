"""Keep the sampler's short-lived arrays on the heap (glibc only).

A likelihood call allocates and frees arrays of about a megabyte tens of
thousands of times per module.  glibc serves such blocks from the heap once
it has seen one freed (its mmap threshold adapts), unless a trim threshold
is fixed in the environment: Dask's nanny sets ``MALLOC_TRIM_THRESHOLD_`` for
its workers, which also fixes the mmap threshold at 128 KiB.  Every block is
then a fresh mapping whose pages fault in again -- 60 times the page faults
and a module 1.5-2 times slower on a virtual machine.
"""

from __future__ import annotations

import ctypes
import functools
import os

# mallopt parameters (malloc.h)
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
#: Blocks below this come from the heap [bytes] (glibc's own ceiling for its adaptive threshold).
MMAP_THRESHOLD = 32 * 1024 * 1024
#: Free memory kept at the heap's top before it is returned [bytes].
TRIM_THRESHOLD = 2 * MMAP_THRESHOLD


@functools.cache
def keep_short_lived_blocks_on_the_heap() -> bool:
    """Raise glibc's mmap and trim thresholds in this process (once; later calls return the first answer).

    Returns
    -------
    bool
        Whether they were set (False where the C library is not glibc).
    """
    if os.name != "posix":
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the C library the process already has loaded
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    return bool(mallopt(_M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and bool(mallopt(_M_TRIM_THRESHOLD, TRIM_THRESHOLD))
