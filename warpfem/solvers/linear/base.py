"""The linear-solver interface of the Newton loop, and the registry that builds solvers by name.

Every Newton system is H d = -g over 3x3-block-sparse matrices of one fixed pattern
(:class:`~warpfem.solvers.sparse.BlockPattern`), with fixed degrees of freedom handled by a mask
P (1 = free, 0 = fixed): the solved system is (P H P + I - P) x = P b. A solver goes through

* ``analyse(pattern)``: once per pattern (the constructor calls it, and the simulator's
  ``HessianSystem`` again when a form makes the pattern grow): workspaces, orderings, symbolic
  factorisations;
* ``prepare(values, mask)``: once per Newton iteration: the numeric factorisation or the
  preconditioner of the matrix with these block values;
* ``solve(b, x, *, tol, maxiter) -> LinearSolveResult``: x from b (already masked); ``x`` is
  overwritten (the initial guess is zero).

For the current Newton loop every solver also keeps the one-call form
``solve(values, mask, b, x, *, tol, maxiter)`` (prepare + solve) and provides ``dot(a, b)``
(float64 reduction, read on the host), ``inv_diag`` (the block-Jacobi inverse diagonal of the last
prepared matrix, Newton's fallback direction), ``device`` and ``scalar``.
"""

from __future__ import annotations

import contextlib

import logging
from dataclasses import dataclass

import numpy as np
import warp as wp

from warpfem.kernels import linalg as K
from warpfem.kernels.generic import launch, ordered_sums
from warpfem.transfer import read, read_scalar

log = logging.getLogger(__name__)


@contextlib.contextmanager
def numpy_global_seed(seed: int = 0):
    """NumPy's global random state seeded inside the block and restored after it: pyamg's set-up
    draws its spectral-radius estimates (the prolongator smoothing weight) from ``np.random``, so
    without this two builds of the same hierarchy differ in the last bits, and so does every
    solve with it."""
    state = np.random.get_state()
    np.random.seed(seed)
    try:
        yield
    finally:
        np.random.set_state(state)


@dataclass
class LinearSolveResult:
    """What one linear solve did.

    ``residual`` is ||b - A x|| / ||b|| as far as the solver knows it (the recursive residual for
    iterative solvers, the true one for direct solvers); ``host_syncs`` counts the times the
    host waited for the device (read-backs) inside the solve, ``failed`` says why a solve could not
    be done at all (e.g. a factorisation of an indefinite matrix), empty otherwise; ``shift`` is the
    diagonal shift a direct factorisation needed (0.0 when the matrix factorised as it is; see
:mod:`warpfem.solvers.linear.direct`); ``deflated`` the number of (near) zero- or
    negative-curvature eigendirections a direct solve took out of the system and stepped along by a
    scaled gradient instead (0 normally).
    """

    iterations: int
    residual: float
    converged: bool
    host_syncs: int = 0
    negative_curvature: bool = False
    failed: str = ""
    shift: float = 0.0
    deflated: int = 0


class MissingExtra(ImportError):
    """An optional dependency of a linear solver is not installed."""


