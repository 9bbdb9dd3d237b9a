"""Sparse direct solves of the Newton systems: Cholesky / LDL^T with the symbolic analysis reused.

The matrix of every Newton iteration has the same pattern (the mesh's block pattern; fixed DOFs
become identity rows and columns *inside* that pattern, explicit zeros kept), so the fill-reducing
ordering and the symbolic factorisation are computed once in ``analyse`` (on the first matrix when
the backend needs values) and only the numeric factorisation runs in ``prepare``.

Backends (``backend=``), measured in docs/linear_solvers.md:

* ``"pardiso"``: Intel MKL PARDISO (supernodal, multithreaded) through ``pypardiso``; phase 11
  (ordering + symbolic) once, phase 22 (numeric Cholesky, matrix type 2) per prepare, phase 33
  per solve. Extra ``[direct]`` (x86-64 only: MKL has no ARM build).
* ``"qdldl"``: QDLDL (up-looking LDL^T, AMD ordering) through ``qdldl``; ``update()`` reuses the
  ordering and the elimination tree. Light and single-threaded, but its non-supernodal
  factorisation was the slowest of the three on the bunny; installed by the ``test`` extra only.
* ``"superlu"``: scipy's SuperLU (``splu``, symmetric mode, no pivoting); always available but
  redoes the ordering and symbolic analysis every prepare.
* ``"auto"``: pardiso when installed, else superlu.

The matrices are assumed symmetric positive definite (Hessians are SPD-projected by default),
but a projected Hessian can be only semi-definite: the projection clamps negative eigenvalues of
each element's dP/dF to exactly zero, and without a mass term (a static solve) a deformation mode
that every element clamps (a homogeneous state) is a global zero eigenvalue. Whether the
factorisation then meets a pivot of +1e-10 or -1e-10 depends on round-off, i.e. on the CPU's code
path (MKL picks its kernels by processor). So a factorisation that finds a non-positive pivot is
retried with a diagonal shift A + delta I on the free DOFs, delta = SHIFTS[k] x the largest free
diagonal entry, the smallest that factorises, and the solve refines against the *unshifted* A
(x <- x + (A + delta I)^-1 (b - A x)) until the residual meets the tolerance or stops decreasing:
a consistent semi-definite system is solved to the requested tolerance, and otherwise the first
shifted solve is a descent direction (Levenberg-Marquardt). ``LinearSolveResult.shift`` reports
delta (0 when A factorised as it is). Only a matrix that no shift up to SHIFTS[-1] makes positive
definite (an unprojected Hessian far from convex) is reported ``failed`` with the reason and
``x`` = the block-Jacobi direction, so the Newton loop can fall back; nothing raises.

The data path is device -> host (blocks) -> factor -> host solve -> device, fine on the CPU; on
CUDA it costs two copies of the blocks per Newton iteration (a GPU direct solver, e.g. cuDSS,
would avoid that; not implemented).
"""

from __future__ import annotations

import logging
import os

import numpy as np
import warp as wp

from warpfem.kernels import linalg as K
from warpfem.solvers.linear.base import HostLinearSolver, LinearSolveResult, MissingExtra, require
from warpfem.transfer import read, upload

log = logging.getLogger(__name__)

BACKENDS = ("auto", "pardiso", "qdldl", "superlu")
#: diagonal shifts tried, in turn, after a non-positive pivot, relative to the largest free diagonal entry
SHIFTS = (1e-10, 1e-8, 1e-6, 1e-4, 1e-2)
#: refinement iterations against the unshifted matrix after a shifted factorisation
SHIFTED_REFINEMENTS = 20
#: eigenvalues at most this x the largest free diagonal entry count as zero (a condition number of 1e10,
#: beyond what a float64 factorisation resolves)
NULL_TOLERANCE = 1e-10
#: vectors of the block inverse iteration that finds the near-null space: the six rigid motions of a
#: free body and three more, whose smallest Ritz value estimates the smallest positive curvature
NULL_PROBES = 9
#: the most factorisations ``keep_factor`` keeps at once with PARDISO (its factor slots: ~4 bytes per
#: equation each, allocated with the analysis)
MAX_KEPT_FACTORS = 2048


