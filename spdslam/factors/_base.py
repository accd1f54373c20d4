"""Factors: a residual function, its noise model and robust kernel, and the registry of
factor types.

A factor is a plain residual function of variable values and measurement data,

    r = residual(*variables, *data)  ∈ R^m,

plus a noise model and an optional robust kernel. Its contribution to the cost is
½ ρ(‖W r‖²), with W the square-root information matrix (WᵀW = Σ⁻¹) and ρ the kernel
(ρ(s) = s without one). Grouping factors of the same type and vectorising them is the
solver's job: factors whose residual function, variable types and data shapes agree are
stacked and linearised with one vmapped call.

A *factor type* is a subclass of :class:`Factor` that declares, in one place, its ``kind``
(a unique name), its ``residual`` function, the residual dimension ``dim``, the default
noise ``sigmas``, the robust-kernel ``group`` it belongs to, an optional ``valid`` rule
(degenerate geometry) and the names of the ``variables`` it connects; its constructor
turns measurements into validated data. Defining the subclass registers it
(``factor_types()``): the solver groups by it, and the mapping pipeline, its sigma table,
its robust-kernel groups, the CLI and the Jacobian test table all iterate over the
registry. ``CustomFactor`` wraps an ad-hoc residual function without declaring a type.
See docs/extending.md.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Any, Callable, ClassVar, cast

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry import array_namespace, manifold

__all__ = [
    "Factor",
    "FactorBatch",
    "CustomFactor",
    "Sigma",
    "GaussianNoise",
    "RobustKernel",
    "Huber",
    "Cauchy",
    "robust_weighting",
    "sqrt_information",
    "diagonal_sqrt_information",
    "tangent_jacobians",
    "factor_types",
    "robust_groups",
    "default_sigmas",
]


# --- robust kernels --------------------------------------------------------------------------


@dataclass(frozen=True)
class RobustKernel:
    """A robust loss ρ(s) of the squared whitened residual norm s = ‖W r‖² (NumPy in, NumPy
    out; JAX in, JAX out)."""

    k: float = 1.0

    def rho(self, s):  # pragma: no cover - abstract
        raise NotImplementedError

    def weight(self, s):
        """ρ'(s): the iteratively-reweighted-least-squares weight."""
        raise NotImplementedError  # pragma: no cover


@dataclass(frozen=True)
class Huber(RobustKernel):
    """ρ(s) = s for √s ≤ k, 2k√s − k² beyond."""

    def rho(self, s):
        xp = array_namespace(s)
        r = xp.sqrt(xp.maximum(s, 1e-300))
        return xp.where(r <= self.k, s, 2.0 * self.k * r - self.k**2)

    def weight(self, s):
        xp = array_namespace(s)
        r = xp.sqrt(xp.maximum(s, 1e-300))
        return xp.where(r <= self.k, 1.0, self.k / r)


@dataclass(frozen=True)
class Cauchy(RobustKernel):
    """ρ(s) = k² log(1 + s/k²)."""

    def rho(self, s):
        return self.k**2 * array_namespace(s).log1p(s / self.k**2)

    def weight(self, s):
        return 1.0 / (1.0 + s / self.k**2)


def robust_weighting(robust: RobustKernel | None, r, J=None):
    """(½ρ(s), √ρ'(s)·r, √ρ'(s)·J) for s = ‖r‖²: the cost term and the iteratively
    reweighted residual and Jacobian; (½s, r, J) without a kernel."""
    s = jnp.sum(r * r)
    if robust is None:
        return 0.5 * s, r, J
    sw = jnp.sqrt(robust.weight(s))
    return 0.5 * robust.rho(s), sw * r, (None if J is None else sw * J)


# --- noise models ----------------------------------------------------------------------------


