"""NumPy or JAX: the array namespace of the inputs.

Geometry is written once for both: a function given NumPy arrays (or Python numbers)
computes in NumPy, with no JAX dispatch (per-frame code in the front end, the scene
generators, the plots); given JAX arrays, or inside ``jit``/``vmap`` (tracers are
``jax.Array``s), it computes in JAX and is differentiable.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

__all__ = ["array_namespace"]


_PLAIN = (np.ndarray, np.generic, float, int, bool, type(None))


def array_namespace(*xs):
    """``jax.numpy`` if any leaf of ``xs`` is a JAX array (or tracer), else ``numpy``."""
    for x in xs:
        if isinstance(x, jax.Array):
            return jnp
        if isinstance(x, _PLAIN):
            continue
        if any(isinstance(leaf, jax.Array) for leaf in jax.tree.leaves(x)):
            return jnp
    return np
