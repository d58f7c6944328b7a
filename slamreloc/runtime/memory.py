"""Giving freed heap memory back to the system during long runs (glibc's malloc_trim).

glibc raises its mmap threshold each time a large block is freed, so after a few frames the
large short-lived buffers of every relocalization (image pyramids, descriptor and activation
tensors) come from the heap, and the pose graph's small long-lived nodes allocated between them
keep the heap from shrinking: in the long-run benchmark (BENCHMARKS.md, "Long runs") the SLAM
process grew many times faster than what it holds. `malloc_trim(0)` returns every free page of
the heap, for well under a millisecond.

A server's threads each get a malloc arena of their own, which reserves 64 MB of address space
(untouched: not resident) on first use: `limit_malloc_arenas` keeps them to a few, so the
server's address space stays near what it holds (a host that caps address space, `ulimit -v`,
counts the reservations).
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


M_ARENA_MAX = -8  # glibc's mallopt parameter


def limit_malloc_arenas(n: int = 2) -> bool:
    """At most `n` malloc arenas for the threads started from now on (glibc `mallopt`); False
    where the C library has no such setting."""
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_ARENA_MAX, n))