def require(module: str, extra: str, what: str):
    """Import ``module`` or raise :class:`MissingExtra` naming the pip extra that provides it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as e:
        raise MissingExtra(f"the {what} needs the Python package '{module}', which is not installed; "
                           f"install it with: pip install \"warpfem[{extra}]\" ({e})") from e


class LinearSolver:
    """Base class: the shared workspace (block-Jacobi inverse diagonal, dot products) and the
    compatibility form of ``solve``. Subclasses implement ``_analyse``, ``_prepare``, ``_solve``."""

    name = "base"
    #: whether ``prepare`` computes ``inv_diag`` (solvers that only need it on failure compute it then)
    eager_inv_diag = True
    #: whether the solve iterates to a relative residual (a start near the solution saves work: the
    #: friction pin's second solve is warm-started only then); False for a factorisation
    iterative = True

    def __init__(self, pattern, *, vec_type, scalar):
        self.pattern = pattern
        self.vec_type = vec_type
        self.scalar = scalar
        self.device = pattern.device
        n = pattern.num_rows
        self.num_rows = n
        self._inv_diag = None  # allocated here when eager, else on first use (see ``inv_diag``)
        if self.eager_inv_diag:
            self._inv_diag = wp.zeros(n, dtype=pattern.block_type, device=self.device)
        self._dot = wp.zeros(1, dtype=wp.float64, device=self.device)
        self.host_syncs = 0  # read-backs by this object (solves and dots), cumulative
        self.analyse_count = 0
        self.prepare_count = 0
        self._values = None
        self._mask = None
        self.analyse(pattern)

    # -- interface --------------------------------------------------------------------------------
    def analyse(self, pattern):
        """Once per pattern: workspaces and any symbolic analysis. Called again with a grown
        pattern of the same mesh (``HessianSystem.ensure_blocks``): the solver binds to it."""
        if pattern is not self.pattern and (pattern.num_rows != self.pattern.num_rows):
            raise ValueError("a linear solver is bound to one pattern; build a new solver for another mesh")
        self.pattern = pattern
        self._values = None
        self.analyse_count += 1
        self._analyse(pattern)

    def prepare(self, values, mask):
        """Once per matrix: factorise / build the preconditioner of (P A P + I - P)."""
        self._values, self._mask = values, mask
        if self.eager_inv_diag:
            self._setup_inv_diag(values, mask)
        self.prepare_count += 1
        self._prepare(values, mask)

    def solve(self, *args, tol: float, maxiter: int) -> LinearSolveResult:
        """``solve(b, x, *, tol, maxiter)`` after :meth:`prepare`, or the one-call form
        ``solve(values, mask, b, x, *, tol, maxiter)`` (prepare, then solve)."""
        if len(args) == 4:
            values, mask, b, x = args
            self.prepare(values, mask)
        elif len(args) == 2:
            b, x = args
            if self._values is None:
                raise RuntimeError(f"{type(self).__name__}.solve(b, x) called before prepare(values, mask)")
        else:
            raise TypeError("solve takes (b, x) after prepare(), or (values, mask, b, x)")
        res = self._solve(b, x, tol=float(tol), maxiter=int(maxiter))
        self.host_syncs += res.host_syncs
        return res

    # -- the step-to-step state (a simulator's ``state_dict``) ---------------------------------------
    def state_dict(self) -> dict:
        """What the solver carries from one Newton system to later ones that changes their numbers or
        its choices (a recorded choice, a kept preconditioner); default: nothing."""
        return {}

    def load_state_dict(self, view):
        """Set what :meth:`state_dict` returned (a :class:`warpfem.io.checkpoint.StateView`)."""

    # -- shared helpers ---------------------------------------------------------------------------
    @property
    def inv_diag(self):
        """The block-Jacobi inverse diagonal workspace (allocated on first use unless ``eager_inv_diag``)."""
        if self._inv_diag is None:
            self._inv_diag = wp.zeros(self.num_rows, dtype=self.pattern.block_type, device=self.device)
        return self._inv_diag

    def _setup_inv_diag(self, values, mask):
        pt = self.pattern
        launch(K.block_jacobi_setup_kernel, pt.num_rows, [pt.offsets, pt.columns, values, mask, self.inv_diag], self.device)

    def dot(self, a, b) -> float:
        """a . b reduced in float64, read on the host (one host sync)."""
        self._dot.zero_()
        if ordered_sums(self.device):  # (a fixed order on devices other than the CPU)
            K.launch_dot(a, b, self._dot, self.device)
        else:
            wp.launch(K.dot_kernel, dim=a.shape[0], inputs=[a, b, self._dot], device=self.device)
        self.host_syncs += 1
        return read_scalar(self._dot)

    def matvec(self, values, mask, x, y):
        """y = (P A P + I - P) x."""
        pt = self.pattern
        wp.launch(K.bsr_masked_mv_kernel, dim=pt.num_rows,
                  inputs=[pt.offsets, pt.columns, values, mask, x, y, 1], device=self.device)

    def _analyse(self, pattern):
        pass

    def _prepare(self, values, mask):
        pass

    def _solve(self, b, x, *, tol, maxiter) -> LinearSolveResult:  # pragma: no cover - abstract
        raise NotImplementedError


class HostLinearSolver(LinearSolver):
    """A solver that works on the host in float64 scalar CSR form (direct and AMG backends).

    ``analyse`` builds, once, the map from the block values to the scalar CSR data of the
    (3n x 3n) matrix, full or one triangle; ``prepare`` copies the blocks to the host (one
    read-back), applies the mask (identity rows and columns at fixed DOFs, keeping the pattern so
    symbolic analyses stay valid) and hands the CSR matrix to the backend.
    """

    triangle = "full"  # "full", "lower" or "upper" (lower CSR arrays == upper CSC arrays)

    def _analyse(self, pattern):
        import scipy.sparse

        n = pattern.num_rows
        offsets = read(pattern.offsets, n + 1).astype(np.int64)
        nnzb = pattern.nnz
        # scalar CSR of the block matrix with data = arange(9 nnzb): its data says where each
        # scalar entry comes from in the flat (nnzb, 3, 3) value array
        idx = np.arange(9 * nnzb, dtype=np.float64).reshape(nnzb, 3, 3) + 1.0  # +1: no explicit zero
        bsr = scipy.sparse.bsr_matrix((idx, pattern.cols_np, offsets), shape=(3 * n, 3 * n))
        A = bsr.tocsr()
        A.sort_indices()
        if self.triangle in ("lower", "upper"):
            A = (scipy.sparse.tril if self.triangle == "lower" else scipy.sparse.triu)(A, format="csr")
            A.sort_indices()
        self._src = (A.data - 1.0).astype(np.int64)
        self._indptr = A.indptr.astype(np.int32)
        self._indices = A.indices.astype(np.int32)
        rows = np.repeat(np.arange(3 * n), np.diff(A.indptr))
        self._row_of = rows
        self._diag_pos = np.nonzero(rows == A.indices)[0]
        if len(self._diag_pos) != 3 * n:
            raise RuntimeError("block pattern without a full diagonal")
        self.n3 = 3 * n

    def host_matrix(self, values, mask):
        """The masked float64 CSR matrix (P A P + I - P) of these device block values."""
        import scipy.sparse

        v = read(values).astype(np.float64, copy=False).reshape(-1)
        m = read(mask).astype(np.float64, copy=False).reshape(-1)
        self.host_syncs += 2
        data = v[self._src]
        data *= m[self._row_of] * m[self._indices]
        data[self._diag_pos] += 1.0 - m
        self._mask_host = m
        return scipy.sparse.csr_matrix((data, self._indices, self._indptr), shape=(self.n3, self.n3))


_REGISTRY: dict[str, str] = {
    "auto": "warpfem.solvers.linear.auto:AutoSolver",
    "pcg": "warpfem.solvers.linear.pcg:DevicePCG",
    "direct": "warpfem.solvers.linear.direct:DirectSolver",
    "amg": "warpfem.solvers.linear.amg:AMGSolver",
    "multigrid": "warpfem.solvers.linear.multigrid:MultigridPCG",
}

LINEAR_SOLVERS = tuple(_REGISTRY)


def make_linear_solver(name: str, pattern, *, vec_type, scalar, positions=None, **options):
    """Build the linear solver ``name`` ("auto", "pcg", "direct", "amg") for ``pattern``.

    ``options`` go to the solver's constructor (e.g. ``check_every`` for pcg, ``backend`` for
    direct, ``rebuild_every`` for amg). ``positions`` ((n, 3), the model's rest positions) give
    amg its rigid-body modes. ``auto`` picks among them by a fixed rule on the problem's size and
    its CG iteration counts (see :mod:`warpfem.solvers.linear.auto`).
    """
    import importlib
    import inspect

    if not isinstance(name, str) or name not in LINEAR_SOLVERS:
        raise ValueError(f"unknown linear solver {name!r}; available: {', '.join(LINEAR_SOLVERS)}")
    modname, clsname = _REGISTRY[name].split(":")
    cls = getattr(importlib.import_module(modname), clsname)
    accepted = set(inspect.signature(cls.__init__).parameters) - {"self", "pattern", "vec_type", "scalar"}
    if "positions" in accepted and positions is not None and "positions" not in options:
        options = {**options, "positions": positions}
    unknown = set(options) - accepted
    if unknown:
        raise TypeError(f"linear solver {name!r}: unknown option(s) {sorted(unknown)}; known: {sorted(accepted)}")
    log.debug("linear solver: %s", name)
    return cls(pattern, vec_type=vec_type, scalar=scalar, **options)
