"""Process-wide allocator setting for the large dense work of modes and calibration (glibc).

A calibration at 200k DOF allocates and frees hundreds of (n, r) blocks of
100-200 MB (solves, products, Gram-Schmidt). glibc serves every block above its
mmap threshold (at most 32 MiB by default) with fresh pages from the kernel and
returns them on free, so each temporary is page-faulted and zeroed again:
about 12 s of kernel time in `benchmarks/bench_calibration.py` (re-basis
cycles 32 s -> 20 s with the setting below). Keeping blocks up to 1 GiB in the
heap lets them be reused. The cost is a higher resident size after the peak
(freed blocks are kept for reuse: peak RSS 4.2 -> 4.8 GB in that benchmark).

The ``frfcal`` command calls :func:`keep_large_allocations` once at start;
Python users can call it themselves. Elsewhere than glibc it does nothing.
"""

from __future__ import annotations

import ctypes
import sys

_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3


def keep_large_allocations(mmap_threshold: int = 1 << 30, trim_threshold: int = (1 << 31) - 1) -> bool:
    """Serve blocks below ``mmap_threshold`` bytes from the heap and keep freed memory for reuse.

    Parameters
    ----------
    mmap_threshold : int
        Blocks at least this large still get their own mapping (bytes, < 2 GiB).
    trim_threshold : int
        Free memory at the top of the heap above which glibc gives it back (bytes, < 2 GiB).

    Returns
    -------
    bool
        True when glibc accepted both settings; False on other platforms or C libraries.
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL("libc.so.6").mallopt
    except (OSError, AttributeError):  # not glibc (e.g. musl)
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    ok_mmap = mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold)) == 1
    ok_trim = mallopt(_M_TRIM_THRESHOLD, int(trim_threshold)) == 1
    return ok_mmap and ok_trim