class _NotPositiveDefinite(RuntimeError):
    pass


_MKL_RT = None  # the path of the MKL library pypardiso loaded first


def _environment_mkl_rt():
    """MKL's runtime library directly in the environment's ``lib*`` folder (where the ``mkl`` wheel
    that pypardiso depends on puts it), shortest path first, or None. Without it pypardiso asks
    ``find_library`` and then globs the whole environment recursively (~0.5 s at start-up)."""
    import glob
    import site
    import sys

    for base in (sys.prefix, site.USER_BASE):
        hits = glob.glob(f"{base}/[Ll]ib*/*mkl_rt*") + glob.glob(f"{base}/Library/bin/*mkl_rt*")
        if hits:
            return sorted(hits, key=len)[0]
    return None


class _Pardiso:
    triangle = "upper"

    def __init__(self):
        global _MKL_RT
        # pypardiso looks for MKL's library on every solver it makes, one at its import (a recursive
        # glob of the environment when find_library fails: ~0.5 s, at every pattern growth); say where
        if not os.environ.get("PYPARDISO_MKL_RT"):
            _MKL_RT = _MKL_RT or _environment_mkl_rt()
            if _MKL_RT:
                os.environ["PYPARDISO_MKL_RT"] = _MKL_RT
        pypardiso = require("pypardiso", "direct", "direct linear solver's 'pardiso' backend")
        self.mod = pypardiso
        self.ps = pypardiso.PyPardisoSolver(mtype=2)  # real symmetric positive definite
        _MKL_RT = _MKL_RT or getattr(getattr(self.ps, "libmkl", None), "_name", None)
        self.ps.set_iparm(1, 1)  # non-default iparms follow
        self.ps.set_iparm(2, 2)  # nested dissection ordering (METIS)
        self.ps.set_iparm(10, 8)  # pivot perturbation 1e-8 (only used by indefinite types)
        self.ps.set_iparm(18, -1)  # report the number of nonzeros of the factor (after the analysis)
        self.ps.set_iparm(21, 0)
        self.analysed = False
        self.symbolic_count = 0
        # factors kept in memory at once (PARDISO's maxfct: every factor shares the one symbolic
        # analysis), the slot the next factorisation writes (mnum) and the free slots
        self.maxfct = 1
        self.mnum = 1
        self.free_slots = []
        self.kept = 0  # factors handed out (``detach``) and not released
        self.current = False  # whether the current slot holds a factorisation
        self._ij = None  # (indptr, indices, their 1-based int32 copies) of the last matrix
        self._zero_data = None

    def call(self, phase, A, b, mnum=None):
        """PARDISO through pypardiso's MKL handle, with our maxfct and slot (pypardiso passes 1, 1)."""
        import ctypes

        ps = self.ps
        x = np.zeros_like(b)
        err = ctypes.c_int32(0)
        i32, f64 = ctypes.POINTER(ctypes.c_int32), ctypes.POINTER(ctypes.c_double)
        ij = self._ij
        if ij is None or ij[0] is not A.indptr or ij[1] is not A.indices:  # 1-based index arrays, once per pattern
            ij = self._ij = (A.indptr, A.indices, A.indptr.astype(np.int32) + 1, A.indices.astype(np.int32) + 1)
        ia, ja = ij[2], ij[3]
        c = ctypes.c_int32
        handle = ps.pt.ctypes.data_as(ctypes.POINTER(np.ctypeslib.as_ctypes_type(ps.pt.dtype)))
        ps._mkl_pardiso(handle, ctypes.byref(c(self.maxfct)),
                        ctypes.byref(c(self.mnum if mnum is None else mnum)), ctypes.byref(c(ps.mtype)),
                        ctypes.byref(c(phase)), ctypes.byref(c(A.shape[0])), A.data.ctypes.data_as(f64),
                        ia.ctypes.data_as(i32), ja.ctypes.data_as(i32), ps.perm.ctypes.data_as(i32),
                        ctypes.byref(c(1 if b.ndim == 1 else b.shape[1])), ps.iparm.ctypes.data_as(i32),
                        ctypes.byref(c(0)), b.ctypes.data_as(f64), x.ctypes.data_as(f64), ctypes.byref(err))
        if err.value != 0:
            if phase == 22 and err.value == -4:
                raise _NotPositiveDefinite("PARDISO found a non-positive pivot (matrix not positive definite)")
            raise self.mod.pardiso_wrapper.PyPardisoError(err.value)
        return x

    def factor(self, A):
        z = np.zeros((A.shape[0], 1))
        if not self.analysed:
            self.call(11, A, z)
            self.analysed = True
            self.symbolic_count += 1
        self.current = False
        self.call(22, A, z)
        self.A = A
        self.current = True

    def solve(self, b):
        return self.call(33, self.A, np.asfortranarray(b.reshape(-1, 1))).ravel()

    def factor_nbytes(self) -> int:
        """Bytes of one numeric factor (its nonzeros in float64; the analysis is shared)."""
        return 8 * int(max(self.ps.iparm[17], 0))

    def detach(self, capacity):
        """The current factor as a kept one (its slot stays allocated until released); the next
        factorisation goes to a free slot. With no free slot and none handed out, the analysis is
        redone for ``capacity`` more slots and the current matrix factorised again (once per
        recording that starts on a solver without the room, :meth:`reserve`)."""
        if not self.free_slots and self.maxfct < capacity + 1 and not self.kept:
            A = self.A
            self.reserve(capacity)
            self.factor(A)
        if not self.free_slots:
            return None  # full, and growing would drop the factors handed out
        # the solve phase reads the factor, not the matrix's values (no iterative refinement,
        # iparm[7] = 0): the kept handle holds the shared structure and one zero array, not A
        z = self._zero_data
        if z is None or len(z) != len(self.A.data):
            z = self._zero_data = np.zeros(len(self.A.data))
        structure = _Structure(z, self.A.indptr, self.A.indices, self.A.shape)
        kept = _KeptFactor(self, structure, self.mnum, self.factor_nbytes())
        self.mnum = self.free_slots.pop()
        self.kept += 1
        self.current = False
        return kept

    def reserve(self, capacity):
        """Room for ``capacity`` kept factors besides the current one (PARDISO's maxfct is set by the
        analysis: with none handed out, everything is released and analysed again on the next
        factorisation)."""
        if self.analysed and not self.kept and self.maxfct < capacity + 1:
            self.call(-1, self.A, np.zeros(0))
            self.maxfct = int(capacity) + 1
            self.free_slots = list(range(self.maxfct, 1, -1))
            self.mnum = 1
            self.analysed = False
            self.current = False

    def release_slot(self, mnum):
        try:
            self.call(0, self.A, np.zeros(0), mnum=mnum)
        except Exception:  # noqa: BLE001 - nothing to free (already released with everything)
            pass
        self.free_slots.append(mnum)
        self.kept -= 1

    def __del__(self):  # release MKL's factorisation memory with the solver
        try:
            if self.analysed:
                self.call(-1, self.A, np.zeros(0))
        except Exception:  # noqa: BLE001 - interpreter shutdown or a failed init; nothing to free
            pass


