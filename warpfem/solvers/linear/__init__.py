"""Linear solvers of the Newton systems behind one interface (see ``base``): ``pcg`` (block-Jacobi
CG with device-side scalars), ``direct`` (sparse Cholesky/LDL^T, symbolic analysis reused),
``amg`` (smoothed-aggregation AMG preconditioned CG, rigid-body near-null space), ``auto``."""

from warpfem.solvers.linear.base import (LINEAR_SOLVERS, LinearSolver, LinearSolveResult, MissingExtra,
                                         make_linear_solver)

__all__ = ["LINEAR_SOLVERS", "LinearSolver", "LinearSolveResult", "MissingExtra", "make_linear_solver"]
