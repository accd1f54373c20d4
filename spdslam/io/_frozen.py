"""Frozen NumPy fields and tolerant equality: what the sequence model's dataclasses
(``_sequence``, ``_classes``) validate and compare their arrays with."""

from __future__ import annotations

import numpy as np

__all__ = ["_close", "_frozen_array"]

_FLOAT_TOL = 1e-12  # equality of round-tripped floats


def _close(a, b) -> bool:
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    return a.shape == b.shape and bool(np.allclose(a, b, rtol=_FLOAT_TOL, atol=_FLOAT_TOL))


def _frozen_array(x, shape=None) -> np.ndarray:
    a = np.array(x, dtype=float)
    if shape is not None and a.shape != shape:
        raise ValueError(f"expected shape {shape}, got {a.shape}")
    a.setflags(write=False)
    return a