class _Structure:
    """A CSR matrix's arrays as PARDISO's solve phase takes them (values unused there)."""

    def __init__(self, data, indptr, indices, shape):
        self.data, self.indptr, self.indices, self.shape = data, indptr, indices, shape


class _KeptFactor:
    """A factorisation handed over by the direct solver (``DirectSolver.keep_factor``): ``solve(b)``
    on the host (float64, the solver's DOF order), ``nbytes``, ``release()`` (also on deletion)."""

    def __init__(self, backend, A, handle, nbytes):
        self.backend, self.A, self.handle, self.nbytes = backend, A, handle, int(nbytes)
        self.released = False

    def solve(self, b):
        if self.released:
            raise RuntimeError("this kept factorisation was released")
        be = self.backend
        if isinstance(be, _Pardiso):
            return be.call(33, self.A, np.asfortranarray(np.asarray(b, dtype=np.float64).reshape(-1, 1)),
                            mnum=self.handle).ravel()
        return self.handle.solve(np.asarray(b, dtype=np.float64))

    def release(self):
        if self.released:
            return
        self.released = True
        if isinstance(self.backend, _Pardiso):
            self.backend.release_slot(self.handle)
        self.handle = None
        self.A = None

    def __del__(self):
        try:
            self.release()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass


class _QDLDL:
    triangle = "lower"  # lower CSR arrays == upper CSC arrays (symmetric)

    def __init__(self, check_definite=True):
        self.mod = require("qdldl", "direct", "direct linear solver's 'qdldl' backend")
        self.solver = None
        self.symbolic_count = 0
        self.check_definite = check_definite
        self.current = False

    def factor(self, A):
        import scipy.sparse

        U = scipy.sparse.csc_matrix((A.data, A.indices, A.indptr), shape=A.shape)
        self.current = False
        if self.solver is None:
            self.solver = self.mod.Solver(U, upper=True)
            self.symbolic_count += 1
        else:
            self.solver.update(U, upper=True)
        if self.check_definite:
            _, D, _ = self.solver.factors()
            if not np.all(D > 0.0):
                raise _NotPositiveDefinite(f"QDLDL found {int(np.sum(~(D > 0.0)))} non-positive pivot(s) "
                                           "(matrix not positive definite)")
        self.current = True

    def solve(self, b):
        return self.solver.solve(b)

    def factor_nbytes(self) -> int:
        if getattr(self, "_nnz", None) is None:
            L, _, _ = self.solver.factors()
            self._nnz = int(L.nnz) + L.shape[0]
        return 12 * self._nnz

    def detach(self, capacity):
        """The current factor as a kept one; the next factorisation builds a new QDLDL solver
        (its ordering and elimination tree again: QDLDL updates in place)."""
        kept = _KeptFactor(self, None, self.solver, self.factor_nbytes())
        self.solver = None
        self.current = False
        return kept


