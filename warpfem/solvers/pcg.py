"""Preconditioned conjugate gradients on the device, block-Jacobi preconditioned.

Solves (P A P + I - P) x = P b, P the fixed-DOF mask (see ``warpfem.kernels.linalg``), with a
block-Jacobi preconditioner that inverts each masked 3x3 diagonal block. Scalars are reduced in
float64 whatever the working precision.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import warp as wp

from warpfem.kernels import linalg as K
from warpfem.kernels.generic import launch
from warpfem.transfer import read_scalar


@dataclass
class PCGResult:
    iterations: int
    residual: float  # final ||r|| / ||b|| (preconditioner-free 2-norm)
    converged: bool
    negative_curvature: bool = False


class BlockJacobiPCG:
    """Workspace and solver for masked block-sparse systems of one pattern.

    Args:
        pattern: the :class:`~warpfem.solvers.sparse.BlockPattern` of the matrices.
        vec_type, scalar: the working precision's vec3 type and scalar type.
    """

    def __init__(self, pattern, *, vec_type, scalar):
        self.pattern = pattern
        self.scalar = scalar
        n, dev = pattern.num_rows, pattern.device
        self.device = dev
        self.r = wp.zeros(n, dtype=vec_type, device=dev)
        self.z = wp.zeros(n, dtype=vec_type, device=dev)
        self.p = wp.zeros(n, dtype=vec_type, device=dev)
        self.Ap = wp.zeros(n, dtype=vec_type, device=dev)
        self.inv_diag = wp.zeros(n, dtype=pattern.block_type, device=dev)
        self._dot = wp.zeros(1, dtype=wp.float64, device=dev)

    def dot(self, a, b) -> float:
        self._dot.zero_()
        K.launch_dot(a, b, self._dot, self.device)
        return read_scalar(self._dot)

    def matvec(self, values, mask, x, y):
        pt = self.pattern
        launch(K.bsr_masked_mv_kernel, dim=pt.num_rows,
                  inputs=[pt.offsets, pt.columns, values, mask, x, y, 1], device=self.device)

    def solve(self, values, mask, b, x, *, tol: float, maxiter: int) -> PCGResult:
        """Solve for x (initial guess 0; ``x`` is overwritten). ``b`` must already be masked."""
        n, dev, s = self.pattern.num_rows, self.device, self.scalar
        pt = self.pattern
        launch(K.block_jacobi_setup_kernel, dim=n, inputs=[pt.offsets, pt.columns, values, mask, self.inv_diag], device=dev)
        x.zero_()
        wp.copy(self.r, b)
        bnorm = np.sqrt(self.dot(b, b))
        if bnorm == 0.0 or not np.isfinite(bnorm):
            return PCGResult(0, 0.0 if bnorm == 0.0 else float("nan"), bnorm == 0.0)
        launch(K.block_apply_kernel, dim=n, inputs=[self.inv_diag, self.r, self.z], device=dev)
        wp.copy(self.p, self.z)
        rz = self.dot(self.r, self.z)
        rnorm = bnorm
        it = 0
        negative = False
        while it < maxiter:
            self.matvec(values, mask, self.p, self.Ap)
            pAp = self.dot(self.p, self.Ap)
            if not pAp > 0.0:
                negative = True
                if it == 0:  # fall back to the preconditioned residual direction
                    wp.copy(x, self.z)
                break
            alpha = rz / pAp
            launch(K.axpy_kernel, dim=n, inputs=[s(alpha), self.p, x], device=dev)
            launch(K.axpy_kernel, dim=n, inputs=[s(-alpha), self.Ap, self.r], device=dev)
            it += 1
            rnorm = np.sqrt(self.dot(self.r, self.r))
            if rnorm <= tol * bnorm:
                break
            launch(K.block_apply_kernel, dim=n, inputs=[self.inv_diag, self.r, self.z], device=dev)
            rz_new = self.dot(self.r, self.z)
            beta = rz_new / rz
            rz = rz_new
            launch(K.xpby_kernel, dim=n, inputs=[self.z, s(beta), self.p], device=dev)
        rel = rnorm / bnorm
        return PCGResult(it, float(rel), bool(rel <= tol), negative)
