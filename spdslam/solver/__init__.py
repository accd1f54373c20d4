"""Nonlinear least squares on factor graphs: Values, graphs, LM / GN, batched solves.

Cost F(x) = Σᵢ ½ ρᵢ(‖Wᵢ rᵢ(x)‖²) (gtsam's ``graph.error`` convention), minimised over the
free variables; steps are taken in tangent coordinates, x ⊞ δ (``spdslam.geometry.manifold``).

One rule (``_lm``: damping, gain ratio, λ schedules, stopping) and one per-factor
linearisation (``_linearize``: whitening, robust weighting, validity), driven two ways:
``LevenbergMarquardt(...).optimize(graph, values)`` / ``Dogleg`` / ``GaussNewton`` run the sparse host
loop (``_optimizers``, CHOLMOD on the host), and ``.batched(graph, values)`` (a
``BatchedProblem`` of array data) / ``.optimize_batched(graphs, values_list)`` run many
problems of one structure in one jitted loop (``_batched``). ``enable_compilation_cache`` /
``ensure_compilation_cache`` (``_cache``) turn on JAX's persistent compilation cache;
``stored_jit`` (``_stored``) keeps spdslam's own compiled programs on disk between processes;
``retain_freed_memory`` (``_allocator``) keeps glibc from handing large freed blocks back.
``FixedLagSmoother`` (``_smoother``) is the online mapper's window solve and marginalisation,
beside the batch optimisers. Imports
only ``spdslam.geometry`` and ``spdslam.factors``.
"""

from ._allocator import ALLOCATOR_ENV as ALLOCATOR_ENV
from ._allocator import retain_freed_memory as retain_freed_memory
from ._batched import DEFAULT_LANES as DEFAULT_LANES
from ._batched import BatchedProblem as BatchedProblem
from ._batched import BatchedResult as BatchedResult
from ._cache import CACHE_ENV as CACHE_ENV
from ._cache import CACHE_MIN_COMPILE_SECS as CACHE_MIN_COMPILE_SECS
from ._cache import CACHE_OFF as CACHE_OFF
from ._cache import DEFAULT_CACHE_DIR as DEFAULT_CACHE_DIR
from ._cache import cache_dir as cache_dir
from ._cache import enable_compilation_cache as enable_compilation_cache
from ._cache import ensure_compilation_cache as ensure_compilation_cache
from ._closed_form import closed_forms as closed_forms
from ._compile import AUTO_OPTIMIZE_WORK as AUTO_OPTIMIZE_WORK
from ._compile import clear_caches as clear_caches
from ._graph import NonlinearFactorGraph as NonlinearFactorGraph
from ._keys import L as L
from ._keys import Symbol as Symbol
from ._keys import X as X
from ._linear import HAVE_CHOLMOD as HAVE_CHOLMOD
from ._linear import HAVE_CVXOPT as HAVE_CVXOPT
from ._linear import default_sparse_solver as default_sparse_solver
from ._lm import CONVERGED_REASONS as CONVERGED_REASONS
from ._lm import DoglegParams as DoglegParams
from ._lm import GaussNewtonParams as GaussNewtonParams
from ._lm import IterationRecord as IterationRecord
from ._lm import LevenbergMarquardtParams as LevenbergMarquardtParams
from ._lm import OptimizerParams as OptimizerParams
from ._marginals import marginal_covariances as marginal_covariances
from ._optimizers import Dogleg as Dogleg
from ._optimizers import GaussNewton as GaussNewton
from ._optimizers import LevenbergMarquardt as LevenbergMarquardt
from ._optimizers import OptimizationResult as OptimizationResult
from ._optimizers import Optimizer as Optimizer
from ._problem import Problem as Problem
from ._problem import group_kernels as group_kernels
from ._smoother import FixedLagSmoother as FixedLagSmoother
from ._smoother import SmootherUpdate as SmootherUpdate
from ._smoother import padded_size as padded_size
from ._smoother import padded_sizes_above as padded_sizes_above
from ._stored import StoredProgram as StoredProgram
from ._stored import stored_jit as stored_jit
from ._values import Values as Values