class _SuperLU:
    triangle = "full"

    def __init__(self):
        self.symbolic_count = 0  # SuperLU redoes the ordering every factorisation (no reuse)
        self.lu = None
        self.current = False

    def factor(self, A):
        import scipy.sparse
        import scipy.sparse.linalg as spla

        C = scipy.sparse.csc_matrix((A.data, A.indices, A.indptr), shape=A.shape)  # symmetric: CSR == CSC
        self.current = False
        try:
            self.lu = spla.splu(C, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0,
                                options={"SymmetricMode": True})
        except RuntimeError as e:  # exactly singular
            raise _NotPositiveDefinite(f"SuperLU: {e}") from e
        self.symbolic_count += 1
        d = self.lu.U.diagonal()
        if not np.all(d > 0.0):
            raise _NotPositiveDefinite(f"SuperLU found {int(np.sum(~(d > 0.0)))} non-positive pivot(s) "
                                       "(matrix not positive definite)")
        self.current = True

    def solve(self, b):
        return self.lu.solve(b)

    def factor_nbytes(self) -> int:
        return 12 * int(self.lu.L.nnz + self.lu.U.nnz)

    def detach(self, capacity):
        """The current factor as a kept one (SuperLU makes a new one per factorisation anyway)."""
        kept = _KeptFactor(self, None, self.lu, self.factor_nbytes())
        self.lu = None
        self.current = False
        return kept


