"""Nonlinear least squares on factor graphs: Values, graphs, LM / GN, batched solves.

Cost F(x) = Σᵢ ½ ρᵢ(‖Wᵢ rᵢ(x)‖²) (gtsam's ``graph.error`` convention), minimised over the
free variables; steps are taken in tangent coordinates, x ⊞ δ (``spdslam.manifold``).
Many problems of one structure: ``BatchedProblem`` (a template problem, data and values as
arrays with a leading batch axis) or ``solve_batched`` (a list of graphs and Values).
"""

from ._batched import BatchedProblem, BatchedResult, solve_batched
from ._graph import FactorGraph, NonlinearFactorGraph
from ._linear import HAVE_CHOLMOD
from ._optimizers import (
    CONVERGED_REASONS,
    GaussNewton,
    GaussNewtonParams,
    IterationRecord,
    LevenbergMarquardt,
    LevenbergMarquardtParams,
    OptimizationResult,
    OptimizerParams,
)
from ._problem import Problem
from ._values import Values

__all__ = [
    "Values",
    "NonlinearFactorGraph",
    "FactorGraph",
    "Problem",
    "OptimizerParams",
    "LevenbergMarquardtParams",
    "GaussNewtonParams",
    "LevenbergMarquardt",
    "GaussNewton",
    "IterationRecord",
    "OptimizationResult",
    "CONVERGED_REASONS",
    "solve_batched",
    "BatchedProblem",
    "BatchedResult",
    "HAVE_CHOLMOD",
]
