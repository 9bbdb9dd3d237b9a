"""Stiffness warping: corotational linear FEM with linearly implicit backward Euler (Müller, Dorsey,
McMillan, Jagnow & Cutler 2002, "Stable real-time deformations"; OpenTissue's FEM module).

The fast, robust integrator of game and surgical-simulation engines (OpenTissue; Mueller, Dorsey,
McMillan, Jagnow, Cutler 2002, "Stable real-time deformations"). Each tet keeps its rest linear
stiffness K_e (from the material's Lame mu_lame, lam_lame); every step the element rotation R_e
is estimated and the stiffness is "warped" into the current frame:

    f_e(x) = -R_e K_e (R_e^T x - X)  =>  f = -(K' x + f0'),
    K' = sum_e R_e K_e R_e^T,   f0' = -sum_e R_e K_e X.

Derivation of the step (Rayleigh damping C = alpha M + beta K'). Backward Euler,

    M (v+ - v) = h (f_ext - K' x+ - f0' - C v+),   x+ = x + h v+,

with K', f0', C frozen at the start of the step (the linearly implicit part: R_e is not
differentiated). Substituting x+ = x + h v+ and v+ = v + dv:

    M dv = h (f_ext - K' x - f0' - h K' (v + dv) - C (v + dv))
    (M + h C + h^2 K') dv = h (f_ext - K' x - f0' - C v - h K' v),
    v+ = v + dv,   x+ = x + h v+.

One PCG solve per step (no Newton loop, no line search). Fixed components are prescribed: dv is
set there so that v+ equals the prescribed velocity (0, or (target - x)/h for ``set_targets``),
the known columns are moved to the right-hand side and the masked product skips fixed rows and
columns (OpenTissue's "skip the fixed columns"), so fixing and releasing vertices between steps
costs nothing and never touches the sparsity pattern.

With every R_e = I (``rotation="identity"``) this is exactly linear elasticity integrated by
backward Euler (the linear system is the one Newton solves in one iteration). With R_e from the
polar decomposition it approximates the corotated material: same small-strain response, exactly
rotation invariant, but the missing dR/dx terms make it a different (non-conservative) model at
large strain.
"""

from __future__ import annotations

import time

import numpy as np
import warp as wp

from warpfem.kernels import linalg as LK
from warpfem.kernels import warping as WK
from warpfem.kernels.generic import COUNTERS, launch
from warpfem.kernels.structs import warped_tets
from warpfem.integrators import make_integrator
from warpfem.solvers.nonlinear import SolveFailed, SolveStats
from warpfem.solvers.linear import make_linear_solver
from warpfem.solvers.linear.auto import simulator_options
from warpfem.solvers.state import SimulatorBase, check_simulator_options, check_solve
from warpfem.solvers.sparse import BlockPattern

__all__ = ["StiffnessWarpingSimulator", "ROTATIONS", "tet_linear_stiffness_blocks"]


#: rotation estimators: name -> kernel int
ROTATIONS = {"identity": WK.ROTATION_IDENTITY, "polar": WK.ROTATION_POLAR, "qr": WK.ROTATION_QR}


def tet_linear_stiffness_blocks(dNdX: np.ndarray, volumes: np.ndarray, mu: float, lam: float) -> np.ndarray:
    """Rest linear stiffness of each tet as 3x3 blocks, (m, 4, 4, 3, 3), N/m (float64).

    For psi = mu eps:eps + lam/2 tr(eps)^2 and shape gradients g_a (1/m):
    K_ab = V (mu (g_a . g_b) I + mu g_b g_a^T + lam g_a g_b^T), so K_ba = K_ab^T.
    """
    g = np.asarray(dNdX, dtype=np.float64).reshape(-1, 4, 3)
    V = np.asarray(volumes, dtype=np.float64)
    gg = np.einsum("eai,ebi->eab", g, g)
    K = mu * gg[..., None, None] * np.eye(3)[None, None, None]
    K += mu * np.einsum("ebi,eaj->eabij", g, g)
    K += lam * np.einsum("eai,ebj->eabij", g, g)
    return K * V[:, None, None, None, None]


