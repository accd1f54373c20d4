"""Axis-aligned image boxes [u_min, v_min, u_max, v_max] (pixels, continuous: a box's width
is u_max − u_min, no +1 pixel)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ._arrays import array_namespace

__all__ = ["box_iou"]


def box_iou(a, b):
    """IoU of boxes (…, 4) [u_min, v_min, u_max, v_max], broadcast over the leading axes
    (pairwise: ``box_iou(A[:, None], B[None])``): |a ∩ b| / (|a| + |b| − |a ∩ b|), with
    |a ∩ b| = max(0, min(a₂, b₂) − max(a₀, b₀)) · max(0, min(a₃, b₃) − max(a₁, b₁)) and
    |c| = max(0, c₂ − c₀) · max(0, c₃ − c₁); 0 where the union is empty. A box with
    u_max ≤ u_min or v_max ≤ v_min overlaps nothing (IoU 0 with any box). Computed in
    float (NumPy: float64). NumPy arrays of floats take a direct path (the association calls
    it per frame on a few boxes, where the namespace dispatch was most of the time)."""
    if isinstance(a, np.ndarray) and isinstance(b, np.ndarray) and a.dtype == b.dtype == np.float64:
        xp: Any = np

        def pos(x):
            return np.maximum(x, 0.0)  # = clip(x, 0, None), NaN included
    else:
        xp = array_namespace(a, b)
        a, b = xp.asarray(a, dtype=float), xp.asarray(b, dtype=float)

        def pos(x):
            return xp.clip(x, 0, None)
    w = pos(xp.minimum(a[..., 2], b[..., 2]) - xp.maximum(a[..., 0], b[..., 0]))
    h = pos(xp.minimum(a[..., 3], b[..., 3]) - xp.maximum(a[..., 1], b[..., 1]))
    inter = w * h

    def area(c):
        return pos(c[..., 2] - c[..., 0]) * pos(c[..., 3] - c[..., 1])

    union = area(a) + area(b) - inter
    with np.errstate(invalid="ignore", divide="ignore"):  # NaN boxes (no effect on JAX)
        return xp.where(union > 0, inter / xp.where(union > 0, union, 1.0), 0.0)
