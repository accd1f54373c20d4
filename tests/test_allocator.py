"""``solver.retain_freed_memory``: glibc's thresholds set, or nothing where it does not apply."""

import ctypes
import sys

import numpy as np
import pytest

from spdslam.solver import ALLOCATOR_ENV, retain_freed_memory

glibc = sys.platform.startswith("linux") and hasattr(ctypes.CDLL(None), "gnu_get_libc_version")


def test_system_leaves_the_defaults_and_a_bad_value_is_refused(monkeypatch):
    monkeypatch.setenv(ALLOCATOR_ENV, "system")
    assert retain_freed_memory() is False
    monkeypatch.setenv(ALLOCATOR_ENV, "huge")
    with pytest.raises(ValueError, match=f"{ALLOCATOR_ENV} must be 'retain' or 'system', got 'huge'"):
        retain_freed_memory()


@pytest.mark.skipif(not glibc, reason="glibc's mallopt")
def test_on_glibc_the_thresholds_are_set_and_arrays_still_work(monkeypatch):
    monkeypatch.delenv(ALLOCATOR_ENV, raising=False)
    assert retain_freed_memory() is True
    a = np.ones((4096, 1024))  # 32 MB: from the heap now, freed and reused
    del a
    b = np.zeros((4096, 1024))
    assert float(b.sum()) == 0.0
