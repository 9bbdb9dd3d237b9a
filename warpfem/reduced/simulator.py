"""Reduced implicit time stepping on a subspace x = X + U q with cubature forces (An, Kim & James 2008,
"Optimizing cubature for efficient integration of subspace deformations").

Incremental potential over the reduced velocity v (r-vector); for backward Euler (s = h; BDF2 and
Newmark change the prediction and s, see :mod:`warpfem.integrators`):

    E(v) = 1/2 (v - v_n)^T M_r (v - v_n) + h/2 v^T C_r v + V_c(q_n + h v) - h v^T U^T f_ext,

M_r = U^T M U (= I for a mass-orthonormal basis), C_r = alpha M_r + beta K_r(q_n) (projected),
V_c the cubature energy. Newton with an Armijo backtracking line search and a dense r x r
Cholesky solve (LAPACK); the material is evaluated at the cubature points only, by one Warp
kernel launch per evaluation (``warpfem.kernels.subspace.cubature_point_kernel``), with the
deformation gradients F = I + G z formed and the reduced force and stiffness reduced on the host
(dense products). The r x r Newton matrix is kept across iterations and steps (BFGS-updated,
evaluated again when it stops contracting). See docs/reduced.md, "Cost of a reduced step".
"""

from __future__ import annotations

import math
import time

import numpy as np
from scipy.linalg.lapack import dpotrf as _potrf, dpotrs as _potrs
import warp as wp

from warpfem.device import get_device as _get_device
from warpfem.kernels import subspace as RK
from warpfem.kernels.generic import RecordedLaunch, launch
from warpfem.kernels.structs import material_params, quadrature_points
from warpfem.integrators import make_integrator
from warpfem.solvers.nonlinear import SolveFailed, SolveStats, newton_solve
from warpfem.transfer import host_aliases
from warpfem.solvers.state import PRECISIONS, State, StepperBase, check_simulator_options, newton_options_from



def _basis_array(U, n, vec, npdt, device):
    r = U.shape[1]
    return wp.array(np.ascontiguousarray(U.reshape(n, 3, r).transpose(0, 2, 1)).astype(npdt), dtype=vec, device=device)


_amax, _asum = np.maximum.reduce, np.add.reduce  # the ufunc reductions without ndarray.max/sum's wrappers

_COPY_ARRAYS = False  # tests: exercise the GPU path (explicit copies to and from the device) on the CPU