def sqrt_information(
    dim: int,
    sigma: Any = None,
    information: Any = None,
    covariance: Any = None,
) -> np.ndarray:
    """Square-root information W (dim×dim, upper triangular) with WᵀW = Σ⁻¹.

    Exactly one of ``sigma`` (scalar or per-component standard deviations),
    ``information`` (Σ⁻¹) or ``covariance`` (Σ) may be given; none means W = I.
    """
    given = [x is not None for x in (sigma, information, covariance)]
    if sum(given) > 1:
        raise ValueError("give at most one of sigma, information, covariance")
    if sigma is not None:
        try:
            s = np.broadcast_to(np.asarray(sigma, dtype=float), (dim,))
        except ValueError:
            raise ValueError(
                f"sigma must be a scalar or {dim} values, got shape {np.shape(sigma)}"
            ) from None
        if not np.all(np.isfinite(s)) or np.any(s <= 0):
            raise ValueError(f"sigma must be finite and positive, got {np.asarray(sigma).tolist()}")
        return np.diag(1.0 / s)
    if covariance is not None:
        cov = np.asarray(covariance, dtype=float)
        if cov.shape != (dim, dim):
            raise ValueError(f"covariance must be {dim}x{dim}, got {cov.shape}")
        information = np.linalg.inv(cov)
    if information is not None:
        info = np.asarray(information, dtype=float)
        if info.shape != (dim, dim):
            raise ValueError(f"information must be {dim}x{dim}, got {info.shape}")
        info = 0.5 * (info + info.T)
        try:
            L = np.linalg.cholesky(info)
        except np.linalg.LinAlgError:
            raise ValueError("information matrix is not positive definite") from None
        return L.T
    return np.eye(dim)


def diagonal_sqrt_information(sigma: Any, n: int, dim: int) -> np.ndarray:
    """W = diag(1/σ) for each of n factors (n, dim, dim): ``sigma`` a scalar, dim values or
    (n, dim), each finite and positive (``sqrt_information``'s check, row by row)."""
    try:
        s = np.broadcast_to(np.asarray(sigma, dtype=float), (n, dim))
    except ValueError:
        raise ValueError(f"sigma must be a scalar, {dim} values or ({n}, {dim}), got shape {np.shape(sigma)}") from None
    wrong = np.any(~np.isfinite(s) | (s <= 0), axis=1)
    if wrong.any():
        raise ValueError(f"sigma must be finite and positive, got {s[wrong][0].tolist()}")
    W = np.zeros((n, dim, dim))
    W[:, np.arange(dim), np.arange(dim)] = 1.0 / s
    return W


class GaussianNoise:
    """A Gaussian noise model, held as its square-root information W (WᵀW = Σ⁻¹).

    ``GaussianNoise.sigmas(σ, dim)``, ``.information(Σ⁻¹)``, ``.covariance(Σ)``; a factor
    takes it as ``noise=`` (or the same as ``sigma=``, ``information=``, ``covariance=``).
    """

    __slots__ = ("sqrt_info",)

    def __init__(self, sqrt_info):
        W = np.asarray(sqrt_info, dtype=float)
        if W.ndim != 2 or W.shape[0] != W.shape[1] or not np.all(np.isfinite(W)):
            raise ValueError(f"a square-root information matrix must be finite and square, got shape {W.shape}")
        self.sqrt_info = W

    @classmethod
    def sigmas(cls, sigma, dim: int | None = None) -> "GaussianNoise":
        s = np.atleast_1d(np.asarray(sigma, dtype=float))
        return cls(sqrt_information(s.size if dim is None else dim, sigma=sigma))

    @classmethod
    def information(cls, information) -> "GaussianNoise":
        info = np.asarray(information, dtype=float)
        return cls(sqrt_information(info.shape[0], information=info))

    @classmethod
    def covariance(cls, covariance) -> "GaussianNoise":
        cov = np.asarray(covariance, dtype=float)
        return cls(sqrt_information(cov.shape[0], covariance=cov))

    @property
    def dim(self) -> int:
        return int(self.sqrt_info.shape[0])

    def __repr__(self) -> str:
        return f"GaussianNoise(dim={self.dim})"


@dataclass(frozen=True)
class Sigma:
    """A factor type's default standard deviation for ``size`` components of its residual
    (None: all of them), in ``unit``; ``name`` (default: the factor's kind) is what the
    mapping's sigma table and ``spdslam run --sigma NAME=VALUE`` call it."""

    value: float
    unit: str
    name: str | None = None
    size: int | None = None


# --- factors and the registry ----------------------------------------------------------------

_REGISTRY: dict[str, type["Factor"]] = {}

_NOISE_ARGS = ("sigma", "information", "covariance", "noise", "sqrt_info")