class StiffnessWarpingSimulator(SimulatorBase):
    """Corotational linear FEM (stiffness warping) with linearly implicit backward Euler.

    Same state API as :class:`warpfem.Simulator` (``step``, ``positions``, ``velocities``,
    ``set_positions``, ``set_velocities``, ``fix``, ``release``, ``set_targets``, energies).
    Tet4 meshes only.

    Args:
        model: the :class:`~warpfem.model.Model` (its material's Young's modulus and Poisson ratio
            give the linear stiffness, via ``mu_lame``/``lam_lame``; density, gravity, applied
            forces, fixed components and mass matrix are used as in the Newton simulator).
        device: Warp device ("cpu", "cuda:0", ...).
        precision: "float32" or "float64".
        dt: time step h (s).
        rotation: "polar" (R = U V^T of the signed SVD of F; exact rotation invariance, inverted
            elements get a proper rotation), "qr" (Gram-Schmidt on the columns of F, OpenTissue's
            choice: cheaper, depends on the local vertex order) or "identity" (R = I: plain linear
            FEM, for tests and comparisons).
        cg_tol: relative residual of the one PCG solve per step.
        max_cg_iters: cap on PCG iterations per step.
        damping_mass, damping_stiffness: Rayleigh alpha (1/s) and beta (s); C = alpha M + beta K'.
        require_convergence: raise :class:`SolveFailed` (state untouched) when PCG does not reach
            ``cg_tol``; otherwise a warning. NaN/inf always raises and leaves the state untouched.
        integrator: the time scheme, as for :class:`warpfem.Simulator`: "backward_euler" (default),
            "bdf2" or "newmark" (or an instance from :mod:`warpfem.integrators`); each step is one
            Newton iteration of that scheme's incremental potential with the warped linear model.
        linear_solver, linear_solver_options: the solver of the step's linear system ("auto",
            "pcg", "direct", "amg", "multigrid"; docs/linear_solvers.md) and its constructor options.
    """

    def __init__(self, model, *, device="cpu", precision="float64", dt=1.0 / 60.0, rotation="polar", cg_tol=1e-6,
                 max_cg_iters=2000, damping_mass=0.0, damping_stiffness=0.0, require_convergence=False,
                 integrator="backward_euler", linear_solver="auto", linear_solver_options=None):
        types = check_simulator_options(precision, dt, damping_mass, damping_stiffness)
        self.integrator = make_integrator(integrator)
        if rotation not in ROTATIONS:
            raise ValueError(f"rotation must be one of {sorted(ROTATIONS)}, got {rotation!r}")
        if not (np.isfinite(cg_tol) and 0.0 < cg_tol < 1.0):
            raise ValueError(f"cg_tol must be in (0, 1), got {cg_tol!r}")
        if int(max_cg_iters) != max_cg_iters or max_cg_iters < 1:
            raise ValueError(f"max_cg_iters must be a positive integer, got {max_cg_iters!r}")
        if getattr(model, "num_bodies", 1) > 1:
            raise ValueError(f"stiffness warping simulates one body; the model has {model.num_bodies} (use warpfem.Simulator)")
        qd = model.quadrature
        from warpfem.mesh.element_types import get_element

        if not get_element(qd.element_type).is_linear_tet:  # one point per element, gradients from Dm^-1
            raise ValueError(f"StiffnessWarpingSimulator supports tet4 meshes only; the model's mesh has "
                             f"element_type {qd.element_type!r} (use warpfem.Simulator for other elements)")
        mat = model.material
        for attr in ("mu_lame", "lam_lame"):
            if not hasattr(mat, attr):
                raise TypeError(f"model.material must be a warpfem material with {attr!r}, got {type(mat).__name__}")

        self.rotation = rotation
        self.cg_tol = float(cg_tol)
        self.max_cg_iters = int(max_cg_iters)
        self._setup_base(model, device, precision, types, dt, damping_mass, damping_stiffness, require_convergence)
        n = self.num_vertices
        self.num_elements = m = qd.num_elements

        dev = self.device
        Ke = tet_linear_stiffness_blocks(qd.qp_dNdX, qd.qp_weight, mat.mu_lame, mat.lam_lame)
        # the kernels' fixed data as one struct (kernels.structs.WarpedTets), built once
        self._tets = warped_tets(self._s, wp.array(model.rest_positions.astype(self._np), dtype=self._vec, device=dev),
                                 wp.array(qd.elements, dtype=wp.int32, device=dev),
                                 wp.array(qd.qp_dNdX.astype(self._np), dtype=self._vec, device=dev),
                                 wp.array(Ke.reshape(-1, 3, 3).astype(self._np), dtype=self._mat, device=dev))
        self._R = wp.zeros(m, dtype=self._mat, device=dev)
        self._energy_e = wp.zeros(m, dtype=self._s, device=dev)

        self._pattern = BlockPattern(qd.elements, 4, n, device=dev, block_type=self._mat)
        self._mass_values = self._pattern.values_from_scalar_matrix(model.mass)
        self._k_values = self._pattern.new_values()  # K'
        self._a_values = self._pattern.new_values()  # M + h C + h^2 K'
        self._pcg = make_linear_solver(linear_solver, self._pattern, vec_type=self._vec, scalar=self._s,
                                       positions=model.rest_positions, **simulator_options(linear_solver, linear_solver_options))

        self._f0, self._fel, self._rhs, self._w, self._dv, self._tmp, self._vnext, self._pv = (
            self._vec_array() for _ in range(8))
        self._prediction_work = {}

    # -- model changes (no pattern rebuild) -----------------------------------------------------------
    def sync_model(self):
        """Upload the model's fixed mask and external forces (call after changing them on the model; in place)."""
        mask, fext = (~self.model.fixed).astype(self._np), self.model.external_forces().astype(self._np)
        if self._mask is None:
            self._mask, self._fext = self._vec_array(mask), self._vec_array(fext)
        else:
            self._mask.assign(mask)
            self._fext.assign(fext)

    # -- stages ------------------------------------------------------------------------------------
    def _launch(self, kernel, dim, inputs):
        launch(kernel, dim, inputs, self.device)

    def _rotations(self, x):
        self._launch(WK.element_rotation_kernel, self.num_elements,
                     [x, self._tets, ROTATIONS[self.rotation], self._R])

    def _assemble(self, x, *, matrix: bool, force_scale: float = 1.0):
        """R_e at x, then K' (if ``matrix``), f0' and the elastic force force_scale * f_el."""
        self._rotations(x)
        if matrix:
            self._k_values.zero_()
        self._f0.zero_()
        self._fel.zero_()
        self._launch(WK.warped_assembly_kernel, self.num_elements,
                     [x, self._tets, self._R, self._s(force_scale), int(matrix), self._pattern.block_index,
                      self._k_values, self._f0, self._fel])

    def _bsr_mv(self, values, x, alpha, y):
        pt = self._pattern
        self._launch(LK.bsr_mv_kernel, pt.num_rows, [pt.offsets, pt.columns, values, x, self._s(alpha), y])

    # -- helpers (analysis, tests) -----------------------------------------------------------------
    def rotations(self, x=None) -> np.ndarray:
        """Element rotations R_e (m, 3, 3) estimated at x (default: current positions)."""
        self._rotations(self.x if x is None else self._vec_array(x))
        return self._R.numpy().astype(np.float64)

    def elastic_forces(self, x=None) -> np.ndarray:
        """Warped elastic force -(K' x + f0') (N) at x (default: current positions), (n, 3)."""
        self._assemble(self.x if x is None else self._vec_array(x), matrix=False)
        return self._fel.numpy().astype(np.float64)

    def force_offset(self, x=None) -> np.ndarray:
        """f0' = -sum_e R_e K_e X (N) with the rotations at x, (n, 3) (the force offset of "Stable real-time deformations")."""
        self._assemble(self.x if x is None else self._vec_array(x), matrix=False)
        return self._f0.numpy().astype(np.float64)

    def stiffness_matrix(self, x=None):
        """Warped stiffness K' = sum_e R_e K_e R_e^T (N/m) with the rotations at x, scipy CSR (3n x 3n)."""
        self._assemble(self.x if x is None else self._vec_array(x), matrix=True)
        return self._pattern.to_scipy(self._k_values)

    def mass_matrix(self):
        """The (3n x 3n) mass matrix as scipy CSR."""
        return self._pattern.to_scipy(self._mass_values)

    def elastic_energy(self, x=None) -> float:
        """Corotational energy sum_e 1/2 u_e^T K_e u_e, u_e = R_e^T x - X (J), rotations taken at x.

        Zero for any rigid motion; the warped force is not exactly its gradient (dR/dx is ignored)."""
        xa = self.x if x is None else self._vec_array(x)
        self._rotations(xa)
        self._launch(WK.warped_energy_kernel, self.num_elements, [xa, self._tets, self._R, self._energy_e])
        return float(self._energy_e.numpy().astype(np.float64).sum())

    # -- time stepping ------------------------------------------------------------------------------
    def _equation_of_motion_acceleration(self, state, out):
        """out = a with M a = f_w(x) + f_ext - C v on the free components (0 on fixed ones), f_w the
        warped force and C = alpha M + beta K' at ``state`` (Newmark's a_0)."""
        n, s = self.num_vertices, self._s
        b = self.damping_stiffness
        self._assemble(state.x, matrix=b != 0.0, force_scale=1.0)
        rhs = self._tmp
        launch(LK.lincomb_kernel, n, [s(self._step_control.load_scale), self._fext, s(1.0), self._fel, rhs], self.device)
        if self.damping_mass != 0.0:
            self._bsr_mv(self._mass_values, state.v, -self.damping_mass, rhs)
        if b != 0.0:
            self._bsr_mv(self._k_values, state.v, -b, rhs)
        launch(LK.mask_kernel, n, [self._mask, rhs], self.device)
        res = self._pcg.solve(self._mass_values, self._mask, rhs, out, tol=1e-12, maxiter=max(self.max_cg_iters, 100))
        if not np.isfinite(res.residual):
            raise SolveFailed("the initial acceleration M a = f + f_ext - C v is not finite; state left unchanged",
                              SolveStats(reason="non-finite initial acceleration"))

    def add_collider(self, *args, **kw):
        """Not supported: stiffness warping (a linearised step with no line search) does not handle contact; use :class:`warpfem.Simulator`."""
        raise ValueError("stiffness warping (a linearised step with no line search) does not handle colliders; use warpfem.Simulator (Newton, any integrator) for contact")

    def _step(self, state_in, state_out, control, dt) -> SolveStats:
        """One linearly implicit step of ``dt`` (one PCG solve) with the simulator's
        integrator: one Newton iteration, from v_n, of the integrator's incremental potential with
        the warped linear model frozen at the start of the step.

        Returns :class:`~warpfem.SolveStats` (``newton_iterations`` = 1, ``cg_iterations``,
        ``residual`` = the PCG relative residual). On NaN/inf (or PCG non-convergence with
        ``require_convergence``) raises :class:`SolveFailed` and leaves the state as it was.
        """
        t0 = time.perf_counter()
        launches0 = COUNTERS["launches"]
        self._step_control = control
        a, b = self.damping_mass, self.damping_stiffness
        n, nnz = self.num_vertices, self._pattern.nnz
        s = self._s
        x, v = state_in.x, state_in.v
        prediction = self.integrator.predict(state_in, dt, self.ops, self._prediction_work)
        xb, vh, c = prediction
        # K', f0' and c * f_el = -c (K' x_n + f0') at the start of the step
        self._assemble(x, matrix=True, force_scale=c)
        # A = (1 + c alpha) M + c (beta + c) K'
        self._launch(LK.scale_copy_kernel, nnz, [self._mass_values, s(1.0 + c * a), self._a_values])
        self._launch(LK.add_scaled_kernel, nnz, [self._k_values, s(c * (b + c)), self._a_values])
        # rhs = -grad E(v_n) = c f_ext + c f_el(x_n) - c alpha M v_n - c (beta + c) K' v_n
        #       - c K' (x_b - x_n) + M (v_hat - v_n)
        rhs = self._rhs
        self._launch(LK.lincomb_kernel, n, [s(c * control.load_scale), self._fext, s(1.0), self._fel, rhs])
        if a != 0.0:
            self._bsr_mv(self._mass_values, v, -c * a, rhs)
        self._bsr_mv(self._k_values, v, -c * (b + c), rhs)
        if xb is not x:
            self._launch(LK.lincomb_kernel, n, [s(1.0), xb, s(-1.0), x, self._tmp])
            self._bsr_mv(self._k_values, self._tmp, -c, rhs)
        if vh is not v:
            self._launch(LK.lincomb_kernel, n, [s(1.0), vh, s(-1.0), v, self._tmp])
            self._bsr_mv(self._mass_values, self._tmp, 1.0, rhs)
        # prescribed components: w = (I - P)(v_prescribed - v), moved to the right-hand side
        pv = self._prescribed_velocity(state_in, xb, c, control, self._pv)
        self._launch(LK.lincomb_kernel, n, [s(1.0), pv, s(-1.0), v, self._tmp])
        self._launch(LK.select_kernel, n, [self._mask, self._zero, self._tmp, self._w])
        self._bsr_mv(self._a_values, self._w, -1.0, rhs)
        self._launch(LK.mask_kernel, n, [self._mask, rhs])
        res = self._pcg.solve(self._a_values, self._mask, rhs, self._dv, tol=self.cg_tol, maxiter=self.max_cg_iters)
        # dv = free solution + prescribed part; v+ = v + dv; x+ = x_b + c v+ (the integrator)
        self._launch(LK.axpy_kernel, n, [s(1.0), self._w, self._dv])
        v_next = self._vnext
        self._launch(LK.lincomb_kernel, n, [s(1.0), v, s(1.0), self._dv, v_next])
        vv = self._pcg.dot(v_next, v_next)
        stats = SolveStats(converged=bool(res.converged), newton_iterations=1, cg_iterations=res.iterations,
                           residual=res.residual, linear_iterations=res.iterations, host_syncs=res.host_syncs)
        stats.reason = "linear solve converged" if res.converged else f"PCG stopped at relative residual {res.residual:.2e}"
        stats.seconds = time.perf_counter() - t0
        stats.launches = COUNTERS["launches"] - launches0
        if not np.isfinite(vv) or not np.isfinite(res.residual):
            stats.converged, stats.reason = False, "non-finite velocity"
        check_solve(stats, f"step {self.step_count}", require_convergence=self.require_convergence,
                    finite=bool(np.isfinite(vv) and np.isfinite(res.residual)), stacklevel=4)
        self.integrator.advance(state_in, v_next, prediction, dt, self.ops, state_out)
        state_out.time = state_in.time + dt
        return stats
