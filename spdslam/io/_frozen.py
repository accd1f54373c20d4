"""Frozen NumPy fields and tolerant equality: what the sequence model's dataclasses
(``_sequence``, ``_classes``) validate and compare their arrays with."""

from __future__ import annotations

import numpy as np

__all__ = ["arrays_close", "frozen_array"]

_FLOAT_TOL = 1e-12  # equality of round-tripped floats


def arrays_close(a, b) -> bool:
    """Whether two arrays have one shape and equal entries up to 1e-12 (relative and
    absolute): equality of floats that went through a file and back."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    return a.shape == b.shape and bool(np.allclose(a, b, rtol=_FLOAT_TOL, atol=_FLOAT_TOL))


def frozen_array(x, shape=None) -> np.ndarray:
    """A read-only float copy of ``x``, of ``shape`` when given (else ``ValueError``)."""
    a = np.array(x, dtype=float)
    if shape is not None and a.shape != shape:
        raise ValueError(f"expected shape {shape}, got {a.shape}")
    a.setflags(write=False)
    return a