class Factor:
    """One residual term ½ρ(‖W r‖²) of a factor graph (see the module docstring).

    Instances hold ``keys`` (the variables, in the order of the residual's arguments),
    ``args`` (the measurement data: a tuple of arrays or pytrees of arrays), ``sqrt_info``
    (W, (m, m); None means identity) and ``robust`` (a kernel or None); they are immutable
    (``replace``, ``with_robust`` make changed copies).

    Noise, for every factor type: at most one of ``sigma`` (scalar or per component),
    ``information``, ``covariance`` (m×m), ``noise`` (a :class:`GaussianNoise`); none
    gives the type's default ``sigmas`` (W = I for types without one).
    """

    kind: ClassVar[str] = ""
    residual: ClassVar[Callable[..., Any]]
    dim: ClassVar[int | None] = None
    sigmas: ClassVar[tuple[Sigma, ...]] = ()
    group: ClassVar[str | None] = None
    valid: ClassVar[Callable[..., Any] | None] = None
    variables: ClassVar[tuple[str, ...]] = ()

    __slots__ = ("keys", "args", "sqrt_info", "robust", "_flat")
    keys: tuple
    args: tuple
    sqrt_info: np.ndarray | None
    robust: RobustKernel | None
    _flat: tuple

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        kind = cls.__dict__.get("kind")
        if not isinstance(kind, str) or not kind:
            return  # an intermediate base, or CustomFactor
        for name in ("residual", "dim", "group"):
            if getattr(cls, name, None) is None:
                raise TypeError(f"factor type {cls.__name__} ({kind!r}) declares no {name}")
        sizes = [s.size for s in cls.sigmas]
        if cls.sigmas and (sum(cls.dim if n is None else n for n in sizes) != cls.dim
                           or (None in sizes and len(sizes) > 1)):
            raise TypeError(f"factor type {cls.__name__}: its sigmas do not cover its {cls.dim} residuals")
        old = _REGISTRY.get(kind)
        if old is not None and (old.__module__, old.__qualname__) != (cls.__module__, cls.__qualname__):
            raise TypeError(f"factor kind {kind!r} is already registered by {old.__module__}.{old.__qualname__}")
        _REGISTRY[kind] = cls

    def __init__(self, keys, args: tuple = (), *, sigma: Any = None, information: Any = None,
                 covariance: Any = None, noise: GaussianNoise | None = None,
                 robust: RobustKernel | None = None, sqrt_info: Any = None):
        if getattr(self, "residual", None) is None:
            raise TypeError(f"{type(self).__name__} is not a factor type (it declares no "
                            "residual): use a registered type or CustomFactor")
        keys = tuple(keys)
        if self.variables and len(keys) != len(self.variables):
            raise ValueError(
                f"{type(self).__name__} connects {len(self.variables)} variables "
                f"({', '.join(self.variables)}), got {len(keys)} keys"
            )
        W = self._whitening(sigma, information, covariance, noise, sqrt_info)
        object.__setattr__(self, "keys", keys)
        object.__setattr__(self, "args", tuple(args))
        object.__setattr__(self, "sqrt_info", W)
        object.__setattr__(self, "robust", robust)

    @classmethod
    def default_sigma(cls) -> np.ndarray | None:
        """The default σ per residual component (dim,), None for W = I."""
        if not cls.sigmas:
            return None
        # (a type with sigmas declares its dim: __init_subclass__)
        return np.concatenate([np.full(cast(int, cls.dim) if s.size is None else s.size, float(s.value))
                               for s in cls.sigmas])

    def _whitening(self, sigma, information, covariance, noise, sqrt_info):
        given = [n for n, v in zip(_NOISE_ARGS, (sigma, information, covariance, noise, sqrt_info))
                 if v is not None]
        if len(given) > 1:
            raise ValueError(f"give at most one of sigma, information, covariance, noise; got {', '.join(given)}")
        if noise is not None:
            if not isinstance(noise, GaussianNoise):
                raise TypeError(f"noise must be a GaussianNoise, got {type(noise).__name__}")
            sqrt_info = noise.sqrt_info
        if sqrt_info is not None:
            W = np.asarray(sqrt_info, dtype=float)
            if self.dim is not None and W.shape != (self.dim, self.dim):
                raise ValueError(f"{self.kind}: the noise model is {W.shape}, the residual has dimension {self.dim}")
            return W
        if sigma is None and information is None and covariance is None:
            sigma = self.default_sigma()
            if sigma is None:
                return None if self.dim is None else np.eye(self.dim)
        if self.dim is None:
            raise ValueError(f"{self.kind}: give sqrt_info or noise (the residual dimension is not declared)")
        return sqrt_information(self.dim, sigma, information, covariance)

    def __setattr__(self, name, value):
        raise AttributeError(f"{type(self).__name__} is immutable: use replace() or with_robust()")

    def __getstate__(self) -> dict:
        return {name: getattr(self, name) for cls in type(self).__mro__
                for name in cls.__dict__.get("__slots__", ()) if name != "_flat"}

    def __setstate__(self, state: dict) -> None:
        for name, value in state.items():
            object.__setattr__(self, name, value)

    def replace(self, **changes) -> "Factor":
        """A copy with ``keys``, ``args``, ``sqrt_info`` or ``robust`` replaced."""
        out = copy.copy(self)
        for name, value in changes.items():
            if name not in Factor.__slots__ or name == "_flat":
                raise TypeError(f"cannot replace {name!r} of a factor")
            if name in ("keys", "args"):
                value = tuple(value)
            if name == "sqrt_info" and value is not None:
                value = np.asarray(value, dtype=float)
            object.__setattr__(out, name, value)
        return out

    def flat_args(self) -> tuple:
        """(leaves of ``args`` as NumPy arrays, their tree structure, ((shape, dtype), …) of
        the leaves): the layout the solver stacks factors by, computed once per factor
        (factors are immutable; a copy made by ``replace`` computes its own)."""
        try:
            return self._flat
        except AttributeError:
            leaves, treedef = jax.tree.flatten(self.args)
            leaves = [np.asarray(x) for x in leaves]
            flat = (leaves, treedef, tuple((x.shape, x.dtype.str) for x in leaves))
            object.__setattr__(self, "_flat", flat)
            return flat

    def with_robust(self, robust: RobustKernel | None) -> "Factor":
        """A copy with another robust kernel."""
        return self.replace(robust=robust)

    def evaluate(self, *values):
        """Whitened residual W r at the given variable values (no robust kernel)."""
        r = jnp.atleast_1d(self.residual(*values, *self.args))
        if self.sqrt_info is None:
            return r
        return jnp.asarray(self.sqrt_info) @ r

    def error(self, *values) -> float:
        """½ ρ(‖W r‖²), this factor's contribution to the cost."""
        s = jnp.sum(self.evaluate(*values) ** 2)
        if self.robust is not None:
            s = self.robust.rho(s)
        return 0.5 * float(s)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.kind}, keys={self.keys!r})"


