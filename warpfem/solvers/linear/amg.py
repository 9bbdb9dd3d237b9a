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
from warpfem.solvers.linear.base import HostLinearSolver, LinearSolveResult, numpy_global_seed, require
from warpfem.transfer import read, upload

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
            with numpy_global_seed():
                self.ml = self.pyamg.smoothed_aggregation_solver(Ab, B=B, symmetry="hermitian", **self.sa_options)
            self._M = self.ml.aspreconditioner(cycle="V")
            self.setup_count += 1
            self._since_build, self._base_iters, self._stale = 1, None, False
            self._built_mask = self._mask_host.copy()
            # what the hierarchy was built from (``state_dict``: a resumed run rebuilds the same one)
            self._built_values = read(values, self.pattern.nnz).copy()

    # -- the kept hierarchy (a simulator's state_dict) ----------------------------------------------------
    def state_dict(self) -> dict:
        """The kept hierarchy, as the matrix and mask it was built from, and the counts that decide
        its next rebuild: a run continued from a checkpoint preconditions exactly as the
        uninterrupted one."""
        from warpfem.io.checkpoint import optional_number

        built = self.ml is not None and getattr(self, "_built_values", None) is not None
        d = {"built": bool(built), "since_build": int(self._since_build), "base_iters": optional_number(self._base_iters),
             "stale": bool(self._stale), "setup_count": int(self.setup_count)}
        if built:
            d["built_values"], d["built_mask"] = self._built_values, self._built_mask.reshape(-1, 3)
        return d

    def load_state_dict(self, view):
        if "built" not in view:  # a checkpoint written before the hierarchy was kept: built afresh
            return
        built = view.flag("built")
        counts = dict(_since_build=view.integer("since_build"), _base_iters=view.number("base_iters", optional=True),
                      _stale=view.flag("stale"), setup_count=view.integer("setup_count"))
        if built:
            dt = np.dtype(np.float64 if self.scalar == wp.float64 else np.float32)
            v = view.array("built_values", (self.pattern.nnz, 3, 3), dt, finite=True)
            m = view.array("built_mask", (self.num_rows, 3), np.float64, finite=True)
            dev = self.device
            self.ml = None
            self._prepare(wp.array(v, dtype=self.pattern.block_type, device=dev),
                          wp.array(m.astype(dt), dtype=self.vec_type, device=dev))
        else:
            self.ml = None
        base = counts.pop("_base_iters")
        self._base_iters = None if base is None else int(base)
        for k, val in counts.items():
            setattr(self, k, val)

    def _solve(self, b, x, *, tol, maxiter) -> LinearSolveResult:
        import scipy.sparse.linalg as spla

        bh = read(b).astype(np.float64).reshape(-1) * self._mask_host
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
        upload(x, xh)
        if self._base_iters is None:
            self._base_iters = max(count[0], 1)
        elif count[0] > self.rebuild_factor * self._base_iters + 2:
            self._stale = True  # the next prepare rebuilds
        # converged: CG's own test (on its recursive residual) passed; ``residual`` is the true one
        return LinearSolveResult(count[0], rel, info == 0 and not failed, host_syncs=1, failed=failed)
