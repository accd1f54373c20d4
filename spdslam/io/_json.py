"""Strict JSON: every file the project writes is RFC 8259 JSON, never ``NaN`` or ``Infinity``."""

from __future__ import annotations

import json
import math
from typing import Any

import numpy as np

__all__ = ["strict", "dumps_strict"]


def strict(obj: Any) -> Any:
    """``obj`` with every float that is NaN or infinite replaced by None (JSON ``null``:
    "not computed"), NumPy scalars and arrays as Python numbers and lists, tuples as lists."""
    if isinstance(obj, dict):
        return {str(k) if not isinstance(k, str) else k: strict(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [strict(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return strict(obj.tolist())
    if isinstance(obj, (bool, np.bool_)):
        return bool(obj)
    if isinstance(obj, (int, np.integer)):
        return int(obj)
    if isinstance(obj, (float, np.floating)):
        return float(obj) if math.isfinite(obj) else None
    return obj


def dumps_strict(obj: Any, indent: int | None = 1, **kw) -> str:
    """``json.dumps`` of :func:`strict` (``obj``) with ``allow_nan=False``."""
    return json.dumps(strict(obj), indent=indent, allow_nan=False, **kw)
