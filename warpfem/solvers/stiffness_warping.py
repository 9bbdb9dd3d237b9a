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

This is one Newton iteration, from v_n, of the step's incremental potential with the elastic term
replaced by the warped linear model frozen at x_n (:class:`WarpedElasticForm`, a quadratic in x):

    E(v) = 1/2 |v - v_hat|_M^2 + s/2 v^T C v + E_w(x_b + s v) - s v^T f_ext,
    E_w(x) = 1/2 (x - x_n)^T K' (x - x_n) - f_w(x_n)^T (x - x_n),   f_w(x_n) = -(K' x_n + f0'),

whose Hessian is the matrix above (M + s C + s^2 K', s = h for backward Euler) and whose gradient
at v_n is minus the right-hand side. The step runs through the one Newton loop of every simulator
(:func:`warpfem.solvers.nonlinear.newton_solve`, ``max_iters = 1``): one linear solve, the full
step accepted by the line search (a conjugate-gradient iterate of a quadratic always decreases it),
the convergence of the step being that of its linear solve. Fixed components are prescribed: the
Newton loop starts at the prescribed velocity there (0, or (target - x)/h for ``set_targets``) and
the masked Newton systems skip fixed rows and columns (OpenTissue's "skip the fixed columns"), so
fixing and releasing vertices between steps costs nothing and never touches the sparsity pattern.

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

from warpfem.kernels import fem as FK
from warpfem.kernels import linalg as LK
from warpfem.kernels import warping as WK
from warpfem.kernels.generic import COUNTERS, launch
from warpfem.kernels.structs import warped_tets
from warpfem.integrators import make_integrator
from warpfem.solvers.forms import DampingForm, Form, IncrementalPotential, InertiaForm, LoadForm, Workspace
from warpfem.solvers.nonlinear import NewtonOptions, SolveStats, newton_solve
from warpfem.solvers.sparse import PatternView
from warpfem.solvers.state import SimulatorBase, check_simulator_options
from warpfem.transfer import read, to_device

__all__ = ["StiffnessWarpingSimulator", "WarpedElasticForm", "ROTATIONS", "tet_linear_stiffness_blocks"]


#: rotation estimators: name -> kernel int
ROTATIONS = {"identity": WK.ROTATION_IDENTITY, "polar": WK.ROTATION_POLAR, "qr": WK.ROTATION_QR}
#: forces and stiffness blocks per tet into slots, then gathered per vertex and per block in a fixed
#: order (bit-identical whatever the thread count; split across CPU threads); False: added with
#: atomics (the reference of tests, never split)
GATHER = True


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


class WarpedElasticForm(Form):
    """The warped linear elasticity of a step, a quadratic in the positions x frozen at the step's
    start x_n (the rotations R_e, hence K' and f0', are those of x_n):

        E_w(x) = 1/2 (x - x_n)^T K' (x - x_n) - f_w^T (x - x_n),   f_w = -(K' x_n + f0'),

    gradient K' (x - x_n) - f_w = K' x + f0' (minus the warped force, R_e not differentiated),
    Hessian K'. ``stiffness`` returns K''s block values (a callable: they follow the pattern),
    ``force`` is the device array of f_w; :meth:`set_linearisation` names x_n for the step."""

    name = "elastic"
    variable = "x"
    order = 0
    joint = True  # a quadratic: its gradient is measured with the other quadratic terms

    def __init__(self, ops, pattern, stiffness, force):
        self.ops, self.pattern, self.stiffness, self.force = ops, pattern, stiffness, force
        self.x0 = None
        self._dx = ops.new_vector()

    def set_linearisation(self, x0):
        """The positions x_n the quadratic is written about (the state's: not copied, not written)."""
        self.x0 = x0

    def _diff_mv(self, x, scale, g, acc, gradient, energy):
        pt, S = self.pattern, self.ops.scalar
        launch(LK.bsr_diff_mv_kernel, pt.num_rows, [pt.offsets, pt.columns, self.stiffness(), x, self.x0, S(scale), g,
                                                    acc, self.acc_slot, gradient, energy], self.ops.device)

    def energy(self, y, x, acc):
        self._diff_mv(x, 1.0, self._dx, acc, 0, 1)  # 1/2 (x - x_n)^T K' (x - x_n)
        self.ops.lincomb(1.0, x, -1.0, self.x0, self._dx)
        launch(LK.dot_slot_kernel, self.ops.n, [self._dx, self.force, wp.float64(-1.0), acc, self.acc_slot],
               self.ops.device)

    def gradient(self, y, x, scale, g, acc):
        self._diff_mv(x, scale, g, acc, 1, 0)
        launch(LK.axpy_kernel, self.ops.n, [self.ops.scalar(-scale), self.force, g], self.ops.device)

    def hessian(self, y, x, scale, values):
        launch(LK.add_scaled_kernel, self.pattern.nnz, [self.stiffness(), self.ops.scalar(scale), values],
               self.ops.device)


class _OneSolvePotential(IncrementalPotential):
    """The step's potential, keeping the result of its last linear solve (``linear``): a step of
    stiffness warping converges when its one linear solve does."""

    linear = None

    def newton_step(self, *args, **kw):
        out = super().newton_step(*args, **kw)
        self.linear = out[0]
        return out

    def solve_newton_system(self, *args, **kw):
        self.linear = super().solve_newton_system(*args, **kw)
        return self.linear


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
        cg_tol: relative residual of the one linear solve per step.
        max_cg_iters: cap on PCG iterations per step.
        damping_mass, damping_stiffness: Rayleigh alpha (1/s) and beta (s); C = alpha M + beta K'.
        require_convergence: raise :class:`SolveFailed` (state untouched) when the linear solve does not reach
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
        # the step is one Newton iteration (one linear solve) of a quadratic potential
        self.options = NewtonOptions(max_iters=1, cg_tol=float(cg_tol), max_cg_iters=int(max_cg_iters))
        self._setup_base(model, device, precision, types, dt, damping_mass, damping_stiffness, require_convergence)
        self.num_elements = m = qd.num_elements

        dev = self.device
        Ke = tet_linear_stiffness_blocks(qd.qp_dNdX, qd.qp_weight, mat.mu_lame, mat.lam_lame)
        # the kernels' fixed data as one struct (kernels.structs.WarpedTets), built once
        self._tets = warped_tets(self._s, to_device(model.rest_positions.astype(self._np), self._vec, dev),
                                 to_device(qd.elements, wp.int32, dev),
                                 to_device(qd.qp_dNdX.astype(self._np), self._vec, dev),
                                 to_device(Ke.reshape(-1, 3, 3).astype(self._np), self._mat, dev))
        self._R = wp.zeros(m, dtype=self._mat, device=dev)
        self._energy_e = wp.zeros(m, dtype=self._s, device=dev)

        self._setup_system(qd.elements, 4, linear_solver, linear_solver_options)
        system, ops = self.system, self.ops
        system.new_values("stiffness")  # K'; the Newton matrix M + s C + s^2 K' is "hessian"
        self._f0, self._fel, self._pv, self._y = (self._vec_array() for _ in range(4))
        self._prediction_work = {}
        # the step's incremental potential: the forms of Simulator with the warped quadratic as elasticity
        pattern = PatternView(system)
        self._inertia = InertiaForm(ops, pattern, lambda: system.values["mass"])
        self._elastic = WarpedElasticForm(ops, pattern, lambda: system.values["stiffness"], self._fel)
        self._load = LoadForm(ops, self._fext, self._fext_norm)
        forms = [self._inertia]
        if self.damping_mass != 0.0 or self.damping_stiffness != 0.0:
            forms.append(DampingForm(ops, pattern, lambda: system.values["mass"], self.damping_mass,
                                     lambda: system.values["stiffness"], self.damping_stiffness))
        forms += [self._elastic, self._load]
        self._work = Workspace(ops)
        self._potential = _OneSolvePotential(ops, forms, system=system, mask=self._mask,
                                             linear_solve=lambda *a, **kw: self._linear_solve(*a, **kw), work=self._work)

    @property
    def cg_tol(self) -> float:
        """Relative residual of the one linear solve per step."""
        return self.options.cg_tol

    @cg_tol.setter
    def cg_tol(self, value):
        self.options.cg_tol = float(value)

    @property
    def max_cg_iters(self) -> int:
        """Cap on the iterations of the one linear solve per step."""
        return self.options.max_cg_iters

    @max_cg_iters.setter
    def max_cg_iters(self, value):
        self.options.max_cg_iters = int(value)

    @property
    def _k_values(self):
        return self.system.values["stiffness"]

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
        bi = self._pattern.block_index
        head = [x, self._tets, self._R, self._s(force_scale), int(matrix), bi, self._k_values, self._f0, self._fel]
        if not GATHER:
            self._launch(WK.warped_assembly_kernel, self.num_elements, head + [0, self._f0, self._fel, self._R])
            return
        maps = self._gather_maps(matrix)
        fo, fe, f0s, fels = maps["force"]
        blocks = maps.get("blocks") if matrix else None
        self._launch(WK.warped_assembly_kernel, self.num_elements,
                     head + [1, f0s, fels, self._R if blocks is None else blocks[2]])
        n = fo.shape[0] - 1
        none = FK.no_rows(self._fel.device)
        self._launch(FK.gather_force_kernel, n, [fo, fe, f0s, self._f0, self._f0, 0, none, 0])
        self._launch(FK.gather_force_kernel, n, [fo, fe, fels, self._fel, self._fel, 0, none, 0])
        if blocks is not None:
            self._launch(FK.gather_blocks_kernel, blocks[0].shape[0] - 1, [*blocks, self._k_values])

    def _gather_maps(self, matrix):
        """The gather maps (``kernels.fem.element_slot_maps``, one point per tet) and slot buffers:
        "force" (offsets, entries, f0 slots, force slots), built once; "blocks" (offsets, entries,
        block slots), built on first use per pattern."""
        maps = self.__dict__.setdefault("_maps", {})
        dev, m = self.device, self.num_elements
        elements = np.asarray(self.model.quadrature.elements, dtype=np.int64).reshape(-1)
        if "force" not in maps:
            fo, fe = FK.element_slot_maps(np.arange(m), elements, 4, num_vertices=self.ops.n)
            maps["force"] = (to_device(fo, wp.int32, dev), to_device(fe, wp.int32, dev),
                             wp.zeros(4 * m, dtype=self._vec, device=dev), wp.zeros(4 * m, dtype=self._vec, device=dev))
        bi = self._pattern.block_index
        key = (id(bi), int(self._pattern.nnz))
        if matrix and maps.get("blocks_of") != key:
            _, _, bo, be = FK.element_slot_maps(np.arange(m), elements, 4, bi.numpy(), num_vertices=self.ops.n,
                                                nnz=self._pattern.nnz)
            maps["blocks"] = (to_device(bo, wp.int32, dev), to_device(be, wp.int32, dev),
                              wp.zeros(10 * m, dtype=self._mat, device=dev))
            maps["blocks_of"] = key
        return maps

    # -- helpers (analysis, tests) -----------------------------------------------------------------
    def rotations(self, x=None) -> np.ndarray:
        """Element rotations R_e (m, 3, 3) estimated at x (default: current positions)."""
        self._rotations(self.x if x is None else self._vec_array(x))
        return read(self._R).astype(np.float64)

    def stresses(self, x=None) -> np.ndarray:
        """The corotational linear first Piola-Kirchhoff stress P = R (2 mu e + lam tr(e) I), e = sym(R^T F)
        - I (Pa), with the element rotations R at x (default: current positions), at every quadrature
        point (Q, 3, 3)."""
        from warpfem.io.vtu import deformation_gradients

        x = self.positions() if x is None else np.asarray(x, dtype=np.float64)
        mat, qd = self.model.material, self.model.quadrature
        F = deformation_gradients(self.model, x)
        R = self.rotations(x)[np.asarray(qd.qp_element, dtype=np.int64)]
        G = np.einsum("qji,qjk->qik", R, F) - np.eye(3)  # R^T F - I
        e = 0.5 * (G + np.swapaxes(G, 1, 2))
        s = 2.0 * mat.mu_lame * e + mat.lam_lame * np.trace(e, axis1=1, axis2=2)[:, None, None] * np.eye(3)
        return R @ s

    def elastic_forces(self, x=None) -> np.ndarray:
        """Warped elastic force -(K' x + f0') (N) at x (default: current positions), (n, 3)."""
        self._assemble(self.x if x is None else self._vec_array(x), matrix=False)
        return read(self._fel).astype(np.float64)

    def force_offset(self, x=None) -> np.ndarray:
        """f0' = -sum_e R_e K_e X (N) with the rotations at x, (n, 3) (the force offset of "Stable real-time deformations")."""
        self._assemble(self.x if x is None else self._vec_array(x), matrix=False)
        return read(self._f0).astype(np.float64)

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
        return float(read(self._energy_e).astype(np.float64).sum())

    # -- time stepping ------------------------------------------------------------------------------
    def _elastic_force_for_acceleration(self, x, out):
        """out := f_w(x), the warped force with the rotations at x, and K' there when stiffness
        damping needs it (SimulatorBase's equation-of-motion acceleration, Newmark's a_0)."""
        self._assemble(x, matrix=self.damping_stiffness != 0.0)
        wp.copy(out, self._fel)
        return self._k_values

    def add_collider(self, *args, **kw):
        """Not supported: stiffness warping (a linearised step) does not handle contact; use :class:`warpfem.Simulator`."""
        raise ValueError("stiffness warping (a linearised step) does not handle colliders; use warpfem.Simulator (Newton, any integrator) for contact")

    def _step(self, state_in, state_out, control, dt) -> SolveStats:
        """One linearly implicit step of ``dt`` with the simulator's integrator: one Newton
        iteration, from v_n, of the integrator's incremental potential with the warped linear model
        frozen at the start of the step, through the one Newton loop (``newton_solve``).

        Returns :class:`~warpfem.SolveStats` (``newton_iterations`` = 1, ``cg_iterations``,
        ``residual`` = the linear solve's relative residual; ``converged`` = the linear solve
        reached ``cg_tol``). On NaN/inf (or non-convergence with ``require_convergence``) raises
        :class:`SolveFailed` and leaves the state as it was.
        """
        t0 = time.perf_counter()
        n, pot = self.num_vertices, self._potential
        self._step_control = control
        syncs0, launches0 = pot.host_syncs, COUNTERS["launches"]
        prediction = self.integrator.predict(state_in, dt, self.ops, self._prediction_work)
        xb, vh, s = prediction
        self._assemble(state_in.x, matrix=True)  # R_e, K', f0' and f_w at x_n
        # the start: v_n on free components, the prescribed velocity on fixed ones
        fixed_v = self._prescribed_velocity(state_in, xb, s, control, self._pv)
        y = self._y
        self._launch(LK.select_kernel, n, [self._mask, state_in.v, fixed_v, y])
        self._inertia.set_prediction(vh)
        self._elastic.set_linearisation(state_in.x)
        pot.linear = None
        pot.begin(xb, s, self._weights(s, control))
        stats = newton_solve(pot, y, self.options)
        stats.newton_syncs = pot.host_syncs - syncs0
        stats.launches = COUNTERS["launches"] - launches0
        lin = pot.linear
        finite = bool(np.isfinite(stats.energy) and (lin is None or np.isfinite(lin.residual)))
        if lin is not None and stats.newton_iterations == 1:  # the Newton step was taken: the linear solve decides
            stats.converged, stats.residual = bool(lin.converged), float(lin.residual)
            stats.tolerance = self.options.cg_tol  # what that residual is tested against
            stats.reason = ("linear solve converged" if lin.converged else
                            f"linear solve stopped at relative residual {lin.residual:.2e}")
        if not finite:
            stats.converged, stats.reason = False, "non-finite velocity"
        self._finish(stats, t0, f"step {self.step_count}", finite=finite)
        self.integrator.advance(state_in, y, prediction, dt, self.ops, state_out)
        state_out.time = state_in.time + dt
        return stats