def _chunk_points(c: int, k: int) -> int:
    """Cubature points per chunk of the host products over k columns, so that every BLAS call stays
    below OpenBLAS's multithreading thresholds (m n k < 262144 for a matrix product, m n < 9216
    for a matrix-vector product): on a small loaded machine a threaded call of these sizes cost
    10-100x a single-threaded one (measured: 26 x 1548 x 26, 0.15 ms on one thread, 0.6-15 ms on two)."""
    return int(max(1, min(c, 9216 // (9 * (k + 1)) - 1, 262144 // (9 * k * k) - 1)))


class _Columns:
    """dF/dz of the cubature points for a subset of the basis columns, laid out for the host
    products: ``G`` (cp, 9, k) (zero rows for the padding points), ``G3`` / ``G3T`` its chunks
    (nch, 9 m, k) / (nch, k, 9 m), and a work array ``T`` (cp, 9, k) for dP/dF G (these two made
    with the first stiffness). ``Gb3`` is
    [G | base] in chunks: F = base + G (scale z) is one product with [scale z; 1]."""

    def __init__(self, G, m, I9):
        cp, _, k = G.shape
        self.k, self.nch = k, cp // m
        Gb = np.zeros((cp * 9, k + 1))
        Gb[:, :k] = G.reshape(-1, k)
        Gb[:, k] = I9
        self.Gb3 = Gb.reshape(self.nch, 9 * m, k + 1)
        self.base = None  # the base in the last column (None: the identity)
        self.zb = np.zeros(k + 1)
        self.zb[k] = 1.0
        self.G = np.ascontiguousarray(G)
        self.G3 = self.G.reshape(self.nch, 9 * m, k)
        self.Gflat = self.G.reshape(-1, k)
        self._m = m
        self.G3T = self.T = self.T3 = None  # allocated with the first stiffness

    def stiffness_buffers(self):
        if self.T is None:
            self.G3T = np.ascontiguousarray(self.G3.transpose(0, 2, 1))
            self.T = np.zeros_like(self.G)
            self.T3 = self.T.reshape(self.nch, 9 * self._m, self.k)


class CubatureForces:
    """Reduced energy (J), force U^T f (r,) and stiffness U^T K U (r, r) by cubature on a device.

    Args:
        model: the Model (tet4).
        U: (3n, r) basis.
        elements, weights: cubature elements and dimensionless weights (weight 1 for every element
            gives the exact reduced quantities).

    The deformation gradient of a cubature tet is affine in the reduced coordinates, F_c = I + G_c z
    with G_c = dF/dz (9 x r) fixed by the basis, so an evaluation is: F for every point by one
    matrix-vector product on the host, one launch of ``cubature_point_kernel`` (w psi, w P and, when
    asked, the 9 x 9 w dP/dF per point), then f = -sum_c G_c^T vec(w P) and
    K = sum_c G_c^T (w dP/dF) G_c as dense products on the host, read from the kernel's output
    arrays in place on the CPU (one copy each on a GPU). ``evaluate_per_element`` is the earlier
    two-kernel path (per-element forces and stiffness blocks, projected per reduced entry in the
    cubature points' order), kept as a reference.
    """

    def __init__(self, model, U, elements, weights, *, device="cpu", precision="float64"):
        if getattr(model, "num_bodies", 1) > 1:
            raise ValueError(f"the reduced simulator simulates one body; the model has {model.num_bodies} (use warpfem.Simulator)")
        qd = model.quadrature
        from warpfem.mesh.element_types import get_element

        if not get_element(qd.element_type).is_linear_tet:
            raise ValueError(f"reduced simulation supports tet4 meshes only, got {qd.element_type!r}")
        U = np.asarray(U, dtype=np.float64)
        n = model.num_vertices
        if U.ndim != 2 or U.shape[0] != 3 * n or U.shape[1] < 1:
            raise ValueError(f"basis U must have shape (3n = {3 * n}, r >= 1), got {U.shape}")
        elements = np.asarray(elements, dtype=np.int64)
        weights = np.asarray(weights, dtype=np.float64)
        m = qd.num_elements
        if elements.shape != weights.shape or elements.ndim != 1 or elements.size == 0:
            raise ValueError(f"cubature elements and weights must be equal-length 1-d arrays, got {elements.shape}, {weights.shape}")
        if elements.min() < 0 or elements.max() >= m:
            raise ValueError(f"cubature element index out of range [0, {m}): {elements[(elements < 0) | (elements >= m)][:5]}")
        if np.any(weights < 0) or not np.all(np.isfinite(weights)):
            raise ValueError("cubature weights must be finite and non-negative")
        self.device = dev = _get_device(device)
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be 'float32' or 'float64', got {precision!r}")
        self._s, vec, mat, npdt = PRECISIONS[precision]
        self.r = r = U.shape[1]
        self.c = c = len(elements)
        mat_ = model.material
        self.material = material_params(self._s, mat_.kind, mat_.kernel_mu, mat_.kernel_lam)
        self.U = _basis_array(U, n, vec, npdt, dev)
        tets = qd.elements.reshape(-1, 4)[elements]
        # the cubature points (kernels.structs.QuadraturePoints): the cubature tets only, one point
        # each, weight = cubature weight x volume; no rest positions (F comes from U q)
        self.points = quadrature_points(
            self._s, None, wp.array(tets.reshape(-1).astype(np.int32), dtype=wp.int32, device=dev), 4,
            wp.array(np.arange(c, dtype=np.int32), dtype=wp.int32, device=dev),
            wp.array((weights * qd.qp_weight[elements]).astype(npdt), dtype=self._s, device=dev),
            wp.array(qd.qp_dNdX.reshape(-1, 4, 3)[elements].reshape(-1, 3).astype(npdt), dtype=vec, device=dev))
        dN = qd.qp_dNdX.reshape(-1, 4, 3)[elements]
        self._q = wp.zeros(r, dtype=self._s, device=dev)
        self._energy = wp.zeros(c, dtype=self._s, device=dev)
        self._f = wp.zeros(4 * c, dtype=vec, device=dev)
        self._H = wp.zeros(16 * c, dtype=mat, device=dev)
        self._force = wp.zeros(r, dtype=self._s, device=dev)
        self._K = wp.zeros((r, r), dtype=self._s, device=dev)
        self._npdt = npdt
        # -- the point path: F_c = I + G_c z, G[c, 3i+j, l] = sum_a U[3 n_a + i, l] dN_a/dX_j --------
        mpts = _chunk_points(c, r)
        self._m = mpts = -(-c // -(-c // mpts))  # the same number of chunks, balanced: little padding
        cp = -(-c // mpts) * mpts  # padded to whole chunks with zero points (never launched)
        G = np.zeros((cp, 9, r))
        G[:c] = np.einsum("caik,caj->cijk", U.reshape(n, 3, r)[tets], dN, optimize=True).reshape(c, 9, r)
        self.G = G
        self._I9 = np.tile(np.eye(3).reshape(9), cp)
        self._all = _Columns(G, mpts, self._I9)
        self._Fd = wp.zeros(cp, dtype=mat, device=dev)
        self._psi_d = wp.zeros(cp, dtype=self._s, device=dev)
        self._P_d = wp.zeros(cp, dtype=mat, device=dev)
        self._D_d = wp.zeros(81 * cp, dtype=self._s, device=dev)
        self._zero_copy = host_aliases(dev) and not _COPY_ARRAYS  # host views of the device arrays: no copies at all
        self._Fh = self._Fd.numpy().reshape(-1) if self._zero_copy else np.zeros(9 * cp, dtype=npdt)
        self._Fw = self._Fh if (self._zero_copy and npdt == np.float64) else np.zeros(9 * cp)
        self._Fw3 = self._Fw.reshape(cp // mpts, -1)
        self._pull(hessian=True)
        self.version = 0  # bumped whenever the point deformation gradients change
        from warpfem.materials.stable_neo_hookean import StableNeoHookean

        # the exact dP/dF in closed form (no SVD); float64 only: in float32 its sums of O(lambda)
        # terms lose ~1e-3 of K (measured), the eigen form keeps ~1e-6
        snh = int(type(mat_) is StableNeoHookean and npdt == np.float64)
        self._launch = {(h, pr): RecordedLaunch(RK.cubature_point_kernel, c, [
            self._Fd, self.points, self.material, h, pr, snh, self._psi_d, self._P_d, self._D_d], dev)
            for h in (0, 1) for pr in (0, 1)}

    # -- public views of the fused evaluation's buffers (the reduced step potential reads them) ------
    @property
    def zero_copy(self) -> bool:
        """Whether the kernel's outputs are read in place (CPU) rather than copied (GPU)."""
        return self._zero_copy

    @property
    def launches(self):
        """The recorded launches of the point kernel, by (chunk, hessian) key."""
        return self._launch

    @property
    def P3(self):
        return self._P3

    @property
    def I9(self):
        return self._I9

    @property
    def all_columns(self):
        return self._all

    @property
    def psi(self):
        return self._psi

    def columns(self, cols) -> _Columns:
        """The point Jacobians of a slice of the basis columns (e.g. the elastic columns without the
        handle lifting), laid out for :meth:`force` / :meth:`stiffness`."""
        return _Columns(self.G[:, :, cols], self._m, self._I9)

    # -- the point path ---------------------------------------------------------------------------
    def _pull(self, hessian):
        cp = self.G.shape[0]
        if self._zero_copy:
            if not hasattr(self, "_psi"):
                self._psi, self._P, self._D = (self._psi_d.numpy(), self._P_d.numpy().reshape(-1),
                                               self._D_d.numpy().reshape(cp, 9, 9))
                self._P3 = self._P.reshape(cp // self._m, 1, -1)
            return
        self._psi, self._P = self._psi_d.numpy(), self._P_d.numpy().reshape(-1)
        self._P3 = self._P.reshape(cp // self._m, 1, -1)
        if hessian:
            self._D = self._D_d.numpy().reshape(cp, 9, 9)
        elif not hasattr(self, "_D"):
            self._D = np.zeros((cp, 9, 9), dtype=self._npdt)

    def set_coordinates(self, z, cols: _Columns | None = None, *, scale: float = 1.0, base=None):
        """Point deformation gradients F = base + scale G z (base: the identity by default, else a
        (9 cp,) float64 array from :meth:`deformation`), written where the kernel reads them."""
        cols = self._all if cols is None else cols
        if base is not cols.base:
            cols.Gb3[:, :, -1] = (self._I9 if base is None else base).reshape(cols.nch, -1)
            cols.base = base
        zb = cols.zb
        np.multiply(z, scale, out=zb[:-1])
        out = self._Fw
        np.matmul(cols.Gb3, zb, out=out.reshape(cols.nch, -1))
        if out is not self._Fh:
            self._Fh[...] = out  # to the working precision
        if not self._zero_copy:
            self._Fd.assign(self._Fh.reshape(-1, 3, 3))
        self.version += 1

    def set_product(self, Gb3, zb):
        """Point deformation gradients F = Gb3 zb for chunks ``Gb3`` laid out like
        ``_Columns.Gb3`` (e.g. [s G_u | F0] with zb = [v; 1]), written where the kernel reads them."""
        np.matmul(Gb3, zb, out=self._Fw3)
        if self._Fw is not self._Fh:
            self._Fh[...] = self._Fw  # to the working precision
        if not self._zero_copy:
            self._Fd.assign(self._Fh.reshape(-1, 3, 3))
        self.version += 1

    def deformation(self, z) -> np.ndarray:
        """I + G z for the whole basis, (9 cp,) float64 (a new array)."""
        z = np.asarray(z, dtype=np.float64)
        return self._I9 + (self._all.G3 @ z).reshape(-1)

    def run(self, *, hessian: bool = False, project: bool = True):
        """Evaluate the material at the current point deformation gradients (one launch)."""
        self._launch[int(bool(hessian)), int(bool(project) and bool(hessian))]()
        self._pull(hessian)

    def energy(self) -> float:
        return float(_asum(self._psi, dtype=np.float64))

    def force(self, cols: _Columns | None = None) -> np.ndarray:
        """-sum_c G_c^T vec(w P_c) over the columns ``cols`` (default: all)."""
        cols = self._all if cols is None else cols
        return -(self._P @ cols.Gflat)

    def stiffness(self, cols: _Columns | None = None) -> np.ndarray:
        """sum_c G_c^T (w dP/dF)_c G_c over ``cols`` (needs :meth:`run` with ``hessian=True``)."""
        cols = self._all if cols is None else cols
        cols.stiffness_buffers()
        np.matmul(self._D, cols.G, out=cols.T)
        K = np.matmul(cols.G3T, cols.T3).sum(axis=0) if cols.nch > 1 else cols.G3T[0] @ cols.T3[0]
        return 0.5 * (K + K.T)

    def evaluate(self, q, *, hessian: bool = False, project: bool = True):
        """(energy J, force (r,), stiffness (r, r) or None) at q, float64 numpy."""
        q = np.asarray(q, dtype=np.float64)
        if q.shape != (self.r,):
            raise ValueError(f"reduced coordinates must have shape ({self.r},), got {q.shape}")
        self.set_coordinates(q)
        self.run(hessian=hessian, project=project)
        return self.energy(), self.force(), (self.stiffness() if hessian else None)

    def evaluate_per_element(self, q, *, hessian: bool = False, project: bool = True):
        """:meth:`evaluate` by the earlier path: per-element node forces and 4 x 4 stiffness blocks
        (``cubature_element_kernel``), projected on the basis per reduced entry, summed over the points in
        their order (``cubature_project_kernel``)."""
        self._q.assign(np.asarray(q, dtype=self._npdt))
        wh = int(bool(hessian))
        launch(RK.cubature_element_kernel, dim=self.c,
                  inputs=[self.U, self._q, self.points, self.material, wh, int(bool(project)), self._energy, self._f,
                          self._H], device=self.device)
        self._force.zero_()
        if hessian:
            self._K.zero_()
        launch(RK.cubature_project_kernel, dim=(self.r, self.r if hessian else 1),
                  inputs=[self.U, self.points, self._f, self._H, wh, self.c, self._force, self._K],
                  device=self.device)
        E = float(self._energy.numpy().astype(np.float64).sum())
        f = self._force.numpy().astype(np.float64)
        K = self._K.numpy().astype(np.float64) if hessian else None
        return E, f, K


class ReducedSimulator(StepperBase):
    """Backward Euler in a subspace (see module docstring).

    Args:
        model: the Model the subspace was trained for.
        subspace: a :class:`~warpfem.reduced.Subspace` (basis + cubature), e.g. from
            :func:`~warpfem.reduced.train_subspace` or :func:`~warpfem.reduced.load_subspace`.
        device, precision, dt (s), damping_mass alpha (1/s), damping_stiffness beta (s),
        require_convergence: as for :class:`warpfem.Simulator`.
        integrator: "backward_euler" (default), "bdf2" or "newmark" (reduced Newmark is the classic
            choice of the reduced-model literature), or an instance from :mod:`warpfem.integrators`.
        Newton options (keyword): ``tol``, ``atol``, ``max_iters``, ``max_line_search``, ``armijo``,
            ``project_hessian`` (``cg_tol`` / ``max_cg_iters`` are accepted and unused: the r x r
            system is solved directly).

    Fixed vertices stay where the basis puts them (at rest: fixed rows of U are zero). State
    (``state``, a :class:`~warpfem.solvers.state.State` as for the full-space simulators, with the
    same ``step`` / ``new_state`` / ``time`` / ``load_scale`` / energies and failure handling from
    :class:`~warpfem.solvers.state.StepperBase`): x = z = [q; a] (reduced coordinates and handle
    coordinates), v = z' = [qdot; adot], numpy float64; ``q``, ``qdot``, ``a``, ``adot`` are
    views of it.

    Newton matrix: the r x r matrix is kept across Newton iterations and steps (BFGS-updated,
    evaluated again when it stops contracting; see ``_ReducedPotential``); set
    ``reuse_newton_matrix = False`` for plain Newton (the exact Hessian at every iterate). Both
    converge to the same solution; ``SolveStats.hessian_evaluations`` counts the evaluations.

    Newton loop: the one of every simulator, :func:`~warpfem.solvers.nonlinear.newton_solve`, on the
    step's :class:`_ReducedPotential` (a specialised copy of the loop for r-vectors was measured
    15 % faster per reduced step on the thin cantilever and not kept: one loop to maintain).
    """

    def __init__(self, model, subspace, *, device="cpu", precision="float64", dt=1.0 / 60.0, damping_mass=0.0,
                 damping_stiffness=0.0, require_convergence=False, integrator="backward_euler", **newton_options):
        types = check_simulator_options(precision, dt, damping_mass, damping_stiffness)
        self.integrator = make_integrator(integrator)
        self.options = newton_options_from(newton_options)
        subspace.check(model)
        lifting = subspace.lifting if subspace.lifting is not None and subspace.lifting.size else None
        self.subspace = subspace
        self._setup_options(model, device, precision, types, dt, damping_mass, damping_stiffness, require_convergence)
        U = subspace.U
        self.r = U.shape[1]
        n = self.num_vertices
        cub = subspace.cubature
        # kinematic handles: x = X + U q + L a (a prescribed); the kernels see the basis B = [U | L]
        self.lifting = lifting
        self.p = 0 if lifting is None else lifting.size
        self._B = U if lifting is None else np.hstack([U, lifting.L])
        if lifting is not None:
            lifting.bind(model.rest_positions)
        self.forces = CubatureForces(model, self._B, cub.elements, cub.weights, device=device, precision=precision)
        self._ucols = self.forces.columns(slice(0, self.r)) if self.p else self.forces.columns(slice(None))
        self._work = (np.zeros(self.r), np.zeros(self.r), np.zeros(self.r))  # Newton's g, d, y_try
        # step-to-step data of the step potential (_ReducedPotential), kept on the simulator:
        self.newton_matrix = None  # the kept r x r Newton matrix
        self.matrix_cache = None  # (s, alpha, M_r, C, C_ul, A, s C) without stiffness damping
        self.reuse_newton_matrix = True  # False: the exact Hessian at every Newton iterate (plain Newton)
        self._pot = None  # the step's potential (work arrays kept across steps)
        self.kept_matrix_poor = 0  # > 0: the kept matrix contracted badly at a step start; refresh there
        self._prediction_work = {}
        self.ops = _CoordinateVectors(self.r + self.p, self._equation_of_motion_acceleration)
        # the state (StepperBase): x = z = [q; a], v = z' = [qdot; adot], numpy float64, two in turn;
        # the control's targets: handle group -> coordinates for the end of the next step
        k = self.r + self.p
        self._setup_states(State(np.zeros(k), np.zeros(k)), State(np.zeros(k), np.zeros(k)))
        self.mass_r = self._reduced_mass(U)
        self.mass_ul = U.T @ (self._mass3() @ lifting.L) if lifting is not None else np.zeros((self.r, 0))
        self._mass_B = None  # B^T M B (kinetic energy), made on first use
        self._X = wp.array(model.rest_positions.astype(self._np), dtype=self._vec, device=self.device)
        self._x = wp.zeros(n, dtype=self._vec, device=self.device)
        self._qdev = wp.zeros(self.r + self.p, dtype=self._s, device=self.device)
        self._surface = None
        self.sync_model()

    def _mass3(self):
        import scipy.sparse

        M = self.model.mass
        return M if M.shape[0] == 3 * self.num_vertices else scipy.sparse.kron(M, scipy.sparse.identity(3), format="csr")

    def _reduced_mass(self, U):
        Mr = U.T @ (self._mass3() @ U)
        return 0.5 * (Mr + Mr.T)

    def sync_model(self):
        """Project the model's external forces (gravity + applied) onto the basis: U^T f_ext (call after changes)."""
        f = self.model.external_forces().reshape(-1)
        self.fext_r = self.subspace.U.T @ f
        self._fext_B = self._B.T @ f  # x^T f_ext = X^T f_ext + z^T B^T f_ext
        self._fext_X = float(self.model.rest_positions.reshape(-1) @ f)

    # -- the state: views of ``state`` (z = [q; a], z' = [qdot; adot]) -------------------------------
    @property
    def q(self) -> np.ndarray:
        """Reduced coordinates (r,): a view of the state's buffer (rewritten by later steps)."""
        return self.state.x[:self.r]

    @q.setter
    def q(self, value):
        self.state.x[:self.r] = value

    @property
    def qdot(self) -> np.ndarray:
        """Reduced velocities (r,): a view of the state's buffer."""
        return self.state.v[:self.r]

    @qdot.setter
    def qdot(self, value):
        self.state.v[:self.r] = value

    @property
    def a(self) -> np.ndarray:
        """Handle coordinates (p,), prescribed: a view of the state's buffer."""
        return self.state.x[self.r:]

    @property
    def adot(self) -> np.ndarray:
        """Handle velocities (p,): a view of the state's buffer."""
        return self.state.v[self.r:]

    # -- state ------------------------------------------------------------------------------------
    def _reconstruct(self, X, U, q, out):
        self._qdev.assign(np.asarray(q, dtype=self._np))
        launch(RK.reconstruct_kernel, dim=len(X), inputs=[X, U, self._qdev, out], device=self.device)
        return out

    @property
    def z(self) -> np.ndarray:
        """Coordinates in the kernel basis [U | L]: [q; a] (a copy)."""
        return self.state.x.copy()

    def positions_device(self):
        """x = X + U q (+ L a) as a device array of vec3 (computed on the device only when asked)."""
        return self._reconstruct(self._X, self.forces.U, self.state.x, self._x)

    @property
    def x(self):
        """Full-mesh positions on the device (a reconstruction; prefer :meth:`surface_positions`)."""
        return self.positions_device()

    def positions(self) -> np.ndarray:
        """Full-mesh positions (n, 3), m, float64."""
        return self.positions_device().numpy().astype(np.float64)

    def velocities(self) -> np.ndarray:
        """Full-mesh velocities U qdot (+ L adot) (n, 3), m/s."""
        return (self._B @ self.state.v).reshape(-1, 3)

    def stresses(self, x=None) -> np.ndarray:
        """First Piola-Kirchhoff stress (Pa) of the model's material at every quadrature point of the full
        mesh (Q, 3, 3), at x (default: the reconstructed positions X + U q)."""
        from warpfem.io.vtu import deformation_gradients

        x = self.positions() if x is None else np.asarray(x, dtype=np.float64)
        return np.asarray(self.model.material.pk1(deformation_gradients(self.model, x)), dtype=np.float64)

    # -- kinematic handles --------------------------------------------------------------------------
    def set_targets(self, indices, positions):
        """Prescribe end-of-step positions (m) of handle vertices, like :meth:`warpfem.Simulator.set_targets`.

        The subspace must have been trained with these handles (``handles=`` of
        :func:`~warpfem.reduced.train_subspace`), and ``indices`` must cover whole handles: a handle's
        motion is fitted as an affine map of its rest positions (exact for translations and
        rotations). Handles not targeted before a step stay where they are.
        """
        idx = np.asarray(indices, dtype=np.int64).reshape(-1)
        pos = np.asarray(positions, dtype=np.float64).reshape(len(idx), 3)
        if not np.all(np.isfinite(pos)):
            raise ValueError("target positions must be finite")
        if self.lifting is None:
            raise ValueError("this subspace was trained without kinematic handles; retrain it with the handles "
                             "(train_subspace(..., handles=[(ids, components)]) / `warpfem train` on a scene with [[handle]]s)")
        lookup = dict(zip(idx.tolist(), range(len(idx))))
        covered = set()
        for g, (ids, comps, Q, first) in enumerate(self.lifting.groups):
            hit = [i in lookup for i in ids.tolist()]
            if not any(hit):
                continue
            if not all(hit):
                raise ValueError(f"set_targets must cover whole handles: handle #{g + 1} has {len(ids)} vertices, "
                                 f"{sum(hit)} were given")
            self.control.targets[g] = self.lifting.group_coords(g, pos[[lookup[i] for i in ids.tolist()]])
            covered.update(ids.tolist())
        stray = [i for i in lookup if i not in covered]
        if stray:
            raise ValueError(f"vertices {stray[:5]} are not handle vertices of this subspace")

    def _next_handle_coords(self, a, control):
        a = np.array(a, dtype=np.float64)
        for g, val in control.targets.items():
            a[self.lifting.group_slice(g)] = val
        return a

    def set_render_surface(self, W):
        """Precompute W U and W X for a render surface embedded with skinning matrix W (p x n,
        scipy sparse or a ``warpfem.skinning.Embedding``), so :meth:`surface_positions` costs O(r)
        per surface point and never builds the full mesh."""
        if hasattr(W, "matrix"):
            W = W.matrix()
        n = self.num_vertices
        if W.shape[1] != n:
            raise ValueError(f"skinning matrix has {W.shape[1]} columns, the mesh has {n} vertices")
        B = self._B
        k = B.shape[1]
        WU = np.asarray(W @ B.reshape(n, 3 * k)).reshape(-1, 3 * k)
        WX = np.asarray(W @ self.model.rest_positions)
        p = WX.shape[0]
        self._surface = (wp.array(WX.astype(self._np), dtype=self._vec, device=self.device),
                         _basis_array(WU.reshape(3 * p, k), p, self._vec, self._np, self.device),
                         wp.zeros(p, dtype=self._vec, device=self.device))

    def surface_positions(self) -> np.ndarray:
        """Render-surface positions (p, 3) = W X + (W U) q (needs :meth:`set_render_surface`)."""
        if self._surface is None:
            raise RuntimeError("call set_render_surface(W) first")
        WX, WU, out = self._surface
        return self._reconstruct(WX, WU, self.state.x, out).numpy().astype(np.float64)

    def surface_points(self, embedding) -> np.ndarray:
        """Render-surface points (p, 3) for an embedding (``warpfem.skinning.Embedding``), the hook
        :class:`warpfem.scenes.SceneRun` uses: W B is precomputed on the first call for that
        embedding (B = [U | L]), so no frame reconstructs the full mesh (O(r) per point)."""
        if getattr(self, "_surface_embedding", None) is not embedding:
            self.set_render_surface(embedding)
            self._surface_embedding = embedding
        return self.surface_positions()

    def project(self, x) -> np.ndarray:
        """q = M_r^-1 U^T M (x - X - L a(x)) for full positions x (n, 3) (exact for x in the subspace)."""
        M3 = self._mass3()
        x = np.asarray(x, dtype=np.float64)
        d = (x - self.model.rest_positions).reshape(-1)
        if self.lifting is not None:
            d = d - self.lifting.L @ self.lifting.coords_from_positions(x)
        return np.linalg.solve(self.mass_r, self.subspace.U.T @ (M3 @ d))

    def elastic_energy(self) -> float:
        """V_c(z) (J): the cubature energy of the current state."""
        return self.forces.evaluate(self.state.x)[0]

    def kinetic_energy(self) -> float:
        """1/2 z'^T B^T M B z' (J): the kinetic energy of the full-mesh velocities B z'."""
        if self._mass_B is None:
            MB = self._B.T @ (self._mass3() @ self._B)
            self._mass_B = 0.5 * (MB + MB.T)
        zd = self.state.v
        return 0.5 * float(zd @ (self._mass_B @ zd))

    def _external_work(self, state) -> float:
        """x^T f_ext (J) of x = X + B z (StepperBase's total energy)."""
        return self._fext_X + float(state.x @ self._fext_B)

    # -- public views the step potential (_ReducedPotential) uses ------------------------------------
    @property
    def ucols(self):
        """The cubature's columns of the free coordinates q (the handle columns excluded)."""
        return self._ucols

    @property
    def newton_work(self):
        """Newton's work vectors (g, d, y_try) for r coordinates, kept across steps."""
        return self._work

    @property
    def numpy_dtype(self):
        return self._np

    @property
    def _newton_matrix(self):  # the older name (tests)
        return self.newton_matrix

    # -- the state the integrators advance: z = [q; a], z' = [qdot; adot] (``state``) ---------------------
    def set_state(self, q=None, qdot=None):
        """Set reduced coordinates / velocities (r,); time integrators restart their history.
        Raises ValueError (state untouched) for a wrong shape or NaN/inf."""
        checked = {}
        for name, val in (("q", q), ("qdot", qdot)):
            if val is not None:
                a = np.asarray(val, dtype=np.float64)
                if a.shape != (self.r,) or not np.all(np.isfinite(a)):
                    raise ValueError(f"{name} must be {self.r} finite numbers, got shape {a.shape}")
                checked[name] = a
        for name, a in checked.items():
            setattr(self, name, a)
        self._state_changed()

    def damping_matrices(self, z):
        """Rows r of the reduced Rayleigh damping C = alpha B^T M B + beta B^T K(z) B: (C_rr, C_rl)."""
        r = self.r
        C = self.damping_mass * self.mass_r
        C_ul = self.damping_mass * self.mass_ul
        if self.damping_stiffness > 0:
            Kn = self.forces.evaluate(z, hessian=True, project=True)[2]
            C = C + self.damping_stiffness * Kn[:r, :r]
            C_ul = C_ul + self.damping_stiffness * Kn[:r, r:]
        return C, C_ul

    def _equation_of_motion_acceleration(self, state, out):
        """out = [a_q; 0]: M_r a_q = U^T f(z) + U^T f_ext - (C z')_q (handles start unaccelerated)."""
        r = self.r
        z = state.x
        C, C_ul = self.damping_matrices(z)
        f = self.forces.evaluate(z)[1][:r]
        zdot = state.v
        rhs = f + self._step_control.load_scale * self.fext_r - C @ zdot[:r] - C_ul @ zdot[r:]
        out[:] = 0.0
        out[:r] = np.linalg.solve(self.mass_r, rhs)
        if not np.all(np.isfinite(out)):
            raise SolveFailed("the initial acceleration is not finite; state left unchanged",
                              SolveStats(reason="non-finite initial acceleration"))

    # -- the full step state (StepperBase.state_dict) -------------------------------------------------------
    def _state_parts(self, view=None):
        """The kept Newton matrix ("reduced/newton_matrix/...": it is BFGS-updated and reused from
        step to step) and what decides when it is evaluated again."""
        return [("reduced", _ReducedState(self))]

    def _checked_target(self, view, key, value):
        groups = self.lifting.groups if self.lifting is not None else ()
        if not (0 <= key < len(groups)):
            raise view.error("control/target_keys", f"handle group {key}: this subspace has {len(groups)}")
        sl = self.lifting.group_slice(key)
        if value.size != len(range(self.p)[sl]):
            raise view.error("control/target_values", f"handle group {key} has {len(range(self.p)[sl])} coordinates, "
                             f"got {value.size}")
        return value

    # -- step ---------------------------------------------------------------------------------------
    def add_collider(self, *args, **kw):
        """Not supported: a reduced simulator (x = X + U q) does not handle contact; use :class:`warpfem.Simulator`."""
        raise ValueError("a reduced simulator (x = X + U q) does not handle colliders; use warpfem.Simulator (Newton, any integrator) for contact")

    def _step(self, state_in, state_out, control, dt) -> SolveStats:
        """One reduced step of ``dt`` from ``state_in`` into ``state_out`` with the simulator's integrator
        (Newton with an Armijo line search and a dense r x r solve: :func:`~warpfem.solvers.nonlinear.newton_solve`,
        as the full-space simulators, on the step's :class:`_ReducedPotential`); raises SolveFailed on NaN
        (nothing written). ``control.targets``: handle group -> coordinates at the end of the step
        (:meth:`set_targets`); ``control.load_scale`` scales the external forces."""
        t0 = time.perf_counter()
        r = self.r
        self._step_control = control
        prediction = self.integrator.predict(state_in, dt, self.ops, self._prediction_work)
        zb, zhat, s = prediction
        # handles: a_{n+1} prescribed, so their end-of-step velocity is (a_{n+1} - a_b) / s; the
        # kinetic and damping energies of V = U v + L adot couple through M_ul = U^T M L (and beta K_ul)
        a_in = state_in.x[r:]
        a_next = self._next_handle_coords(a_in, control) if self.p else a_in
        adot = (a_next - zb[r:]) / s
        if self._pot is None:
            self._pot = _ReducedPotential(self)
        pot = self._pot.begin(zb=zb, v_hat=zhat[:r], adot_hat=zhat[r:], adot=adot, s=s, zn=state_in.x,
                              load_scale=control.load_scale)
        v = np.array(state_in.v[:r], dtype=np.float64)
        st = newton_solve(pot, v, self.options)
        st.hessian_evaluations = pot.hessians
        if not st.converged:
            self.newton_matrix = None  # computed along a failed solve: not reused
        self._finish(st, t0, f"reduced step {self.step_count}", finite=bool(np.all(np.isfinite(v))))
        self.integrator.advance(state_in, np.concatenate([v, adot]), prediction, dt, self.ops, state_out)
        state_out.x[r:] = a_next  # exactly the prescribed coordinates
        state_out.time = state_in.time + dt
        return st


class _ReducedState:
    """The reduced simulator's step-to-step data beyond its State: the kept Newton matrix (H, its
    Cholesky factor, A and s it was formed with, K when known), the step-scale cache its A comes
    from, and the count that holds a badly contracting kept matrix back."""

    def __init__(self, sim):
        self.sim = sim

    def state_dict(self) -> dict:
        sim = self.sim
        cache, nm = sim.matrix_cache, sim.newton_matrix
        d = {"kept_matrix_poor": int(sim.kept_matrix_poor),
             "matrix_cache_s": float("nan") if cache is None else float(cache[0]),
             "has_newton_matrix": nm is not None}
        if nm is not None:
            d.update({"newton_matrix/s": float(nm["s"]), "newton_matrix/A": np.array(nm["A"]),
                      "newton_matrix/H": np.array(nm["H"]),
                      "newton_matrix/A_is_cached": cache is not None and nm["A"] is cache[5]})
            for k in ("K", "chol"):
                d[f"newton_matrix/has_{k}"] = nm[k] is not None
                if nm[k] is not None:
                    d[f"newton_matrix/{k}"] = np.array(nm[k])
        return d

    def load_state_dict(self, view):
        sim, r = self.sim, self.sim.r
        poor = view.integer("kept_matrix_poor")
        s_cache = view.number("matrix_cache_s", optional=True)
        nm = None
        if view.flag("has_newton_matrix"):
            mv = view.view("newton_matrix")
            nm = {"s": mv.number("s"), "A": mv.array("A", (r, r), np.float64), "H": mv.array("H", (r, r), np.float64)}
            for k in ("K", "chol"):
                nm[k] = mv.array(k, (r, r), np.float64).copy() if mv.flag(f"has_{k}") else None
            cached = mv.flag("A_is_cached")
            if cached and s_cache is None:
                raise mv.error("A_is_cached", "set without a matrix_cache_s")
        cache = None
        if s_cache is not None and sim.damping_stiffness == 0:  # the same computation as _ReducedPotential.begin
            C, C_ul = sim.damping_matrices(None)
            cache = (s_cache, sim.damping_mass, sim.mass_r, C, C_ul, sim.mass_r + s_cache * C, s_cache * C)
        if nm is not None:
            if cached and cache is not None:
                if not np.array_equal(cache[5], nm["A"]):
                    raise view.error("newton_matrix/A", "differs from this simulator's A = M_r + s C (another "
                                     "damping or mass?)")
                nm["A"] = cache[5]  # the same object: a kept factor stays valid from step to step
            else:
                nm["A"] = nm["A"].copy()
            nm["H"] = nm["H"].copy()
        sim.kept_matrix_poor, sim.matrix_cache, sim.newton_matrix = poor, cache, nm


class _ReducedPotential:
    """The incremental potential of a reduced step, the same terms as the full-space forms
    (:mod:`warpfem.solvers.forms`) projected on the basis B = [U | L] (L: handle lifting):

        inertia    1/2 (v - v_hat)^T M_r (v - v_hat) + v^T M_ul (adot - adot_hat)
        damping    s/2 v^T C_r v + s v^T C_ul adot        (C frozen at the step start)
        elastic    V_c(z_b + s [v; adot])                 (cubature)
        loads      -s v^T U^T f_ext

    over the reduced velocity v (r numbers). Gradient g = A v - b - s f_u(v), A = M_r + s C_r,
    Newton matrix H = A + s^2 K_uu(v).

    Cost per evaluation: F_c = F0_c + s G_u,c v for every cubature point (F0 = I + G (z_b + s [0; adot])
    once per step: the handle terms are constant over the step), one kernel launch (w psi, w P
    per point), E = sum w psi and f_u = -G_u^T vec(w P) on the host. The energy and the gradient at
    a point come from the same launch: the line search's accepted trial point is not evaluated again.

    Newton matrix (modified Newton, Shamanskii, with BFGS updates): H is factored (Cholesky) at
    some iterate and kept, across iterations and across steps, updated after every step by BFGS
    with the secant pair (v_k+1 - v_k, g_k+1 - g_k) (free: both gradients are computed anyway),
    while it keeps contracting: it is evaluated again at the current iterate when the last
    iteration reduced the gradient norm by less than ``refresh_ratio``, when the last line search
    had to shorten the step, when the kept matrix is not positive definite with this step's A and
    s, and for 8 steps at their start after a kept matrix contracted badly on a step's first
    iteration (a thin beam's stiff directions rotate from step to step). The exact Hessian (dP/dF unprojected) is tried
    first, which gives Newton's quadratic convergence; with ``project_hessian`` (default) an
    indefinite exact H falls back to the per-point SPD-projected dP/dF (descent guaranteed). The
    converged solution is the same (the stopping test is on the true gradient); only the path to
    it changes."""

    gradient_test_below = 1e-9  # float64 dense sums of cubature terms resolve no finer energy change
    refresh_ratio = 0.1  # a kept Newton matrix is evaluated again when ||g_k+1|| > ratio ||g_k||

    def __init__(self, sim):
        """Work arrays for every step of ``sim`` (one potential per simulator, :meth:`begin` per step)."""
        self.sim = sim
        self.r = r = sim.r
        self.cf, self.cols = sim.forces, sim.ucols
        self.eps = float(np.finfo(sim.numpy_dtype).eps)
        self._g, self._d, self._y = sim.newton_work
        # w = [dv; v; 1]: the point being evaluated (v), its distance to v_hat, and the constant 1 of
        # the product F = [s G_u | F0] [v; 1] (so the line search writes its trial point into w)
        self._w = np.zeros(2 * r + 1)
        self._w[-1] = 1.0
        self._wdv, self._wv, self._wzb, self._w2 = self._w[:r], self._w[r:2 * r], self._w[r:], self._w[:2 * r]
        # the gradient's terms at the evaluated point: M dv + lin, s C v, -s f_u, -s f_ext
        self._Z = np.zeros((4, r))
        self._Z01 = self._Z[:2].reshape(-1)
        self._Z3a, self._Z3b = self._Z[:3, None, :], self._Z[:3, :, None]
        self._gt = np.zeros(r)  # the gradient at the evaluated point
        self._ones4 = np.ones(4)
        cf = self.cf
        self._run0 = cf.launches[(0, 0)] if cf.zero_copy else None
        self._fch = np.zeros((self.cols.nch, r + 1))  # per-chunk force sums (and P : F0)
        self._fch3, self._fchu = self._fch[:, None, :], self._fch[:, :r]
        self._zfull = np.zeros(r + sim.p + 1)  # [z_b + s [0; adot]] for F0 (and a spare 1)
        self._zfull[-1] = 1.0
        self._F0 = np.zeros(self.cf.all_columns.Gb3.shape[:2])
        self._I9 = self.cf.I9.reshape(self._F0.shape)
        self._by_s = {}  # s -> [s G_u | F0] in chunks (F = [s G_u | F0] [v; 1], s f_u = -[s G_u]^T vec(w P))
        self._blk_key = None
        self._MsC = np.zeros((2 * r, 2 * r))  # blockdiag(M_r, s C_r)
        self._at = np.full(r, np.nan)  # the point of the loaded deformation gradients
        self._bW = np.zeros((2, r))  # [H s_k; y_k] of a BFGS update (y_k stored there by _accepted)
        self._bWT, self._bcW = self._bW.T, np.zeros((2, r))
        self._bc = np.zeros(2)
        self._bc2 = self._bc[:, None]
        self._sk, self._yk = np.zeros(r), self._bW[1]
        self._absbuf = np.zeros(r)
        self._n2 = np.zeros((3, 1, 1))
        self._vprev, self._gprev = np.zeros(r), np.zeros(r)

    def begin(self, *, zb, v_hat, adot_hat, adot, s, zn=None, load_scale=None):
        """Set up the potential of the coming step (prediction z_b, v_hat, the handles' velocity, s;
        z_n the coordinates at its start, default the simulator's; the load scale, default the
        simulator's)."""
        sim, r = self.sim, self.r
        self.opts = sim.options
        self.zb, self.v_hat, self.adot, self.s = zb, v_hat, adot, s = zb, v_hat, adot, float(s)
        if sim.damping_stiffness > 0:  # C = alpha M_r + beta K_r(z_n) changes every step
            C, C_ul = sim.damping_matrices(np.concatenate([sim.q, sim.a]) if zn is None else zn)
            self.A = sim.mass_r + s * C
            sC = s * C
        else:  # C = alpha M_r: the same C and A (the same objects) for every step with this s and alpha,
            # so a kept Newton factor stays valid from step to step
            cache = sim.matrix_cache
            if cache is None or cache[0] != s or cache[1] != sim.damping_mass or cache[2] is not sim.mass_r:
                C, C_ul = sim.damping_matrices(None)
                sim.matrix_cache = cache = (s, sim.damping_mass, sim.mass_r, C, C_ul, sim.mass_r + s * C, s * C)
            C, C_ul, self.A, sC = cache[3], cache[4], cache[5], cache[6]
        self.C = C
        if self._blk_key is not sC or self._blk_M is not sim.mass_r:
            self._MsC[:r, :r] = sim.mass_r
            self._MsC[r:, r:] = sC
            self._blk_key, self._blk_M = sC, sim.mass_r
        self.lin = (sim.mass_ul @ (adot - adot_hat) + s * (C_ul @ adot)) if sim.p else None  # constant part of the gradient
        # F0 = I + G (z_b + s [0; adot]) for every point (the handle terms are constant over the step)
        zf = self._zfull
        zf[:r] = zb[:r]
        if sim.p:
            np.multiply(adot, s, out=zf[r:-1])
            zf[r:-1] += zb[r:]
        cols = self.cols
        np.matmul(self.cf.all_columns.G3, zf[:-1], out=self._F0)
        self._F0 += self._I9
        sc = self._by_s.get(s)
        if sc is None:
            if len(self._by_s) > 4:
                self._by_s.clear()
            Gb3s = cols.Gb3.copy()
            Gb3s[:, :, :-1] *= s
            self._by_s[s] = sc = Gb3s
        self._Gb3s = sc
        self._Gb3s[:, :, -1] = self._F0
        self._zmax_b = float(np.abs(zb[:r]).max())
        self._zmax_a = float(np.abs(zf[r:-1]).max()) if sim.p else 0.0
        self._sfext = sfe = (s * (sim.load_scale if load_scale is None else float(load_scale))) * sim.fext_r
        np.negative(sfe, out=self._Z[3])
        self._sfext_norm = math.sqrt(sfe @ sfe)
        self._fl = np.stack([sfe, self.lin]) if sim.p else sfe  # v . s f_ext (and v . lin) in one product
        self._version = -1
        self._valid = False  # the cached energy / gradient are those of the loaded point
        self._has_prev = False
        self._pair = False
        if sim.kept_matrix_poor > 0:
            sim.kept_matrix_poor -= 1  # try the kept matrix again after a few steps
        self._gn = []  # gradient norms at the accepted iterates of this solve
        self._alpha = 1.0  # last step length tried by the line search
        self._matrix_iterate = -1  # the iterate (index into _gn) where the kept matrix was evaluated in this solve
        self.hessians = 0
        return self

    # -- evaluation -------------------------------------------------------------------------------
    def _load_w(self):
        """Point deformation gradients at the v held in w: F = [s G_u | F0] [v; 1]."""
        cf = self.cf
        cf.set_product(self._Gb3s, self._wzb)
        self._at[:] = self._wv
        self._version = cf.version

    def _eval_w(self):
        """Energy, its magnitude, the gradient (into ``_gt``), its magnitude and norm at the v held
        in w, from one launch: g = M (v - v_hat) + lin + s C v - s f_u(v) - s f_ext."""
        cf, Z = self.cf, self._Z
        np.subtract(self._wv, self.v_hat, out=self._wdv)
        self._load_w()
        if self._run0 is not None:
            self._run0()  # zero-copy: the kernel's outputs are read in place
        else:
            cf.run()
        E = float(_asum(cf.psi, dtype=np.float64))
        np.matmul(self._MsC, self._w2, out=self._Z01)  # [M dv; s C v]
        quad2 = self._w2 @ self._Z01  # dv . M dv + v . s C v
        # s G_u^T vec(w P) = -s f_u by chunks of points (single-threaded BLAS, see _chunk_points),
        # from the same matrix [s G_u | F0] as F (read once from memory per evaluation; the last
        # column's P : F0 is not used)
        np.matmul(cf.P3, self._Gb3s, out=self._fch3)
        _asum(self._fchu, axis=0, out=Z[2])
        if self.lin is not None:
            Z[0] += self.lin
            vw = self._fl @ self._wv
            work, vlin = float(vw[0]), float(vw[1])
        else:
            work, vlin = float(self._sfext @ self._wv), 0.0
        gt = self._gt
        np.matmul(self._ones4, Z, out=gt)  # t0 + t1 - t2 - s f_ext
        n2 = np.matmul(self._Z3a, self._Z3b, out=self._n2).reshape(3)  # |t0|^2, |t1|^2, |t2|^2
        quad = 0.5 * float(quad2) + vlin
        self._valid = True
        self._E = (quad + E - work, abs(quad) + abs(E) + abs(work))
        self._gmag = math.sqrt(n2[0]) + math.sqrt(n2[1]) + math.sqrt(n2[2]) + self._sfext_norm
        self._gnt = math.sqrt(gt @ gt)
        return self._E

    def _evaluate(self, v):
        """:meth:`_eval_w` at v (skipped when v is the point already evaluated)."""
        if self._valid and self._version == self.cf.version and (v == self._at).all():
            return
        self._wv[:] = v
        self._eval_w()

    def _hessian(self, v, project):
        if self._version != self.cf.version or not (v == self._at).all():
            self._wv[:] = v
            self._load_w()
        self._valid = False
        cf = self.cf
        cf.run(hessian=True, project=project)
        self.hessians += 1
        return cf.stiffness(self.cols)

    def coords(self, v):
        return self.zb + self.s * np.concatenate([v, self.adot])

    # -- the problem interface of warpfem.solvers.nonlinear.newton_solve (the reference loop) ------
    def new_vector(self):
        return np.zeros(self.r)

    def vectors(self):
        return self._g, self._d, self._y

    def trial(self, y, alpha, d, out):
        np.multiply(d, alpha, out=out)
        out += y
        self._alpha = alpha

    @staticmethod
    def assign(dst, src):
        dst[:] = src

    def energy(self, v):
        self._evaluate(v)
        return self._E

    def gradient(self, v, g):
        self._evaluate(v)
        g[:] = self._gt
        gn = self._gnt
        if g is self._g:  # the loop's gradient at an accepted iterate (not a side test)
            self._accepted(v, g, gn)
        return self._gmag, gn

    def _accepted(self, v, g, gn):
        """Record an accepted iterate: its gradient norm, and the secant pair of the last step."""
        self._gn.append(gn)
        if self._has_prev:  # the secant pair of the last step, for the BFGS update
            np.subtract(v, self._vprev, out=self._sk)
            np.subtract(g, self._gprev, out=self._yk)
            self._pair = True
        self._vprev[:] = v
        self._gprev[:] = g
        self._has_prev = True

    # -- Newton matrix ----------------------------------------------------------------------------
    def _factor(self, K):
        """Cholesky factor of A + s^2 K (None when not positive definite or not finite), and the matrix."""
        H = self.A + (self.s * self.s) * K
        if not math.isfinite(_asum(H, axis=None)):  # a sum is finite only when every term is
            return None, H
        c, info = _potrf(H, lower=1, clean=1)
        return (c if info == 0 else None), H

    def _refresh(self, v, opts):
        K = self._hessian(v, project=False)
        chol, H = self._factor(K)
        if chol is None and opts.project_hessian:
            K = self._hessian(v, project=True)
            chol, H = self._factor(K)
        self.sim.newton_matrix = nm = dict(K=K, A=self.A, s=self.s, chol=chol, H=H)
        self._matrix_iterate = len(self._gn) - 1
        return nm

    def _want_refresh(self):
        gn = self._gn
        if len(gn) == 1:  # the first iteration of a step: a kept matrix that served badly lately is not tried
            return self.sim.kept_matrix_poor > 0
        if self._matrix_iterate < 0 and len(gn) == 2:  # how the kept matrix did on this step's first iteration
            self.sim.kept_matrix_poor = 8 if gn[1] > self.refresh_ratio * gn[0] else 0
        if self._alpha < 1.0:
            return True  # the line search had to shorten the last step
        return gn[-1] > self.refresh_ratio * gn[-2]

    def solve_newton_system(self, v, g, d, opts):
        nm = self.sim.newton_matrix
        if nm is None or (self._matrix_iterate != len(self._gn) - 1
                          and (not self.sim.reuse_newton_matrix or self._want_refresh())):
            nm = self._refresh(v, opts)
        else:
            if nm["A"] is not self.A or nm["s"] != self.s:  # kept from an earlier step: this step's A and s
                if nm["K"] is None:
                    nm["K"] = (nm["H"] - nm["A"]) / (nm["s"] * nm["s"])
                chol, H = self._factor(nm["K"])
                if chol is None:
                    nm = self._refresh(v, opts)
                else:
                    nm.update(A=self.A, s=self.s, chol=chol, H=H)
            if self._pair and self._matrix_iterate != len(self._gn) - 1:
                self._bfgs(nm)
        self._pair = False
        self._alpha = 1.0
        if nm["chol"] is not None:
            x, _ = _potrs(nm["chol"], g, lower=1)
            np.negative(x, out=d)
            return 0
        try:  # not positive definite (exact Hessian requested): a plain solve, as the full simulators do
            d[:] = np.linalg.solve(nm["H"], -g)
        except np.linalg.LinAlgError:
            d[:] = -g
        return 0

    def _bfgs(self, nm):
        """BFGS update of the kept matrix with the last step's secant pair (sk, yk = g_k+1 - g_k):
        H+ = H - H sk sk^T H / (sk^T H sk) + yk yk^T / (yk^T sk) (Nocedal & Wright, "Numerical
        Optimization", ch. 6). It follows the change of the Hessian between evaluations (a rotating
        thin beam's stiff directions) at O(r^2); skipped unless yk^T sk > 0, so H stays SPD."""
        sk, yk = self._sk, self._yk
        sy = float(sk @ yk)
        if not (sy > 1e-12 * math.sqrt(float(sk @ sk) * float(yk @ yk))) or nm["chol"] is None:
            return
        W, cw = self._bW, self._bc  # W = [H sk; yk] (rows), H+ = H + W^T diag(-1/sHs, 1/sy) W
        Hs = np.matmul(nm["H"], sk, out=W[0])
        sHs = float(sk @ Hs)
        if not sHs > 0.0:
            return
        cw[0], cw[1] = -1.0 / sHs, 1.0 / sy
        H = np.matmul(self._bWT, np.multiply(W, self._bc2, out=self._bcW))
        H += nm["H"]
        c, info = _potrf(H, lower=1, clean=1)
        if info == 0:
            nm.update(H=H, chol=c, K=None)  # K = (H - A) / s^2 when a later step needs it

    def refresh_direction(self) -> bool:
        """After a failed line search: True (try again) when the direction came from a kept matrix
        not evaluated at this iterate; the next solve evaluates it here."""
        if self._matrix_iterate == len(self._gn) - 1:
            return False
        self._alpha = 0.0
        return True

    @staticmethod
    def fallback_direction(g, d):
        d[:] = -g

    def direction_check(self, v, g, d):
        # max |z_b + s [v; adot]| bounded by max |z_b| + |s| max |v| (and the handles' part);
        # negligible when max |d| <= 8 eps (max |v| + max|z| / |s|). The 2-norms bound the maxima
        # (max |v| <= |v|, max |d| >= |d| / sqrt(r)), which settles the test without them unless d is tiny.
        s = abs(self.s)
        gd = float(g @ d)
        vn = math.sqrt(v @ v)
        bound = 8.0 * self.eps * (vn + max(self._zmax_b + s * vn, self._zmax_a) / s)
        if float(d @ d) > self.r * bound * bound:
            return gd, False
        buf = self._absbuf
        vmax = float(_amax(np.abs(v, out=buf)))
        zmax = max(self._zmax_b + s * vmax, self._zmax_a)
        scale = vmax + zmax / s
        return gd, bool(float(_amax(np.abs(d, out=buf))) <= 8.0 * self.eps * scale)


class _CoordinateVectors:
    """The integrators' vector algebra (``warpfem.integrators.VectorOps``) on numpy coordinate
    vectors z = [q; a] of a reduced simulator."""

    def __init__(self, size, acceleration):
        self.size, self._acceleration = int(size), acceleration

    def new_vector(self):
        return np.zeros(self.size)

    @staticmethod
    def lincomb(a, x, b, y, out):
        out[:] = a * x + b * y

    @staticmethod
    def copy(dst, src):
        dst[:] = src

    @staticmethod
    def clone(a):
        """A copy of a coordinate vector; anything else (a step size) as it is."""
        return a.copy() if isinstance(a, np.ndarray) else a

    def acceleration(self, state, out):
        self._acceleration(state, out)
