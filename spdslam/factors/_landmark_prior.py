"""A Gaussian prior on a whole landmark, in the landmark's own chart.

    r(x) = (x ⊟ x̄) − o,   x ⊟ x̄ = manifold.local(x̄, x) ∈ R⁹,   cost ½‖W r‖²,

with x̄ the prior's point, o an offset in its chart (default 0: a prior with mean x̄) and
WᵀW the information. It is what the online mapper (``spdslam.mapping.OnlineMapper``) keeps
of the views that left its window: the Gauss–Newton quadratic ½δᵀHδ + gᵀδ of their factors
at a linearisation point x₀ is, up to a constant, this prior with x̄ = x₀, o = −H⁺g and
WᵀW = H. The offset stays in x₀'s chart (never retracted): along a weakly determined
direction it may be large while W o is not. SPD and RTS landmarks (9 tangent coordinates);
the Full quadric's 10 are not taken.
"""

from __future__ import annotations

from typing import Any, Hashable

import jax
import numpy as np

from ..geometry import manifold
from ._base import Factor

__all__ = ["LandmarkPriorFactor", "landmark_prior_residual"]


def landmark_prior_residual(landmark, mean, offset):
    """r = (landmark ⊟ mean) − offset (the mean's chart); zero when landmark = mean ⊞ offset."""
    return manifold.local(mean, landmark) - offset


class LandmarkPriorFactor(Factor):
    """Prior x ≈ x̄ ⊞ o on a landmark: r = (x ⊟ x̄) − o ∈ R⁹ (``landmark_prior_residual``,
    ``offset`` o default 0); noise as for every factor (``information=H``; a marginal's H may
    be only positive semi-definite: give ``sqrt_info`` then). No default: without a noise
    model W = I."""

    kind = "landmark_prior"
    residual = staticmethod(landmark_prior_residual)
    variables = ("landmark",)
    dim = 9
    group = "landmark_prior"

    def __init__(self, landmark_key: Hashable, mean: Any, offset: Any = None, **noise):
        try:
            d = manifold.tangent_dim(mean)
        except TypeError:
            raise TypeError(f"the prior mean must be a landmark, got {type(mean).__name__}") from None
        if d != self.dim:
            raise ValueError(f"a landmark prior needs a landmark with {self.dim} tangent "
                             f"coordinates (SPD or RTS), got {type(mean).__name__} with {d}")
        mean = jax.tree.map(lambda a: np.asarray(a, dtype=float), mean)
        o = np.zeros(self.dim) if offset is None else np.asarray(offset, dtype=float)
        if o.shape != (self.dim,) or not np.all(np.isfinite(o)):
            raise ValueError(f"the offset must be {self.dim} finite numbers, got shape {o.shape}")
        super().__init__((landmark_key,), (mean, o), **noise)
