"""Factor groups linearised by their type's closed form (``factors.closed_form``): NumPy on
the host, no tracing and no compiled program, with the same per-factor terms as the
general path (``_linearize``):

    r̃ = √ρ'(s) W r,   J̃ = √ρ'(s) W ∂r(x ⊞ δ)/∂δ|₀,   ½ρ(s),  s = ‖W r‖²,

finiteness of W r and W J, and the factor's validity. ``closed_forms(False)`` turns them off
(every group then takes the general path, and every type its compiled retraction), for the
tests and benchmarks that compare the two.
"""

from __future__ import annotations

import contextlib
from typing import Any, Iterator

import jax
import numpy as np

from ..factors import ClosedForm, closed_form
from ..geometry import native

__all__ = ["ClosedFormGroup", "closed_forms", "closed_forms_enabled", "closed_form_of"]

_ENABLED = [True]


@contextlib.contextmanager
def closed_forms(enabled: bool) -> Iterator[None]:
    """Within the block, problems built use the factor types' closed forms and the variable
    types' NumPy retractions (``geometry.manifold``'s ``host_retract``) (True, the default), or
    the general JAX path for every group and type (False)."""
    before = _ENABLED[0]
    _ENABLED[0] = bool(enabled)
    try:
        yield
    finally:
        _ENABLED[0] = before


def closed_forms_enabled() -> bool:
    """Whether problems built now use the closed forms (``closed_forms``)."""
    return _ENABLED[0]


def closed_form_of(spec: Any, tspecs: tuple) -> ClosedForm | None:
    """The closed form that linearises a group (``_problem._GroupSpec``), or None (turned
    off, or none for its residual, validity rule and variable types)."""
    if not _ENABLED[0]:
        return None
    return closed_form(spec.residual, spec.valid, tuple(tspecs[t].cls for t in spec.var_types))


class ClosedFormGroup:
    """A group's cost, sparse terms and terms (``_problem._GroupKernels``' interface) by its
    closed form."""

    #: nothing to compile (``_GroupKernels.sizes``)
    sizes: set[int] = set()

    def __init__(self, spec: Any, cf: ClosedForm):
        self.spec, self.cf = spec, cf
        D = spec.D
        iu, ju = np.triu_indices(D)
        self._upper = iu * D + ju

    def note(self, xs, Ts, mask, data) -> None:
        """(Nothing to keep: there is no program to compile ahead.)"""

    def compile_sizes(self, sizes) -> int:
        return 0

    def _terms(self, xs, Ts, mask, data, jacobian: bool):
        leaves, W = data
        args = jax.tree.unflatten(self.spec.args_treedef, [np.asarray(a) for a in leaves])
        with np.errstate(all="ignore"):  # a degenerate factor is reported as not finite
            r, J, valid = self.cf.linearize(xs, Ts, args, jacobian)
            W = None if W is None else np.asarray(W)
            lib = native.native_kernels()
            if lib is not None and (W is None or W.shape == (len(r), r.shape[1], r.shape[1])):
                r, J, finite, s = native.whiten(lib, W, r, J)  # the same, per row in C
            else:
                if W is not None:
                    r = (W @ r[:, :, None])[:, :, 0]
                    J = None if J is None else W @ J
                finite = np.all(np.isfinite(r), axis=1)
                if J is not None:
                    finite &= np.all(np.isfinite(J), axis=(1, 2))
                s = np.sum(r * r, axis=1)
            robust = self.spec.robust
            if robust is None:
                half_rho = 0.5 * s
            else:
                half_rho = 0.5 * robust.rho(s)
                sw = np.sqrt(robust.weight(s))
                r = sw[:, None] * r
                J = None if J is None else sw[:, None, None] * J
        half_rho = np.where(np.asarray(mask), half_rho, 0.0)
        return r, J, half_rho, (valid if self.spec.valid is not None else None), finite

    def cost(self, xs, mask, data):
        """(½ρ(s) (nf,), valid)."""
        _, _, half_rho, valid, _ = self._terms(xs, None, mask, data, False)
        return half_rho, valid

    def sparse(self, xs, Ts, mask, data):
        """(JᵀJ upper triangles (nf, D(D+1)/2), Jᵀr (nf, D), ½ρ(s), valid, finite) in NumPy
        (with the compiled kernels ``_Kernels.linearize_into`` sums them from ``terms``)."""
        r, J, half_rho, valid, finite = self._terms(xs, Ts, mask, data, True)
        n, D = len(r), self.spec.D
        # Jᵀ made contiguous first: matmul's stacked path is 2–3× faster on it than on a view
        H = np.take((np.ascontiguousarray(np.swapaxes(J, 1, 2)) @ J).reshape(n, D * D), self._upper, axis=1)
        g = np.einsum("nmi,nm->ni", J, r)
        return H, g, half_rho, valid, finite

    def terms(self, xs, Ts, mask, data):
        """(r (nf, m), J (nf, m, D), ½ρ(s), valid, finite)."""
        return self._terms(xs, Ts, mask, data, True)
