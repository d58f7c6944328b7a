"""Giving freed heap memory back to the system during long runs (glibc's malloc_trim).

glibc raises its mmap threshold each time a large block is freed, so after a few frames the
large short-lived buffers of every relocalization (image pyramids, descriptor and activation
tensors) come from the heap, and the pose graph's small long-lived nodes allocated between them
keep the heap from shrinking: in the long-run benchmark (BENCHMARKS.md, "Long runs") the SLAM
process grew many times faster than what it holds. `malloc_trim(0)` returns every free page of
the heap, for well under a millisecond.
"""

from __future__ import annotations

import ctypes
from functools import cache


@cache
def _malloc_trim():
    try:
        fn = ctypes.CDLL(None).malloc_trim  # the process's C library
    except (OSError, AttributeError):  # not glibc (macOS, musl): nothing to do
        return None
    fn.argtypes, fn.restype = [ctypes.c_size_t], ctypes.c_int
    return fn


def release_free_memory() -> bool:
    """Return free heap pages to the operating system; False where the C library cannot."""
    fn = _malloc_trim()
    return bool(fn(0)) if fn is not None else False