class FactorBatch:
    """n factors of one registered type held as columns (the jaxls way): the keys as one
    column per variable, the measurement data stacked along a leading axis (the leaves of
    one factor's ``args`` with an extra first axis), W stacked (n, m, m) or None (identity),
    one robust kernel. The solver lays a batch out with array operations, without a Python
    object per factor; ``batch[i]`` and iteration give the same factors one by one
    (``Factor``), for code that wants them. Made by a type's ``many`` (box and pose
    factors); a graph holds it as one entry (``NonlinearFactorGraph.add``).

    ``treedef``/``shapes``: the tree structure of one factor's ``args`` and its leaves'
    ((shape, dtype), …), as ``Factor.flat_args`` gives them.
    """

    __slots__ = ("factor_type", "key_columns", "leaves", "treedef", "shapes", "sqrt_info", "robust")
    factor_type: "type[Factor]"
    key_columns: tuple
    leaves: list
    treedef: Any
    shapes: tuple
    sqrt_info: np.ndarray | None
    robust: RobustKernel | None

    def __init__(self, factor_type: "type[Factor]", key_columns, leaves, treedef, shapes,
                 sqrt_info=None, robust: RobustKernel | None = None):
        cols = tuple(list(c) for c in key_columns)
        n = len(cols[0]) if cols else 0
        if any(len(c) != n for c in cols) or any(len(a) != n for a in leaves) or (
                sqrt_info is not None and len(sqrt_info) != n):
            raise ValueError(f"{factor_type.__name__} batch: key columns, data and noise of different lengths")
        for name, value in (("factor_type", factor_type), ("key_columns", cols), ("leaves", list(leaves)),
                            ("treedef", treedef), ("shapes", tuple(shapes)), ("sqrt_info", sqrt_info),
                            ("robust", robust)):
            object.__setattr__(self, name, value)

    def __setattr__(self, name, value):
        raise AttributeError("FactorBatch is immutable: use with_robust()")

    @property
    def kind(self) -> str:
        return self.factor_type.kind

    @property
    def residual(self) -> Callable[..., Any]:
        return self.factor_type.residual

    @property
    def valid(self) -> Callable[..., Any] | None:
        return self.factor_type.valid

    def __len__(self) -> int:
        return len(self.key_columns[0]) if self.key_columns else 0

    def __getitem__(self, i: int) -> Factor:
        n = len(self)
        if not -n <= i < n:
            raise IndexError(f"factor {i} of a batch of {n}")
        i %= n
        f = object.__new__(self.factor_type)
        leaves = [a[i] for a in self.leaves]
        for name, value in (("keys", tuple(c[i] for c in self.key_columns)),
                            ("args", tuple(jax.tree.unflatten(self.treedef, leaves))),
                            ("sqrt_info", None if self.sqrt_info is None else self.sqrt_info[i]),
                            ("robust", self.robust), ("_flat", (leaves, self.treedef, self.shapes))):
            object.__setattr__(f, name, value)
        return f

    def __iter__(self):
        return (self[i] for i in range(len(self)))

    def with_robust(self, robust: RobustKernel | None) -> "FactorBatch":
        """A copy with another robust kernel."""
        return FactorBatch(self.factor_type, self.key_columns, self.leaves, self.treedef, self.shapes,
                           self.sqrt_info, robust)

    def __repr__(self) -> str:
        return f"FactorBatch({self.kind}, {len(self)} factors)"


