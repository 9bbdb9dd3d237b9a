"""Smoothed-aggregation multigrid as the preconditioner of the device PCG: the hierarchy is
built once, the coarse operators are re-formed on the device as Galerkin products.

Set-up (host, once per solver, at the first ``prepare``): pyamg's smoothed aggregation of the
first masked matrix with the six rigid-body modes as near-null space ("Algebraic multigrid by
smoothed aggregation for second and fourth order elliptic problems", Vanek, Mandel, Brezina) gives
the prolongators P_l (3x6 blocks on the finest level, 6x6 below). They are uploaded as
``warp.sparse`` BSR matrices with their transposes R_l = P_l^T and never change.

Per ``prepare`` (device, Warp's sparse routines): A_0 = P H P (the masked Hessian without the
identity of the fixed DOFs), then the identity of the fixed DOFs goes into A_0's diagonal and its
block l1-Jacobi diagonal is formed. The coarse operators A_{l+1} = R_l (A_l P_l) (two ``bsr_mm``
products each, masked to block structures computed once at set-up), their l1 diagonals and the
coarsest level's inverse (a few hundred unknowns, copied to the host and inverted by Cholesky: the
one host step) are re-formed at every prepare with ``coarse_update="every"``, and with the default
``"lagged"`` only when a solve needs clearly more iterations than the first one after the last
re-formation (the V-cycle stays SPD with older coarse operators).

Per CG iteration one V-cycle: on every level a Chebyshev polynomial smoother in the l1-Jacobi
preconditioned operator D^-1 A, D the block diagonal plus the absolute off-diagonal row sums
("Multigrid smoothers for ultraparallel computing", Baker, Falgout, Kolev, Yang: rho(D^-1 A) <= 1
for any SPD A, so the finest level's interval [lower, 1] needs no eigenvalue estimate and holds for
every Newton matrix; the coarse levels, whose operators change only when they are re-formed, use
[lower u, u] with u from a Lanczos estimate of rho(D^-1 A) at each re-formation: rho is 0.68-0.88
on the 6x6-block levels of the boxes and bunnies measured, so the smoothing gets stronger), restriction by
R_l, the coarsest level by its dense inverse, prolongation by P_l, the same smoother after. Chebyshev recurrence as in
Saad, "Iterative Methods for Sparse Linear Systems", Algorithm 12.1 (block l1 diagonals: 3x3 on
the finest level, 6x6 below, inverted in the kernel). The V-cycle is symmetric and, the l1
smoother being convergent, positive definite, so CG stays valid.

Fixed DOFs: the prolongators are not masked; instead the coarse operators are the Galerkin
products of the free-space matrix P H P and the preconditioned residual is z = P M r + (I - P) r.
The right-hand side is zero at fixed DOFs, so r, p, x stay exactly zero there (the masked operator
(P H P + I - P) decouples them); on the free DOFs the V-cycle is the exact Galerkin cycle of the
free system (rows of P_0 at fixed DOFs only meet the identity block, which does not couple back).

Mixed precision (``preconditioner_precision="float32"``, the default): in a float64 solve the
whole V-cycle (matrices, inverse blocks, vectors, transfers, coarsest inverse) runs in float32
between a conversion of r at its entry and of z at its exit; float32 rounding is far below the
preconditioner's own approximation error, and CG itself stays float64.

CG is the device-scalar loop of :mod:`warpfem.solvers.linear.pcg` (its start, matvec, carry and
direction kernels) with the block-Jacobi step replaced by the V-cycle; the host reads the 4-number
report every ``check_every`` iterations.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import warp as wp
import warp.sparse as wsp

from warpfem.kernels.generic import RecordedLaunch, both_precisions, launch, splittable
from warpfem.model import rigid_body_modes
from warpfem.solvers.linear.base import LinearSolver, LinearSolveResult, numpy_global_seed, require
from warpfem.solvers.linear.pcg import (_NEGATIVE, _NONFINITE, _RUNNING, _pcg_carry_kernel, _pcg_direction_kernel,
                                        _pcg_matvec_kernel, _pcg_start_kernel)
from warpfem.transfer import read, read_scalar, strict_device, to_device, upload

log = logging.getLogger(__name__)

wp.set_module_options({"enable_backward": False})


# -- set-up of each prepare ----------------------------------------------------------------------
@both_precisions(values="m[]", mask="v[]", out="m[]")
@wp.kernel
def _mask_values_kernel(values: wp.array(dtype=Any), mask: wp.array(dtype=Any), rows: wp.array(dtype=wp.int32),
                        cols: wp.array(dtype=wp.int32), out: wp.array(dtype=Any), start: int):
    """out[q] = P_r A_q P_c: the free-space block (no identity at fixed DOFs)."""
    q = wp.tid() + start
    out[q] = wp.diag(mask[rows[q]]) * values[q] * wp.diag(mask[cols[q]])


@both_precisions(mask="v[]", out="m[]")
@wp.kernel
def _add_fixed_identity_kernel(mask: wp.array(dtype=Any), diag_index: wp.array(dtype=wp.int32),
                               out: wp.array(dtype=Any), start: int):
    """out[diagonal block i] += I - P_i."""
    i = wp.tid() + start
    m = mask[i]
    one = type(m[0])(1.0)
    out[diag_index[i]] = out[diag_index[i]] + wp.diag(type(m)(one, one, one) - m)


@wp.kernel
def _block_l1_inverse_kernel(offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32),
                             values: wp.array(dtype=Any), bs: int, tiny: Any, dinv: wp.array(dtype=Any), start: int):
    """dinv[i] = (A_ii + diag(sum_{j != i} |A_ij| row sums))^-1, the block l1-Jacobi inverse, by
    Gauss-Jordan elimination (the block is SPD; no pivoting). A pivot below ``tiny`` times its
    diagonal entry (a coarse unknown no free DOF reaches, or a dependent coarse mode) gets a zero
    row and column in the inverse."""
    i = wp.tid() + start
    D = values[offsets[i]] - values[offsets[i]]
    L = D
    for q in range(offsets[i], offsets[i + 1]):
        B = values[q]
        if columns[q] == i:
            D = B
        else:
            for a in range(bs):
                for c in range(bs):
                    L[a, a] = L[a, a] + wp.abs(B[a, c])
    D = D + L
    Inv = D - D
    one = tiny - tiny + type(tiny)(1.0)
    for a in range(bs):
        Inv[a, a] = one
    null = Inv - Inv  # null[k, k] = 1 for a skipped pivot
    for k in range(bs):
        piv = D[k, k]
        if not (piv > tiny * wp.abs(D[k, k] + L[k, k])) or piv <= tiny - tiny:
            null[k, k] = one
        else:
            ip = one / piv
            for c in range(bs):
                D[k, c] = D[k, c] * ip
                Inv[k, c] = Inv[k, c] * ip
            for r in range(bs):
                if r != k:
                    f = D[r, k]
                    for c in range(bs):
                        D[r, c] = D[r, c] - f * D[k, c]
                        Inv[r, c] = Inv[r, c] - f * Inv[k, c]
    for k in range(bs):
        if null[k, k] != tiny - tiny:
            for c in range(bs):
                Inv[k, c] = tiny - tiny
                Inv[c, k] = tiny - tiny
    dinv[i] = Inv


# -- V-cycle ----------------------------------------------------------------------------------------
@wp.kernel
def _cheb_start_kernel(r: wp.array(dtype=Any), dinv: wp.array(dtype=Any), d: wp.array(dtype=Any), c0: Any):
    """d = c0 D^-1 r (the first Chebyshev correction)."""
    t = wp.tid()
    d[t] = c0 * (dinv[t] * r[t])


@wp.kernel
def _cheb_step_kernel(r: wp.array(dtype=Any), Ad: wp.array(dtype=Any), dinv: wp.array(dtype=Any),
                      d: wp.array(dtype=Any), x: wp.array(dtype=Any), c1: Any, c2: Any):
    """x += d; r -= A d; d = c1 d + c2 D^-1 r (one step of the Chebyshev recurrence)."""
    t = wp.tid()
    rt = r[t] - Ad[t]
    r[t] = rt
    dt = d[t]
    x[t] = x[t] + dt
    d[t] = c1 * dt + c2 * (dinv[t] * rt)


@both_precisions(src="s[]", a="s", dst="s[]")
@wp.kernel
def _scale_kernel(src: wp.array(dtype=Any), a: Any, dst: wp.array(dtype=Any)):
    t = wp.tid()
    dst[t] = a * src[t]


splittable("view", 32768)(_scale_kernel)


@both_precisions(d="s[]", x="s[]")
@wp.kernel
def _add_kernel(d: wp.array(dtype=Any), x: wp.array(dtype=Any)):
    t = wp.tid()
    x[t] = x[t] + d[t]


splittable("view", 32768)(_add_kernel)


@wp.kernel
def _bsr_block_mv_kernel(offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32),
                         values: wp.array(dtype=Any), x: wp.array(dtype=Any), alpha: Any, f: wp.array(dtype=Any),
                         beta: Any, y: wp.array(dtype=Any), start: int):
    """y = alpha A x + beta f, one thread per block row (f may be y); ``start``: the first row."""
    i = wp.tid() + start
    fi = f[i]
    acc = fi - fi
    for q in range(offsets[i], offsets[i + 1]):
        acc += values[q] * x[columns[q]]
    y[i] = alpha * acc + beta * fi


def _block_mv_overloads():
    """The block shapes of the hierarchy (3x3 finest; 3x6, 6x3 transfers and 6x6 below with the six
    rigid-body modes; 3x3 everywhere with translations only), in both precisions."""
    for s in (wp.float32, wp.float64):
        vec = {3: wp.types.vector(3, s), 6: wp.types.vector(6, s)}
        for bi, bj in ((3, 3), (3, 6), (6, 3), (6, 6)):
            wp.overload(_bsr_block_mv_kernel, {
                "offsets": wp.array(dtype=wp.int32), "columns": wp.array(dtype=wp.int32),
                "values": wp.array(dtype=wp.types.matrix(shape=(bi, bj), dtype=s)), "x": wp.array(dtype=vec[bj]),
                "alpha": s, "f": wp.array(dtype=vec[bi]), "beta": s, "y": wp.array(dtype=vec[bi]), "start": int})


_block_mv_overloads()
# split across CPU threads (``kernels.generic.splittable``): row-wise and element-wise, no reductions
splittable("start", 256)(_bsr_block_mv_kernel)


def _block_overloads():
    """Smoother kernels on 3x3 (finest, or translations only) and 6x6 blocks, both precisions."""
    for s in (wp.float32, wp.float64):
        for b in (3, 6):
            v, m = wp.array(dtype=wp.types.vector(b, s)), wp.array(dtype=wp.types.matrix(shape=(b, b), dtype=s))
            wp.overload(_block_l1_inverse_kernel, {"offsets": wp.array(dtype=wp.int32),
                                                   "columns": wp.array(dtype=wp.int32), "values": m, "bs": int,
                                                   "tiny": s, "dinv": m, "start": int})
            wp.overload(_cheb_start_kernel, {"r": v, "dinv": m, "d": v, "c0": s})
            wp.overload(_cheb_step_kernel, {"r": v, "Ad": v, "dinv": m, "d": v, "x": v, "c1": s, "c2": s})


_block_overloads()
# the set-up of each prepare, split too: row-wise (the l1 inverse: ~1.5 us per 3x3 row) and block-wise
splittable("start", 8192)(_mask_values_kernel)
splittable("start", 8192)(_add_fixed_identity_kernel)
splittable("start", 1024)(_block_l1_inverse_kernel)
splittable("view", 8192)(_cheb_start_kernel)
splittable("view", 8192)(_cheb_step_kernel)


@wp.kernel
def _convert_kernel(src: wp.array(dtype=Any), dst: wp.array(dtype=Any)):
    """dst = src in dst's precision (the mixed-precision V-cycle's entry and exit)."""
    t = wp.tid()
    d = dst[t]
    dst[t] = type(d)(src[t])


wp.overload(_convert_kernel, {"src": wp.array(dtype=wp.float64), "dst": wp.array(dtype=wp.float32)})
wp.overload(_convert_kernel, {"src": wp.array(dtype=wp.float32), "dst": wp.array(dtype=wp.float64)})
splittable("view", 32768)(_convert_kernel)


@both_precisions(M="s[,]", x="s[]", y="s[]")
@wp.kernel
def _dense_mv_kernel(M: wp.array2d(dtype=Any), x: wp.array(dtype=Any), y: wp.array(dtype=Any)):
    """y = M x (the coarsest level's pseudo-inverse)."""
    i = wp.tid()
    s = x[0] - x[0]
    for j in range(M.shape[1]):
        s += M[i, j] * x[j]
    y[i] = s


# -- CG around the V-cycle ----------------------------------------------------------------------
@both_precisions(b="s[]", x="s[]", r="s[]")
@wp.kernel
def _mg_init_kernel(b: wp.array(dtype=Any), x: wp.array(dtype=Any), r: wp.array(dtype=Any),
                    rr: wp.array(dtype=wp.float64), slot: int, start: int, row_block: int, row_stride: int):
    """x = 0, r = b, rr[slot] += b.b."""
    t = wp.tid() + start
    bt = b[t]
    x[t] = bt - bt
    r[t] = bt
    wp.atomic_add(rr, slot + (t // row_block) * row_stride, wp.float64(bt * bt))


@both_precisions(x="s[]", r="s[]", z="s[]", p="s[]", Ap="s[]")
@wp.kernel
def _mg_update_kernel(x: wp.array(dtype=Any), r: wp.array(dtype=Any), z: wp.array(dtype=Any), p: wp.array(dtype=Any),
                      Ap: wp.array(dtype=Any), status: wp.array(dtype=wp.int32), iters: wp.array(dtype=wp.int32),
                      rz: wp.array(dtype=wp.float64), rr: wp.array(dtype=wp.float64), pap: wp.array(dtype=wp.float64),
                      j: int, start: int, row_block: int, row_stride: int):
    """alpha = rz/pAp; x += alpha p; r -= alpha Ap; rr[j+1] accumulated (z comes from the V-cycle
    next). With non-positive curvature on the first iteration, x = z."""
    t = wp.tid() + start
    if status[j] != int(_RUNNING):
        return
    a = pap[j]
    if not (a > wp.float64(0.0)) or not wp.isfinite(a):
        if iters[j] == 0:
            x[t] = z[t]
        return
    xt = x[t]
    alpha = type(xt)(rz[j] / a)
    x[t] = xt + alpha * p[t]
    rt = r[t] - alpha * Ap[t]
    r[t] = rt
    wp.atomic_add(rr, j + 1 + (t // row_block) * row_stride, wp.float64(rt * rt))


@both_precisions(r="s[]", z="s[]", mask="s[]", p="s[]")
@wp.kernel
def _mg_precond_finish_kernel(r: wp.array(dtype=Any), z: wp.array(dtype=Any), mask: wp.array(dtype=Any),
                              p: wp.array(dtype=Any), status: wp.array(dtype=wp.int32),
                              pap: wp.array(dtype=wp.float64), rz: wp.array(dtype=wp.float64), j: int, init: int,
                              start: int, row_block: int, row_stride: int):
    """z = P z + (I - P) r; rz[slot] += r.z (slot j+1 after an update, j at the start, where also p = z)."""
    t = wp.tid() + start
    slot = j
    if init == 0:
        if status[j] != int(_RUNNING):
            return
        a = pap[j]
        if not (a > wp.float64(0.0)) or not wp.isfinite(a):
            return
        slot = j + 1
    m = mask[t]
    rt = r[t]
    zt = m * z[t] + rt - m * rt
    z[t] = zt
    if init != 0:
        p[t] = zt
    wp.atomic_add(rz, slot + (t // row_block) * row_stride, wp.float64(rt * zt))


# split across CPU threads by their recorded launches (``RecordedLaunch``): rows of partial sums
# (``written``: the one entry each adds into, for the fixed-order sums of other devices)
splittable("reduce", 8192, acc=3, slot=4, written=lambda a: a[4])(_mg_init_kernel)
splittable("reduce", 8192, acc=8, slot=10, written=lambda a: a[10] + 1)(_mg_update_kernel)
splittable("reduce", 8192, acc=6, slot=7, written=lambda a: a[7] + (0 if a[8] else 1))(_mg_precond_finish_kernel)


def _chebyshev_coefficients(degree: int, lower: float, upper: float = 1.0):
    """(c0, [(c1, c2)] * (degree - 1)) of the Chebyshev recurrence on [lower, upper] (Saad, Alg. 12.1)."""
    theta, delta = 0.5 * (upper + lower), 0.5 * (upper - lower)
    sigma = theta / delta
    rho = 1.0 / sigma
    steps = []
    for _ in range(degree - 1):
        rho_new = 1.0 / (2.0 * sigma - rho)
        steps.append((rho_new * rho, 2.0 * rho_new / delta))
        rho = rho_new
    return 1.0 / theta, steps


class _Level:
    """One level of the hierarchy on the device: its matrix A (BSR), work vectors (flat scalars),
    the l1-Jacobi inverse diagonal and, above the coarsest, the transfer operators."""

    def __init__(self, A, size, scalar, device):
        self.A = A
        self.size = size
        z = lambda: wp.zeros(size, dtype=scalar, device=device)  # noqa: E731
        self.f, self.x, self.r, self.d, self.t = z(), z(), z(), z(), z()
        b = A.block_shape[0]
        self.block = b
        self.dinv = wp.zeros(size // b, dtype=wp.types.matrix(shape=(b, b), dtype=scalar), device=device)
        self.P = self.R = None
        self.AP = None  # A P, in the structure computed at set-up
        self.Minv = None  # the coarsest level's dense inverse
        self.cheb = None  # (c0, [(c1, c2)]): the smoother's Chebyshev coefficients


class MultigridPCG(LinearSolver):
    """CG preconditioned by a smoothed-aggregation V-cycle that runs on the device.

    Args:
        positions: (n, 3) rest positions for the rigid-body near-null space (default translations only).
        max_coarse: at most about this many unknowns on the coarsest level (its dense inverse is
            formed on the host when the coarse operators are re-formed and applied on the device).
        max_levels: cap on the number of levels.
        degree: Chebyshev polynomial degree of each smoothing (matrix products per pre- or
            post-smoothing); a sequence gives one per level (the last repeats below).
        lower: the Chebyshev interval is [lower u, u] of the l1-Jacobi preconditioned spectrum
            (a sequence: one per level, as ``degree``).
        upper: u on the coarse levels: "estimate" (default): ``safety`` times the largest
            eigenvalue of D^-1 A estimated by Lanczos (host) whenever the coarse operators are
            re-formed, capped at 1; a number in (0, 1]: that bound. The finest level uses u = 1,
            the l1 bound that holds for every matrix, unless ``estimate_finest``.
        safety: factor on the estimated eigenvalue (>= 1; the Chebyshev polynomial still damps
            eigenvalues up to u + lower u).
        estimate_finest: estimate u on the finest level too, from the matrix of the prepare that
            re-forms the coarse operators. Later matrices (the lagged ones, contact blocks that
            couple vertices stiffly) may have eigenvalues above it, where the smoother amplifies:
            off by default (measured effect in docs/linear_solvers.md).
        check_every: CG iterations between host read-backs of the residual (default 1 on the CPU,
            where a read-back costs microseconds and an extra V-cycle does not; 4 on CUDA).
        coarse_update: "every": the coarse operators are re-formed (Galerkin products) at every
            prepare; "lagged": only the finest level follows each matrix, the coarse operators are
            re-formed when a solve needs more than ``lag_factor`` times the iterations (+2) of the
            first solve after the last re-formation (the V-cycle stays SPD with older coarse
            operators, so CG stays valid; measured effect in docs/linear_solvers.md).
        rebuild_factor: rebuild the hierarchy (from the matrix of the next prepare) when a solve
            needs more than this times the iterations of the first solve after the last build (+5).
        preconditioner_precision: "float32" (default; in a float32 solve the same as "same"): in a
            float64 solve every level's matrix, the l1-Jacobi inverses, the transfers, the smoother
            vectors and the coarsest inverse are float32, r is converted at the V-cycle's entry and
            z at its exit, and CG (products, residuals, dot products, the convergence test) stays
            float64: the same iterations, 0.8x the step time on the 98k-tet box (measured in
            docs/linear_solvers.md); "same": the V-cycle in the solver's precision.
        strength, aggregate, smooth, improve_candidates: passed to pyamg's
            ``smoothed_aggregation_solver`` for the set-up (``smooth``: one Jacobi step of the
            tentative prolongator, weighted by the inverse 3x3 / 6x6 block diagonal).
    """

    name = "multigrid"
    dense_estimate_below = 300  # levels with fewer unknowns get their rho(D^-1 A) by a dense eigensolve

    def __init__(self, pattern, *, vec_type, scalar, positions=None, max_coarse: int = 300, max_levels: int = 10,
                 degree: int = 3, lower: float = 0.03, check_every: int | None = None, rebuild_factor: float = 3.0,
                 coarse_update: str = "lagged", lag_factor: float = 1.5, strength="symmetric", aggregate="standard",
                 smooth=("jacobi", {"omega": 4.0 / 3.0, "weighting": "block"}), improve_candidates=None, upper="estimate",
                 safety: float = 1.1, estimate_finest: bool = False, preconditioner_precision: str = "float32"):
        self.pyamg = require("pyamg", "amg", "'multigrid' linear solver")
        degrees = tuple(degree) if isinstance(degree, (tuple, list)) else (degree,)
        if not degrees or any(int(g) != g or g < 1 for g in degrees):
            raise ValueError(f"degree must be a positive integer (or one per level), got {degree!r}")
        lowers = tuple(lower) if isinstance(lower, (tuple, list)) else (lower,)
        if not lowers or not all(0.0 < g < 1.0 for g in lowers):
            raise ValueError(f"lower must be in (0, 1) (or one per level), got {lower!r}")
        if int(max_coarse) != max_coarse or max_coarse < 6:
            raise ValueError(f"max_coarse must be an integer >= 6, got {max_coarse!r}")
        if int(max_levels) != max_levels or max_levels < 2:
            raise ValueError(f"max_levels must be an integer >= 2, got {max_levels!r}")
        if not (np.isfinite(rebuild_factor) and rebuild_factor >= 1.0):
            raise ValueError(f"rebuild_factor must be >= 1, got {rebuild_factor!r}")
        if check_every is None:
            check_every = 4 if (pattern.device.is_cuda or strict_device()) else 1
        if int(check_every) != check_every or check_every < 1:
            raise ValueError(f"check_every must be a positive integer, got {check_every!r}")
        self.degree, self.lower = tuple(int(g) for g in degrees), tuple(float(g) for g in lowers)
        if not (upper == "estimate" or (isinstance(upper, (int, float)) and 0.0 < upper <= 1.0)):
            raise ValueError(f"upper must be 'estimate' or in (0, 1], got {upper!r}")
        if not (np.isfinite(safety) and safety >= 1.0):
            raise ValueError(f"safety must be >= 1, got {safety!r}")
        self.upper, self.safety, self.estimate_finest = upper, float(safety), bool(estimate_finest)
        self.max_coarse, self.max_levels = int(max_coarse), int(max_levels)
        self.check_every = int(check_every)
        self.rebuild_factor = float(rebuild_factor)
        if coarse_update not in ("every", "lagged"):
            raise ValueError(f"coarse_update must be 'every' or 'lagged', got {coarse_update!r}")
        if not (np.isfinite(lag_factor) and lag_factor >= 1.0):
            raise ValueError(f"lag_factor must be >= 1, got {lag_factor!r}")
        self.coarse_update, self.lag_factor = coarse_update, float(lag_factor)
        if preconditioner_precision not in ("same", "float32"):
            raise ValueError(f"preconditioner_precision must be 'same' or 'float32', got {preconditioner_precision!r}")
        self.preconditioner_precision = preconditioner_precision
        self.sa_options = dict(strength=strength, aggregate=aggregate, smooth=smooth,
                               improve_candidates=improve_candidates)
        n = pattern.num_rows
        if positions is None:
            self._B0 = rigid_body_modes(np.zeros((n, 3)))[:, :3] * np.sqrt(n)
        else:
            X = np.asarray(positions, dtype=np.float64)
            if X.shape != (n, 3) or not np.all(np.isfinite(X)):
                raise ValueError(f"positions must be finite with shape ({n}, 3), got {X.shape}")
            self._B0 = rigid_body_modes(X)
        self.levels = None
        self.setup_count = 0
        self.galerkin_count = 0
        self._refresh_coarse, self._galerkin_iters = False, None
        self._base_iters = None
        self._stale = False
        super().__init__(pattern, vec_type=vec_type, scalar=scalar)

    # -- workspace ------------------------------------------------------------------------------------
    def _analyse(self, pattern):
        n, dev, k = pattern.num_rows, self.device, self.check_every
        vec = self.vec_type
        self.b, self.x, self.r, self.z, self.p, self.Ap = (wp.zeros(n, dtype=vec, device=dev) for _ in range(6))
        flat = lambda a: a.view(self.scalar).flatten()  # noqa: E731
        self._bf, self._xf, self._rf, self._zf, self._pf, self._Apf = map(flat, (self.b, self.x, self.r, self.z,
                                                                              self.p, self.Ap))
        self._rz = wp.zeros(k + 1, dtype=wp.float64, device=dev)
        self._rr = wp.zeros(k + 1, dtype=wp.float64, device=dev)
        self._pap = wp.zeros(k + 1, dtype=wp.float64, device=dev)
        self._status = wp.zeros(k + 1, dtype=wp.int32, device=dev)
        self._iters = wp.zeros(k + 1, dtype=wp.int32, device=dev)
        self._bb = wp.zeros(1, dtype=wp.float64, device=dev)
        self._tol2 = wp.zeros(1, dtype=wp.float64, device=dev)
        self._maxiter = wp.zeros(1, dtype=wp.int32, device=dev)
        self._report = wp.zeros(4, dtype=wp.float64, device=dev)
        self._rows = to_device(pattern.rows_np, wp.int32, dev)
        self._cols = to_device(pattern.cols_np, wp.int32, dev)
        self._diag = to_device(np.asarray(pattern.diag_index, dtype=np.int32), wp.int32, dev)
        # the V-cycle's scalar: float32 with preconditioner_precision "float32", else the solver's
        vs = wp.float32 if self.preconditioner_precision == "float32" else self.scalar
        self.vscalar, self._mixed = vs, vs != self.scalar
        # the pattern's topology; values set every prepare
        self._A0 = wsp.bsr_copy(pattern.matrix, scalar_type=vs, structure_only=True) if self._mixed else \
            wsp.bsr_copy(pattern.matrix)
        self._mask_v = wp.zeros(n, dtype=wp.types.vector(3, vs), device=dev) if self._mixed else None
        self._tiny = vs(1e-10 if vs == wp.float64 else 1e-5)
        self._cmds = None
        self.levels = None  # the hierarchy is built for this pattern (again when a form grew it)
        #: the matrices the kept hierarchy comes from (device copies, read only by ``state_dict``): the
        #: one it was built from and the one its coarse operators were last formed from ("same": that one)
        self._sources = {}

    # -- hierarchy ------------------------------------------------------------------------------------
    def _host_matrix(self, values, mask):
        import scipy.sparse

        m = read(mask).astype(np.float64).reshape(-1)
        A = self.pattern.to_scipy(values)
        self.host_syncs += 2
        Dm = scipy.sparse.diags(m)
        A = (Dm @ A @ Dm + scipy.sparse.diags(1.0 - m)).tocsr()
        return A, m

    def _build(self, values, mask):
        """pyamg's smoothed aggregation of this masked matrix; the prolongators go to the device."""
        import scipy.sparse

        A, m = self._host_matrix(values, mask)
        with numpy_global_seed():  # the same hierarchy, bit for bit, every run
            ml = self.pyamg.smoothed_aggregation_solver(
                scipy.sparse.bsr_matrix(A, blocksize=(3, 3)), B=self._B0 * m[:, None], symmetry="hermitian",
                max_coarse=max(1, self.max_coarse // self._B0.shape[1]),  # pyamg counts aggregates (blocks)
                max_levels=self.max_levels, keep=False, coarse_solver="pinv", **self.sa_options)
        dev, s = self.device, self.vscalar
        levels = [_Level(self._A0, 3 * self.num_rows, s, dev)]
        if not self._mixed:
            levels[0].f, levels[0].x = self._rf, self._zf  # the V-cycle reads CG's r and writes its z
        for lvl in ml.levels[:-1]:
            P = lvl.P
            bi = levels[-1].A.block_shape[0]
            bj = self._B0.shape[1]  # coarse unknowns per aggregate: the near-null space modes
            P = scipy.sparse.bsr_matrix(P, blocksize=(bi, bj))
            Pw = self._bsr_from_scipy(P, (bi, bj))
            Rw = self._bsr_from_scipy(scipy.sparse.bsr_matrix(P.T.tocsr(), blocksize=(bj, bi)), (bj, bi))
            cur = levels[-1]
            cur.P, cur.R = Pw, Rw
            # the products' topologies, structural, computed once here: the sparse products then
            # run masked to them (warp.sparse's own compact topology of R (A P) kept ~9x more
            # blocks than the structural product, all of them zero, on a 41k-tet box)
            S_A = self._structure(cur.A)
            S_P = self._structure(Pw)
            S_AP = (S_A @ S_P).tocsr()
            S_RAP = (S_P.T.tocsr() @ S_AP).tocsr()
            cur.AP = self._bsr_topology(S_AP, (bi, bj))
            nxt_A = self._bsr_topology(S_RAP, (bj, bj))
            levels.append(_Level(nxt_A, P.shape[1], s, dev))
        self.levels = levels
        self._cmds = None
        self.intervals = None  # the levels' Chebyshev upper bounds, set at each re-formation
        self.setup_count += 1
        self._base_iters, self._stale = None, False
        log.debug("multigrid: %d levels, unknowns %s", len(levels), [lv.size for lv in levels])

    def _set_intervals(self, mask):
        """Each level's Chebyshev coefficients on [lower u, u]. The finest level: u = 1, the l1
        bound that holds for any matrix of a Newton solve (with ``estimate_finest``, as below
        from the matrix of this prepare). Coarse levels, whose operators change only here: with
        ``upper="estimate"``, u = ``safety`` times the largest eigenvalue of D^-1 A (Lanczos on
        D^-1/2 A D^-1/2, host), capped at 1; a number: u = that number."""
        est = []
        for l, lv in enumerate(self.levels[:-1]):
            if l == 0 and not self.estimate_finest:
                u = 1.0
            elif self.upper == "estimate":
                u = min(1.0, self.safety * self._largest_eigenvalue(lv, read(mask).reshape(-1) if l == 0 else None))
            else:
                u = float(self.upper)
            est.append(u)
            lo = self.lower[min(l, len(self.lower) - 1)]
            lv.cheb = _chebyshev_coefficients(self.degree[min(l, len(self.degree) - 1)], lo * u, u)
        self.intervals = est
        self._cmds = None
        log.debug("multigrid: Chebyshev upper bounds %s", est)

    def _largest_eigenvalue(self, lv, free):
        """rho(D^-1 A) of a level (D^-1 its l1-Jacobi inverse blocks; ``free`` the finest level's
        mask: fixed DOFs left out) as the largest eigenvalue of D^-1/2 A D^-1/2: Lanczos (eigsh,
        tolerance 1e-2), dense below 300 unknowns. Returns 1 (the l1 bound) where no estimate
        comes out (no convergence, a zero or non-finite matrix)."""
        import scipy.sparse
        import scipy.sparse.linalg

        A = self._scipy(lv.A).tocsr()
        b = lv.block
        Di = read(lv.dinv).astype(np.float64).reshape(-1, b, b)
        Di = 0.5 * (Di + Di.transpose(0, 2, 1))
        w, V = np.linalg.eigh(Di)
        S = np.einsum("nij,nj,nkj->nik", V, np.sqrt(np.maximum(w, 0.0)), V)  # Dinv^(1/2) blocks
        if free is not None:
            S = S * free.reshape(-1, 1, b)  # zero columns at fixed DOFs (and rows, by symmetry below)
            S = S * free.reshape(-1, b, 1)
        nb = S.shape[0]
        H = scipy.sparse.bsr_matrix((S, np.arange(nb), np.arange(nb + 1)), shape=A.shape).tocsr()
        self.host_syncs += 2
        try:
            if A.shape[0] < self.dense_estimate_below:
                Sd = (H @ A @ H).toarray()
                lam = float(np.linalg.eigvalsh(0.5 * (Sd + Sd.T))[-1])
            else:
                op = scipy.sparse.linalg.LinearOperator(A.shape, matvec=lambda v: H @ (A @ (H @ v)), dtype=np.float64)
                v0 = np.random.default_rng(0).standard_normal(A.shape[0])
                lam = float(scipy.sparse.linalg.eigsh(op, k=1, which="LA", v0=v0, ncv=min(12, A.shape[0] - 1),
                                                      tol=1e-2, return_eigenvectors=False, maxiter=200)[0])
        except (scipy.sparse.linalg.ArpackNoConvergence, np.linalg.LinAlgError, ValueError):
            return 1.0
        return lam if np.isfinite(lam) and lam > 0.0 else 1.0

    @staticmethod
    def _scipy(A):
        import scipy.sparse

        bi, bj = A.block_shape
        nnz = A.nnz_sync()
        off = read(A.offsets, A.nrow + 1)
        cols = read(A.columns, nnz)
        vals = read(A.values, nnz).astype(np.float64).reshape(nnz, bi, bj)
        return scipy.sparse.bsr_matrix((vals, cols, off), shape=(A.nrow * bi, A.ncol * bj))

    @staticmethod
    def _structure(M):
        """The block structure of a device BSR matrix as a scipy CSR matrix of ones."""
        import scipy.sparse

        off = read(M.offsets, M.nrow + 1)
        cols = read(M.columns, int(off[-1]))
        return scipy.sparse.csr_matrix((np.ones(len(cols)), cols, off), shape=(M.nrow, M.ncol))

    def _bsr_topology(self, S, block):
        """A device BSR matrix with the block structure of the scipy matrix S and zero values."""
        S = S.tocsr()
        S.sort_indices()
        rows = np.repeat(np.arange(S.shape[0], dtype=np.int32), np.diff(S.indptr))
        dev, bt = self.device, self._block_type(*block)
        out = wsp.bsr_zeros(S.shape[0], S.shape[1], block_type=bt, device=dev)
        wsp.bsr_set_from_triplets(out, to_device(rows, wp.int32, dev),
                                  to_device(S.indices.astype(np.int32), wp.int32, dev),
                                  wp.zeros(len(rows), dtype=bt, device=dev), prune_numerical_zeros=False)
        return out

    def _block_type(self, bi, bj):
        s = self.vscalar
        return s if (bi, bj) == (1, 1) else wp.types.matrix(shape=(bi, bj), dtype=s)

    def _bsr_from_scipy(self, M, block):
        M.sort_indices()
        bi, bj = block
        nr, nc = M.shape[0] // bi, M.shape[1] // bj
        rows = np.repeat(np.arange(nr, dtype=np.int32), np.diff(M.indptr))
        np_t = np.float32 if self.vscalar == wp.float32 else np.float64
        dev = self.device
        data = M.data.astype(np_t).reshape(-1, bi, bj)
        out = wsp.bsr_zeros(nr, nc, block_type=self._block_type(bi, bj), device=dev)
        wsp.bsr_set_from_triplets(out, to_device(rows, wp.int32, dev),
                                  to_device(M.indices.astype(np.int32), wp.int32, dev),
                                  to_device(data, self._block_type(bi, bj), dev),
                                  prune_numerical_zeros=False)
        return out

    def _galerkin(self, values, mask, coarse: bool = True):
        """Every level's matrix from the Newton matrix (device), the smoothers' diagonals, and the
        coarsest pseudo-inverse (host); with ``coarse`` False only the finest level's (the coarse
        operators of an earlier matrix are kept)."""
        pt, dev = self.pattern, self.device
        A0 = self._A0
        if self._mixed:  # the Newton matrix and the mask in the V-cycle's precision, then masked in place
            key = (values.ptr, mask.ptr, A0.values.ptr, pt.nnz)
            if getattr(self, "_flat", (None,))[0] != key:  # the flat views, made once (split launches reuse them)
                flat = lambda a, s: a.view(s).flatten()  # noqa: E731
                self._flat = (key, flat(values[: pt.nnz], self.scalar), flat(A0.values[: pt.nnz], self.vscalar),
                              flat(mask, self.scalar), flat(self._mask_v, self.vscalar))
            _, v_src, v_dst, m_src, m_dst = self._flat
            launch(_convert_kernel, 9 * pt.nnz, [v_src, v_dst], dev)
            launch(_convert_kernel, 3 * pt.num_rows, [m_src, m_dst], dev)
            values, mask = A0.values, self._mask_v
        launch(_mask_values_kernel, pt.nnz, [values, mask, self._rows, self._cols, A0.values], dev)
        if coarse:
            for cur, nxt in zip(self.levels[:-1], self.levels[1:]):
                wsp.bsr_mm(cur.A, cur.P, cur.AP, topology="masked")
                wsp.bsr_mm(cur.R, cur.AP, nxt.A, topology="masked")
            self.galerkin_count += 1
        launch(_add_fixed_identity_kernel, pt.num_rows, [mask, self._diag, A0.values], dev)
        for lv in self.levels[:-1] if coarse else self.levels[:1]:
            A = lv.A
            launch(_block_l1_inverse_kernel, A.nrow, [A.offsets, A.columns, A.values, A.block_shape[0], self._tiny,
                                                      lv.dinv], dev)
        last = self.levels[-1]
        if not coarse and len(self.levels) > 1:
            return
        Ac = self._dense(last.A)
        self.host_syncs += 1
        Minv = self._pinv(Ac)
        if last.Minv is None or last.Minv.shape != Minv.shape:
            last.Minv = to_device(Minv, self.vscalar, dev)
            self._cmds = None
        else:
            upload(last.Minv, Minv)

    @classmethod
    def _dense(cls, A) -> np.ndarray:
        return cls._scipy(A).toarray()

    @staticmethod
    def _pinv(A) -> np.ndarray:
        """Inverse of the symmetric PSD coarsest matrix: by Cholesky (rows and columns that no
        free DOF reaches, exactly zero, are left out and get zero rows in the inverse); if that
        fails (dependent coarse modes), the pseudo-inverse from the eigen-decomposition,
        eigenvalues below 1e-12 of the largest dropped."""
        import scipy.linalg

        A = 0.5 * (A + A.T)
        d = np.diag(A)
        live = d > 0.0
        inv = np.zeros_like(A)
        if not live.any():
            return inv
        Al = A[np.ix_(live, live)]
        L, info = scipy.linalg.lapack.dpotrf(Al, lower=1)
        if info == 0:
            Li, info = scipy.linalg.lapack.dpotri(L, lower=1)
            if info == 0:
                Li = np.tril(Li) + np.tril(Li, -1).T
                inv[np.ix_(live, live)] = Li
                if np.all(np.isfinite(inv)):
                    return inv
        w, V = np.linalg.eigh(A)
        keep = w > 1e-12 * max(float(w.max()), 0.0)
        winv = np.where(keep, 1.0 / np.where(keep, w, 1.0), 0.0)
        return (V * winv) @ V.T

    # -- interface ------------------------------------------------------------------------------------
    def _prepare(self, values, mask):
        built = self.levels is None or self._stale
        if built:
            self._build(values, mask)
        coarse = built or self.coarse_update == "every" or self._refresh_coarse
        self._galerkin(values, mask, coarse=coarse)
        if coarse:
            self._set_intervals(mask)  # the coarse smoothers' intervals follow each re-formation
            self._keep_sources(values, mask, built)
        if coarse:
            self._refresh_coarse, self._galerkin_iters = False, None

    # -- the kept hierarchy (a simulator's state_dict) ----------------------------------------------------
    def _keep_sources(self, values, mask, built):
        """Device copies of the matrix (and mask) the hierarchy was built from and of the one its
        coarse operators were formed from: what :meth:`load_state_dict` rebuilds the same
        hierarchy from. A copy on the device at each build or re-formation (rare: the hierarchy is
        kept over many Newton systems), no read-back (:meth:`state_dict` reads them); with
        ``coarse_update="every"`` only at a build (every prepare forms its own coarse operators,
        the prolongators stay those of the build)."""
        if self.coarse_update == "every" and not built:
            return
        pair = (wp.clone(values), wp.clone(mask))
        if built:
            self._sources = {"built": pair, "coarse": "same"}
        else:
            self._sources["coarse"] = pair

    def state_dict(self) -> dict:
        """The kept hierarchy, as the matrices it comes from (``_keep_sources``), and the
        iteration counts that decide its next rebuild or re-formation: a run continued from a
        checkpoint then preconditions its Newton systems exactly as the uninterrupted run
        (with a new hierarchy the CG iterates, hence the Newton path, would differ in the last
        bits)."""
        from warpfem.io.checkpoint import optional_number

        src = self._sources if self.levels is not None else {}
        d = {"built": bool("built" in src), "base_iters": optional_number(self._base_iters),
             "galerkin_iters": optional_number(self._galerkin_iters), "stale": bool(self._stale),
             "refresh_coarse": bool(self._refresh_coarse), "setup_count": int(self.setup_count),
             "galerkin_count": int(self.galerkin_count)}
        nnz = self.pattern.nnz
        if "built" in src:
            d["built_values"], d["built_mask"] = (read(src["built"][0], nnz).copy(), read(src["built"][1]).copy())
            same = isinstance(src["coarse"], str)
            d["coarse_same"] = bool(same)
            if not same:
                d["coarse_values"], d["coarse_mask"] = (read(src["coarse"][0], nnz).copy(), read(src["coarse"][1]).copy())
        return d

    def load_state_dict(self, view):
        if "built" not in view:  # a checkpoint written before the multigrid kept its hierarchy: built afresh
            return
        built = view.flag("built")
        counts = dict(_base_iters=view.number("base_iters", optional=True),
                      _galerkin_iters=view.number("galerkin_iters", optional=True), _stale=view.flag("stale"),
                      _refresh_coarse=view.flag("refresh_coarse"), setup_count=view.integer("setup_count"),
                      galerkin_count=view.integer("galerkin_count"))
        pairs = []
        if built:
            nnz, n = self.pattern.nnz, self.num_rows
            dt = np.dtype(np.float64 if self.scalar == wp.float64 else np.float32)
            keys = [("built_values", "built_mask")] + ([] if view.flag("coarse_same") else [("coarse_values", "coarse_mask")])
            for kv, km in keys:
                pairs.append((view.array(kv, (nnz, 3, 3), dt, finite=True), view.array(km, (n, 3), dt, finite=True)))
        # checked: now the hierarchy, rebuilt from the same matrices by the same code (bit for bit)
        self.levels, self._sources = None, {}
        if built:
            dev = self.device
            arrays = [(wp.array(v, dtype=self.pattern.block_type, device=dev), wp.array(m, dtype=self.vec_type, device=dev))
                      for v, m in pairs]
            self._build(*arrays[0])
            vc, mc = arrays[-1]
            self._galerkin(vc, mc, coarse=True)
            self._set_intervals(mc)
            self.__dict__.pop("_flat", None)  # (views of the arrays above)
            self._sources = {"built": arrays[0], "coarse": "same" if len(arrays) == 1 else arrays[1]}
        for k, v in counts.items():
            setattr(self, k, (None if v is None else int(v)) if k.endswith("_iters") else v)

    def _commands(self):
        """The launches of a V-cycle and of a chunk of CG iterations, recorded once per (values,
        mask) arrays (the sparse products of the V-cycle are calls into warp.sparse)."""
        key = (self._values.ptr, self._mask.ptr,
               *((lv.A.offsets.ptr, lv.A.columns.ptr, lv.A.values.ptr) for lv in self.levels))
        if self._cmds is not None and self._cmds[0] == key:
            return self._cmds[1]
        dev, n, k = self.device, self.num_rows, self.check_every
        pt = self.pattern
        R = lambda kern, dim, inputs: RecordedLaunch(kern, dim, inputs, dev)  # noqa: E731
        mask_f = self._mask.view(self.scalar).flatten()
        cmds = dict(
            init=R(_mg_init_kernel, 3 * n, [self._bf, self._xf, self._rf, self._rr, k]),
            start=R(_pcg_start_kernel, 1, [self._rr, self._status, self._iters, self._bb, self._report, k]),
            init_finish=R(_mg_precond_finish_kernel, 3 * n, [self._rf, self._zf, mask_f, self._pf, self._status,
                                                             self._pap, self._rz, k, 1]),
            carry=R(_pcg_carry_kernel, 1, [self._rz, self._rr, self._pap, self._status, self._iters, k]),
            iters=[])
        for j in range(k):
            cmds["iters"].append((
                R(_pcg_matvec_kernel, n, [pt.offsets, pt.columns, self._values, self._mask, self.p, self.Ap,
                                          self._status, self._pap, j]),
                R(_mg_update_kernel, 3 * n, [self._xf, self._rf, self._zf, self._pf, self._Apf, self._status,
                                             self._iters, self._rz, self._rr, self._pap, j]),
                R(_mg_precond_finish_kernel, 3 * n, [self._rf, self._zf, mask_f, self._pf, self._status, self._pap,
                                                     self._rz, j, 0]),
                R(_pcg_direction_kernel, n, [self.z, self.p, self._status, self._iters, self._rz, self._rr, self._pap,
                                             self._bb, self._tol2, self._maxiter, self._report, j])))
        if self._mixed:
            lv0 = self.levels[0]
            cmds["to_vcycle"] = R(_convert_kernel, 3 * n, [self._rf, lv0.f])
            cmds["from_vcycle"] = R(_convert_kernel, 3 * n, [lv0.x, self._zf])
        s = self.vscalar
        for l, lv in enumerate(self.levels):
            if lv.Minv is not None:
                lv.cmd_coarse = R(_dense_mv_kernel, lv.size, [lv.Minv, lv.f, lv.x])
                continue
            c0, steps = lv.cheb
            nb, bv = lv.size // lv.block, self._blocks
            r, t, d, x = bv(lv.r, lv.block), bv(lv.t, lv.block), bv(lv.d, lv.block), bv(lv.x, lv.block)
            lv.cmd_start_pre = R(_cheb_start_kernel, nb, [r, lv.dinv, d, s(c0)])
            lv.cmd_steps = [R(_cheb_step_kernel, nb, [r, t, lv.dinv, d, x, s(c1), s(c2)]) for c1, c2 in steps]
            lv.cmd_last = R(_cheb_step_kernel, nb, [r, t, lv.dinv, d, x, s(0.0), s(0.0)])
            lv.cmd_add = R(_add_kernel, lv.size, [lv.d, lv.x])
            lv.cmd_zero_x = R(_scale_kernel, lv.size, [lv.f, s(0.0), lv.x])
            lv.cmd_copy_r = R(_scale_kernel, lv.size, [lv.f, s(1.0), lv.r])
            lv.cmd_residual = self._mv(lv.A, lv.x, -1.0, lv.f, 1.0, lv.r)
            lv.cmd_Ad = self._mv(lv.A, lv.d, 1.0, lv.t, 0.0, lv.t)
            nxt = self.levels[l + 1]
            lv.cmd_restrict = self._mv(lv.R, lv.r, 1.0, nxt.f, 0.0, nxt.f)
            lv.cmd_prolong = self._mv(lv.P, nxt.x, 1.0, lv.x, 1.0, lv.x)
        self._cmds = (key, cmds)
        return cmds

    def _blocks(self, v, b):
        """The flat vector v viewed as an array of b-vectors (no copy)."""
        return v.reshape((v.shape[0] // b, b)).view(wp.types.vector(b, self.vscalar))

    def _mv(self, A, x, alpha, f, beta, y):
        """A recorded y = alpha A x + beta f (flat vectors, viewed as the blocks' vectors)."""
        s = self.vscalar
        br, bc = A.block_shape
        blocks = self._blocks
        return RecordedLaunch(_bsr_block_mv_kernel, A.nrow, [A.offsets, A.columns, A.values, blocks(x, bc), s(alpha),
                                                              blocks(f, br), s(beta), blocks(y, br)], self.device)

    def _smooth(self, lv, from_zero: bool):
        """x += p(D^-1 A) D^-1 (f - A x): ``degree`` products with A; with ``from_zero`` x = 0 on
        entry and the residual f - A x is left in r."""
        if from_zero:
            lv.cmd_zero_x()
            lv.cmd_copy_r()
        else:
            lv.cmd_residual()
        lv.cmd_start_pre()
        for step in lv.cmd_steps:
            lv.cmd_Ad()
            step()
        if from_zero:  # last step: x += d, r -= A d (the residual the restriction needs)
            lv.cmd_Ad()
            lv.cmd_last()
        else:
            lv.cmd_add()

    def _vcycle(self):
        """z = M r on the finest level's vectors (levels[0].f = r, result in levels[0].x)."""
        levels = self.levels
        for lv in levels[:-1]:
            self._smooth(lv, True)
            lv.cmd_restrict()
        levels[-1].cmd_coarse()
        for lv in reversed(levels[:-1]):
            lv.cmd_prolong()
            self._smooth(lv, False)

    def _precondition(self):
        if self._mixed:
            cmds = self._cmds[1]
            cmds["to_vcycle"]()
            self._vcycle()
            cmds["from_vcycle"]()
        else:
            self._vcycle()

    def _solve(self, b, x, *, tol, maxiter) -> LinearSolveResult:
        if maxiter < 1:
            raise ValueError(f"maxiter must be >= 1, got {maxiter}")
        cmds = self._commands()
        wp.copy(self.b, b)
        self._tol2.fill_(float(tol) ** 2)
        self._maxiter.fill_(int(maxiter))
        self._rz.zero_()
        self._rr.zero_()
        cmds["init"]()
        cmds["start"]()
        self._precondition()
        cmds["init_finish"]()
        syncs = 0
        if self.check_every == 1:
            stop = np.float64(float(tol) ** 2) * np.float64(read_scalar(self._bb))
            syncs += 1
        while True:
            cmds["carry"]()
            for matvec, update, finish, direction in cmds["iters"]:
                matvec()
                update()
                if self.check_every == 1:
                    # one read-back before the V-cycle: the last iteration's is skipped (the
                    # direction kernel sees the same residual and stops without z)
                    syncs += 1
                    if read_scalar(self._rr, 1) <= stop:  # the direction kernel's own test, same float64 numbers
                        direction()
                        continue
                self._precondition()
                finish()
                direction()
            rep = read(self._report)
            syncs += 1
            if int(rep[0]) != _RUNNING:
                break
        wp.copy(x, self.x)
        status, it, rr, bb = int(rep[0]), int(rep[1]), float(rep[2]), float(rep[3])
        if self._base_iters is None:
            self._base_iters = max(it, 1)
        elif it > self.rebuild_factor * self._base_iters + 5:
            self._stale = True
        if self._galerkin_iters is None:
            self._galerkin_iters = max(it, 1)
        elif it > self.lag_factor * self._galerkin_iters + 2:
            self._refresh_coarse = True  # the next prepare re-forms the coarse operators
        if bb == 0.0:
            return LinearSolveResult(0, 0.0, True, host_syncs=syncs)
        rel = float(np.sqrt(max(rr, 0.0) / bb)) if np.isfinite(rr) and np.isfinite(bb) else float("nan")
        return LinearSolveResult(it, rel, bool(rel <= tol), host_syncs=syncs, negative_curvature=status == _NEGATIVE,
                                 failed="" if status != _NONFINITE else "non-finite residual")
