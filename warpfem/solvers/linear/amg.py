"""Smoothed-aggregation algebraic multigrid (pyamg) as the preconditioner of CG, for large, stiff
or nearly incompressible meshes where block-Jacobi CG needs thousands of iterations.

The near-null space handed to the aggregation is the six rigid-body modes of each vertex set
(three translations, three infinitesimal rotations about the centroid; "Algebraic multigrid by
smoothed aggregation for second and fourth order elliptic problems", Vanek, Mandel, Brezina), so
the coarse levels represent rigid motions of aggregates exactly, which is what block-Jacobi misses.
Fixed DOFs are identity rows and columns of the solved matrix; their rows of the near-null space are
zero. CG (scipy) runs on the host in float64 with one V-cycle per iteration.

``prepare`` builds the hierarchy (the expensive part) on the first call, then keeps it as the
preconditioner of the new matrices (still SPD, so CG stays valid; it converges more slowly as the
Hessian drifts) until a solve needs more than ``rebuild_factor`` times the iterations of the first
solve after the last build, or ``rebuild_every`` prepares have passed; then it rebuilds.
Extra ``[amg]`` (pyamg).
"""

from __future__ import annotations

import logging

import numpy as np
import warp as wp

from warpfem.model import rigid_body_modes
from warpfem.solvers.linear.base import HostLinearSolver, LinearSolveResult, require

log = logging.getLogger(__name__)


class AMGSolver(HostLinearSolver):
    """CG preconditioned by a smoothed-aggregation AMG V-cycle with rigid-body near-null space.

    Args:
        positions: (n, 3) vertex positions for the rigid-body modes (rest positions are fine:
            the modes only need to be near the null space). Default: translations only.
        rebuild_every: rebuild the hierarchy at least every this many ``prepare`` calls (1: every
            Newton iteration; default 0: only when the iterations grow).
        rebuild_factor: rebuild when a solve takes more than this times the iterations of the first
            solve with the current hierarchy.
        max_coarse: size of the coarsest level, solved directly.
        strength, aggregate, smooth, presmoother, postsmoother, max_levels, improve_candidates:
            passed to ``pyamg.smoothed_aggregation_solver`` (its defaults otherwise).
    """

    name = "amg"
    triangle = "full"

    def __init__(self, pattern, *, vec_type, scalar, positions=None, rebuild_every: int = 0, rebuild_factor: float = 2.0,
                 max_coarse: int = 300,
                 **sa_options):
        self.pyamg = require("pyamg", "amg", "'amg' linear solver")
        if int(rebuild_every) != rebuild_every or rebuild_every < 0:
            raise ValueError(f"rebuild_every must be an integer >= 0, got {rebuild_every!r}")
        if not (np.isfinite(rebuild_factor) and rebuild_factor >= 1.0):
            raise ValueError(f"rebuild_factor must be >= 1, got {rebuild_factor!r}")
        self.rebuild_factor = float(rebuild_factor)
        allowed = {"strength", "aggregate", "smooth", "presmoother", "postsmoother", "max_levels", "improve_candidates"}
        unknown = set(sa_options) - allowed
        if unknown:
            raise TypeError(f"unknown option(s) {sorted(unknown)}; known: rebuild_every, rebuild_factor, max_coarse, positions, "
                            f"{', '.join(sorted(allowed))}")
        self.rebuild_every = int(rebuild_every)
        # pyamg's defaults otherwise (symmetric strength, Jacobi-smoothed prolongation, symmetric
        # Gauss-Seidel): on the bunny at nu = 0.3 and 0.49 they gave the fewest iterations and the
        # cheapest cycle of the variants tried (docs/linear_solvers.md)
        # the coarsest level by sparse LU: pyamg's default dense pseudo-inverse (an SVD, redone at
        # every rebuild) cost more than the whole V-cycle hierarchy on the octopus
        self.sa_options = dict(max_coarse=int(max_coarse), coarse_solver="splu", **sa_options)
        n = pattern.num_rows
        if positions is None:
            self._B0 = rigid_body_modes(np.zeros((n, 3)))[:, :3] * np.sqrt(n)
        else:
            P = np.asarray(positions, dtype=np.float64)
            if P.shape != (n, 3) or not np.all(np.isfinite(P)):
                raise ValueError(f"positions must be finite with shape ({n}, 3), got {P.shape}")
            self._B0 = rigid_body_modes(P)
        self.ml = None
        self.setup_count = 0
        self._since_build = 0
        self._base_iters = None
        self._stale = False
        super().__init__(pattern, vec_type=vec_type, scalar=scalar)

    def _analyse(self, pattern):
        super()._analyse(pattern)
        self._stale = True  # a grown pattern: the hierarchy is rebuilt on the next prepare

    def _prepare(self, values, mask):
        import scipy.sparse

        A = self.host_matrix(values, mask)
        self._A_host = A
        self._since_build += 1
        if (self.ml is None or self._stale or self.rebuild_every == 1
                or not np.array_equal(self._mask_host, self._built_mask)
                or (self.rebuild_every > 1 and self._since_build > self.rebuild_every)):
            B = self._B0 * self._mask_host[:, None]
            Ab = scipy.sparse.bsr_matrix(A, blocksize=(3, 3))
            state = np.random.get_state()  # pyamg's estimates start from numpy's global generator: seeded,
            np.random.seed(0)  # so the hierarchy is the same every run (its state given back)
            try:
                self.ml = self.pyamg.smoothed_aggregation_solver(Ab, B=B, symmetry="hermitian", **self.sa_options)
            finally:
                np.random.set_state(state)
            self._M = self.ml.aspreconditioner(cycle="V")
            self.setup_count += 1
            self._since_build, self._base_iters, self._stale = 1, None, False
            self._built_mask = self._mask_host.copy()

    def _solve(self, b, x, *, tol, maxiter) -> LinearSolveResult:
        import scipy.sparse.linalg as spla

        bh = b.numpy().astype(np.float64).reshape(-1) * self._mask_host
        bn = float(np.linalg.norm(bh))
        if bn == 0.0 or not np.isfinite(bn):
            x.zero_()
            return LinearSolveResult(0, 0.0 if bn == 0.0 else float("nan"), bn == 0.0, host_syncs=1)
        count = [0]

        def cb(_xk):
            count[0] += 1

        xh, info = spla.cg(self._A_host, bh, rtol=tol, atol=0.0, maxiter=maxiter, M=self._M, callback=cb)
        xh *= self._mask_host  # exactly zero at fixed DOFs (CG leaves round-off there)
        rel = float(np.linalg.norm(self._A_host @ xh - bh) / bn)
        failed = "" if np.all(np.isfinite(xh)) else "non-finite solution"
        if info < 0:
            failed = f"scipy cg breakdown (info {info})"
        np_t = np.float32 if x.dtype == wp.vec3 else np.float64
        wp.copy(x, wp.array(xh.reshape(-1, 3).astype(np_t), dtype=x.dtype, device=self.device))
        if self._base_iters is None:
            self._base_iters = max(count[0], 1)
        elif count[0] > self.rebuild_factor * self._base_iters + 2:
            self._stale = True  # the next prepare rebuilds
        # converged: CG's own test (on its recursive residual) passed; ``residual`` is the true one
        return LinearSolveResult(count[0], rel, info == 0 and not failed, host_syncs=1, failed=failed)