class CustomFactor(Factor):
    """A factor of an ad-hoc residual function, without a registered type.

    ``CustomFactor(residual, keys, args=(), sqrt_info=None, robust=None, valid=None,
    name="")``: ``residual(*variables, *args)`` a JAX-traceable function of the values of
    ``keys`` (in order); ``valid`` an optional ``valid(*variables, *args) -> bool`` (False
    marks degenerate geometry; the solver rejects any step that makes a valid factor
    invalid); ``name`` the kind shown in messages (default: the function's name). Noise as
    for every factor (``sigma`` etc. need the dimension: give ``sqrt_info`` or ``noise``).
    """

    __slots__ = ("residual", "valid", "name")
    name: str

    def __init__(self, residual: Callable[..., Any], keys, args: tuple = (), sqrt_info: Any = None,
                 robust: RobustKernel | None = None, valid: Callable[..., Any] | None = None,
                 name: str = "", *, noise: GaussianNoise | None = None):
        object.__setattr__(self, "residual", residual)
        object.__setattr__(self, "valid", valid)
        object.__setattr__(self, "name", name)
        super().__init__(keys, args, noise=noise, robust=robust, sqrt_info=sqrt_info)

    @property
    def kind(self) -> str:  # type: ignore[override]  # per instance, not the ClassVar of a registered type
        return self.name or getattr(self.residual, "__name__", "factor")


def factor_types() -> dict[str, type[Factor]]:
    """The registered factor types, {kind: class}, in the order they were defined."""
    return dict(_REGISTRY)


def robust_groups() -> dict[str, tuple[str, ...]]:
    """{group: kinds}: the factor kinds a robust kernel chosen for a group applies to."""
    out: dict[str, list[str]] = {}
    for kind, cls in _REGISTRY.items():
        out.setdefault(cast(str, cls.group), []).append(kind)  # registered types declare one
    return {g: tuple(k) for g, k in out.items()}


def default_sigmas() -> dict[str, Sigma]:
    """{name: Sigma} of every registered type's default noise (names as ``Sigma.name``,
    the kind by default)."""
    out = {}
    for kind, cls in _REGISTRY.items():
        for s in cls.sigmas:
            out[s.name or kind] = s
    return out


def tangent_jacobians(residual: Callable, values: tuple, args: tuple = ()):
    """r and the Jacobians ∂r(x₁ ⊞ δ₁, …)/∂δₖ at δ = 0, one (m, dₖ) block per variable.

    Derivatives are with respect to each variable's tangent coordinates (its registered
    retraction), evaluated by forward-mode autodiff.
    """
    values = tuple(values)
    dims = [manifold.tangent_dim(v) for v in values]

    def perturbed(*deltas):
        xs = [manifold.retract(v, d) for v, d in zip(values, deltas)]
        return jnp.atleast_1d(residual(*xs, *args))

    zeros = tuple(jnp.zeros(d) for d in dims)
    r = perturbed(*zeros)
    J = jax.jacfwd(perturbed, argnums=tuple(range(len(values))))(*zeros)
    return r, list(J)

