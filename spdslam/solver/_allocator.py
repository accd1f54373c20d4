"""The C allocator's handling of large blocks (glibc): kept for reuse instead of handed back.

A linearisation, a cost evaluation or an association pass makes NumPy temporaries of 1–50 MB
(a group's stacked Jacobians, their JᵀJ). With glibc's defaults a block above the mmap
threshold (128 kB, rising to at most 32 MB as such blocks are freed) is mapped for that one
array and unmapped when freed, and free memory at the top of the heap is trimmed back to the
system: every such array is then fresh pages, and the kernel zero-fills each page on its
first touch. ``retain_freed_memory`` sets glibc's mmap and trim thresholds (``mallopt``) to
``limit`` bytes, so that blocks up to that size come from the heap and freed ones are reused;
the process keeps its peak heap until it exits (docs/performance.md, section 8, "Fresh pages").

It changes the whole process's allocator, so the library never calls it by itself: the
``spdslam`` command does when a command starts, and a program that embeds spdslam may.
``SPDSLAM_ALLOCATOR=system`` leaves glibc's defaults.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import sys

__all__ = ["ALLOCATOR_ENV", "retain_freed_memory"]

#: ``system``: ``retain_freed_memory`` does nothing (glibc's defaults stay)
ALLOCATOR_ENV = "SPDSLAM_ALLOCATOR"

_M_TRIM_THRESHOLD = -1  # glibc's malloc.h
_M_MMAP_THRESHOLD = -3


def retain_freed_memory(limit: int = 1 << 30) -> bool:
    """glibc's mmap and trim thresholds set to ``limit`` bytes (module docstring); True if
    both were set, False where there is no glibc (macOS, musl), where ``SPDSLAM_ALLOCATOR``
    is ``system``, or where glibc refused a value."""
    value = os.environ.get(ALLOCATOR_ENV, "").strip().lower()
    if value not in ("", "retain", "system"):
        raise ValueError(f"{ALLOCATOR_ENV} must be 'retain' or 'system', got {value!r}")
    if value == "system" or not sys.platform.startswith("linux") or int(limit) <= 0:
        return False
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
        libc.gnu_get_libc_version  # noqa: B018 - glibc only (musl has mallopt as a stub)
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    limit = min(int(limit), 2**31 - 1)
    # the trim threshold first: setting either fixes both (no dynamic mmap threshold)
    return bool(mallopt(_M_TRIM_THRESHOLD, limit)) and bool(mallopt(_M_MMAP_THRESHOLD, limit))