def _make_backend(name):
    if name == "pardiso":
        return _Pardiso()
    if name == "qdldl":
        return _QDLDL()
    if name == "superlu":
        return _SuperLU()
    raise ValueError(f"unknown direct backend {name!r}; available: {', '.join(BACKENDS)}")


def available_backends() -> list[str]:
    """The installed direct backends in the order ``auto`` prefers them (measured: PARDISO, then
    SuperLU, whose factorisation was faster than QDLDL's on the bunny despite redoing the ordering)."""
    out = []
    try:
        _make_backend("pardiso")
        out.append("pardiso")
    except (MissingExtra, ImportError, OSError):
        pass
    out.append("superlu")
    try:
        _make_backend("qdldl")
        out.append("qdldl")
    except (MissingExtra, ImportError, OSError):
        pass
    return out


class DirectSolver(HostLinearSolver):
    """Sparse Cholesky/LDL^T of (P A P + I - P) on the host, symbolic analysis reused.

    Args:
        backend: "auto", "pardiso", "qdldl" or "superlu" (see the module docstring).
    """

    name = "direct"
    eager_inv_diag = False  # the block-Jacobi inverse is only needed when a factorisation fails
    iterative = False

    def __init__(self, pattern, *, vec_type, scalar, backend: str = "auto"):
        if backend not in BACKENDS:
            raise ValueError(f"unknown direct backend {backend!r}; available: {', '.join(BACKENDS)}")
        if backend == "auto":
            backend = available_backends()[0]
        self.backend_name = backend
        self.backend = _make_backend(backend)
        self.triangle = self.backend.triangle
        self._failure = ""
        self._shift = 0.0
        self._null = None
        self._scale = 1.0
        self.shifted_factorisations = 0  # how many factorisations needed a diagonal shift (cumulative)
        #: set by project-on-demand Newton while it tries the exact Hessian: a non-positive pivot
        #: then fails the solve at once (no shifted retries), and the Newton loop projects
        self.definite_only = False
        import weakref

        self._kept = weakref.WeakSet()  # factorisations handed over by keep_factor
        super().__init__(pattern, vec_type=vec_type, scalar=scalar)

    @property
    def symbolic_count(self) -> int:
        """How many symbolic analyses (orderings) the backend has done (over every pattern)."""
        return self.backend.symbolic_count + getattr(self, "_symbolic_before", 0)

    def _analyse(self, pattern):
        super()._analyse(pattern)
        if self.analyse_count > 1:  # a grown pattern: a fresh backend, analysed on its next factorisation
            self._symbolic_before = self.symbolic_count
            self.backend = _make_backend(self.backend_name)

    @property
    def has_factor(self) -> bool:
        """Whether the solver holds a usable factorisation of the last prepared matrix (not after
        :meth:`keep_factor` handed it over, nor after a factorisation that failed)."""
        return bool(getattr(self.backend, "current", False)) and not self._failure

    @property
    def kept_bytes(self) -> int:
        """Bytes of the factorisations handed over by :meth:`keep_factor` and not yet released."""
        return int(sum(k.nbytes for k in list(self._kept) if not k.released))

    def keep_factor(self, budget_bytes):
        """Hand over the factorisation of the last prepared matrix, for a later solve with it (the
        reverse pass of a recorded step, :mod:`warpfem.solvers.adjoint`), when it fits in
        ``budget_bytes``. Returns a kept factor (``solve(b)``: host float64 in the masked system's
        DOF order, ``nbytes``, ``shift``, ``release()``, also done when it is deleted) or None (no
        factorisation, it does not fit, or no PARDISO factor slot is left); the next ``prepare``
        factorises into new storage. Costs the forward nothing with PARDISO (a factor slot of the
        same analysis; :meth:`reserve_factors` makes the slots before a recording) and SuperLU; with
        QDLDL the next factorisation redoes its ordering."""
        if not self.has_factor:
            return None
        nb = self.backend.factor_nbytes()
        if nb <= 0 or nb > budget_bytes:
            return None
        kf = self.backend.detach(capacity=min(int(budget_bytes // nb), MAX_KEPT_FACTORS))
        if kf is not None:
            kf.shift = self._shift
            self._kept.add(kf)
        return kf

    def reserve_factors(self, budget_bytes):
        """Before a recording: room for the factorisations that ``budget_bytes`` allows (PARDISO's
        factor slots; the current factorisation is dropped when they grow, so call it before a step)."""
        reserve = getattr(self.backend, "reserve", None)
        if reserve is not None and getattr(self.backend, "analysed", False):
            nb = self.backend.factor_nbytes()
            if 0 < nb <= budget_bytes:
                reserve(min(int(budget_bytes // nb), MAX_KEPT_FACTORS))

    @property
    def failure(self) -> str:
        """Why the last prepared matrix could not be factorised even with a shift ("" when it was)."""
        return self._failure

    @property
    def shift(self) -> float:
        """The diagonal shift the last factorisation needed (0.0: the matrix factorised as it is)."""
        return self._shift

    def _prepare(self, values, mask):
        A = self.host_matrix(values, mask)
        self._A_host = A
        self._failure = ""
        self._shift = 0.0
        self._null = None
        free = self._mask_host > 0.0
        d = A.data[self._diag_pos]  # the diagonal (positions found once per pattern; A.diagonal() searches)
        scale = float(np.max(np.abs(d[free]))) if free.any() else 1.0
        self._scale = scale if (np.isfinite(scale) and scale > 0.0) else 1.0
        try:
            self.backend.factor(A)
        except _NotPositiveDefinite as e:
            if self.definite_only:
                self._failure = f"{e} (exact Hessian: the Newton loop projects it)"
                self._setup_inv_diag(values, mask)
                return
            self._factor_shifted(A, str(e), values, mask)

    def _factor_shifted(self, A, reason, values, mask):
        """Factorise A + delta I (free DOFs) with the smallest delta of SHIFTS that works."""
        scale = self._scale
        for rel in SHIFTS:
            delta = rel * scale
            As = A.copy()
            As.data[self._diag_pos] += delta * self._mask_host
            try:
                self.backend.factor(As)
            except _NotPositiveDefinite:
                continue
            self._shift = delta
            self.shifted_factorisations += 1
            log.info("direct solver (%s): %s; factorised with a diagonal shift of %.1e x the largest diagonal "
                     "entry (%.3e) and refining against the unshifted matrix", self.backend_name, reason, rel, delta)
            return
        self._failure = f"{reason}; still not positive definite with a diagonal shift of {SHIFTS[-1]:g} x {scale:.3e}"
        self._setup_inv_diag(values, mask)
        log.warning("direct solver (%s): %s; returning the block-Jacobi direction", self.backend_name, self._failure)

    def _solve(self, b, x, *, tol, maxiter) -> LinearSolveResult:
        if self._failure:
            wp.launch(K.block_apply_kernel, dim=self.num_rows, inputs=[self.inv_diag, b, x], device=self.device)
            return LinearSolveResult(0, float("nan"), False, host_syncs=0, failed=self._failure)
        bh = read(b).reshape(-1) * self._mask_host  # float64; the system is P b (b should already be masked)
        syncs = 1
        bn = float(np.linalg.norm(bh))
        xh, rel = self._refined_solve(bh, bn, tol)
        if not np.all(np.isfinite(xh)):
            return LinearSolveResult(1, float("nan"), False, host_syncs=syncs, failed="non-finite solution")
        deflated = 0
        xx = float(xh @ xh)
        # Rayleigh quotient of the solution: when x is dominated by an eigendirection of (near) zero
        # eigenvalue, x.b / x.x is that eigenvalue. A pivot of the wrong sign sent us here already.
        if self._shift > 0.0 or (xx > 0.0 and float(xh @ bh) < NULL_TOLERANCE * self._scale * xx):
            V, lam_plus = self._near_null_space()
            if V.shape[1]:
                deflated = V.shape[1]
                c = V.T @ bh
                xh, rel = self._refined_solve(bh - V @ c, bn, tol)
                xh = xh - V @ (V.T @ xh) + V @ (c / lam_plus)
        upload(x, xh)  # (on the CPU outside strict device mode: written into x's memory, no temporary)
        return LinearSolveResult(1, rel, bool(rel <= tol), host_syncs=syncs, shift=self._shift, deflated=deflated)

    def _refined_solve(self, bh, bn, tol):
        """x ~ A^-1 b from the factor, with iterative refinement against the unshifted matrix: when
        a tight tolerance is below the factor's accuracy (2 rounds), or after a shifted
        factorisation (until the tolerance is met or the residual stops decreasing; each round
        shrinks the error in an eigendirection of eigenvalue lam by delta / (lam + delta)).
        Returns (x, ||A x - b|| / ||b||)."""
        xh = self.backend.solve(bh) * self._mask_host  # exactly zero at fixed DOFs
        if not np.all(np.isfinite(xh)):
            return xh, float("nan")
        r = self._host_residual(xh, bh)
        rel = 0.0 if bn == 0.0 else float(np.linalg.norm(r) / bn)
        for _ in range(SHIFTED_REFINEMENTS if self._shift > 0.0 else 2):
            if rel <= tol:
                break
            x_new = xh - self.backend.solve(r) * self._mask_host
            r_new = self._host_residual(x_new, bh)
            rel_new = float(np.linalg.norm(r_new) / bn)
            if not (np.isfinite(rel_new) and rel_new < rel):
                break
            xh, r, rel = x_new, r_new, rel_new
        return xh, rel

    def _near_null_space(self):
        """(V, lam_plus): an orthonormal basis V of the free-DOF eigendirections of A with
        eigenvalue <= NULL_TOLERANCE x the largest diagonal entry (zero or negative), and the
        smallest Ritz value above that (the curvature the step along V is scaled by).

        Block inverse iteration with the (shifted) factor on NULL_PROBES masked vectors, then
        Rayleigh-Ritz with the unshifted A; computed once per prepared matrix."""
        if self._null is not None:
            return self._null
        m = self._mask_host
        n_free = int(np.sum(m > 0.0))
        k = min(NULL_PROBES, n_free)
        rng = np.random.default_rng(0)
        V = rng.standard_normal((self.n3, k)) * m[:, None]
        for _ in range(3):
            V = np.linalg.qr(V)[0]
            V = np.column_stack([self.backend.solve(np.ascontiguousarray(V[:, j])) for j in range(k)]) * m[:, None]
        V = np.linalg.qr(V)[0]
        AV = np.column_stack([self._host_residual(V[:, j], np.zeros(self.n3)) for j in range(k)])
        theta, Y = np.linalg.eigh(0.5 * (V.T @ AV + AV.T @ V))
        V = V @ Y
        small = theta <= NULL_TOLERANCE * self._scale
        above = theta[~small]
        lam_plus = float(above[0]) if above.size else float(self._scale)
        self._null = (V[:, small], lam_plus)
        if small.any():
            log.info("direct solver (%s): %d eigendirection(s) of (near) zero or negative curvature (Ritz values "
                     "%s, smallest positive %.3e): solved on the rest, a gradient step scaled by %.3e along them",
                     self.backend_name, int(small.sum()), np.array2string(theta[small], precision=3), lam_plus, lam_plus)
        return self._null

    def _host_residual(self, xh, bh):
        A = self._A_host
        if self.triangle == "full":
            return A @ xh - bh
        d = A.data[self._diag_pos]
        return A @ xh + A.T @ xh - d * xh - bh


def _np_of(arr):
    return np.float32 if arr.dtype == wp.vec3 else np.float64
