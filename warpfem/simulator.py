"""Backward Euler and quasi-static solves of a :class:`~warpfem.model.Model` on a Warp device.

Backward Euler as minimisation of the incremental potential (seed 004, slips corrected):

    E(v) = 1/2 (v - v_n)^T M (v - v_n) + h/2 v^T C v + V(x_n + h v) - h v^T f_ext,
    x_{n+1} = x_n + h v_{n+1},

with Rayleigh damping C = alpha M + beta K(x_n) (K the SPD-projected stiffness at the start of
the step, so the damping term is a fixed quadratic and E stays a potential). Its gradient is
M (v - v_n) + h C v - h f(x_n + h v) - h f_ext = 0, the backward Euler equations.
The quasi-static solve minimises V(x) - x^T f_ext over the free components of x.
"""

from __future__ import annotations

import time
import warnings

import numpy as np
import warp as wp

from warpfem.kernels import fem as FK
from warpfem.kernels import linalg as LK
from warpfem.solvers.newton import NewtonOptions, SolveFailed, SolveStats, newton_solve
from warpfem.solvers.linear import make_linear_solver
from warpfem.solvers.state import SimulatorState, check_simulator_options
from warpfem.solvers.sparse import BlockPattern


class _Potential:
    """E(y) = a/2 (y - y0)^T M (y - y0) + 1/2 y^T (cm M + ck Kn) y + V(xb + s y) - s y^T f_ext."""

    def __init__(self, sim, *, a, y0, cm, ck, s, xb, fext_scale=1.0):
        self.sim, self.a, self.y0, self.cm, self.ck, self.s, self.xb = sim, a, y0, cm, ck, s, xb
        self.fext_scale = fext_scale
        self.mask, self.n = sim._mask, sim.num_vertices

    def _x_of(self, y):
        sim = self.sim
        wp.launch(LK.lincomb_kernel, dim=self.n, inputs=[sim._s(1.0), self.xb, sim._s(self.s), y, sim._x_tmp], device=sim.device)
        return sim._x_tmp

    def _quadratic(self, y, out):
        """out = a M (y - y0) + (cm M + ck Kn) y."""
        sim = self.sim
        out.zero_()
        sim._bsr_mv(sim._mass_values, y, self.a + self.cm, out)
        if self.a != 0.0:
            sim._bsr_mv(sim._mass_values, self.y0, -self.a, out)
        if self.ck != 0.0:
            sim._bsr_mv(sim._kn_values, y, self.ck, out)

    def energy(self, y):
        sim = self.sim
        V, Vmag = sim._elastic_energy(self._x_of(y))
        q = sim._tmp2
        self._quadratic(y, q)
        # a/2 (y-y0)^T M (y-y0) + 1/2 y^T C y = 1/2 y^T q - a/2 y0^T M y + a/2 y0^T M y0 ... evaluate directly:
        quad = 0.5 * sim._pcg.dot(y, q)
        if self.a != 0.0:
            sim._tmp3.zero_()
            sim._bsr_mv(sim._mass_values, self.y0, self.a, sim._tmp3)
            quad += -0.5 * sim._pcg.dot(self.y0, q) + 0.5 * sim._pcg.dot(self.y0, sim._tmp3) - 0.5 * sim._pcg.dot(y, sim._tmp3) + 0.5 * sim._pcg.dot(y, sim._tmp3)
            # (the last two cancel; kept explicit: q = aM(y-y0)+Cy so 1/2 (y-y0)^T aM(y-y0) + 1/2 y^T C y
            #  = 1/2 y^T q - 1/2 y0^T q + 1/2 y0^T C y, and y0^T C y is added below)
            if self.cm != 0.0 or self.ck != 0.0:
                sim._tmp3.zero_()
                sim._bsr_mv(sim._mass_values, y, self.cm, sim._tmp3)
                if self.ck != 0.0:
                    sim._bsr_mv(sim._kn_values, y, self.ck, sim._tmp3)
                quad += 0.5 * sim._pcg.dot(self.y0, sim._tmp3)
            quad -= 0.5 * sim._pcg.dot(self.y0, sim._tmp3) * 0.0
        work = self.s * self.fext_scale * sim._pcg.dot(y, sim._fext)
        E = quad + V - work
        return E, abs(quad) + Vmag + abs(work)

    def gradient(self, y, g):
        """g = P grad E(y); returns the sum of the norms of its terms (the scale of its round-off)."""
        sim = self.sim
        self._quadratic(y, g)
        x = self._x_of(y)
        f = sim._tmp3
        f.zero_()
        for count, args, _ in sim._qp_sets:
            wp.launch(FK.qp_force_kernel, dim=count, inputs=[x, *args, sim._s(-self.s), f], device=sim.device)
        dot = sim._pcg.dot
        fa = sim._tmp2
        fa.zero_()
        for count, args, _ in sim._qp_sets:
            wp.launch(FK.qp_force_abs_kernel, dim=count, inputs=[x, *args, sim._s(self.s), fa], device=sim.device)
        magnitude = np.sqrt(dot(g, g)) + np.sqrt(dot(fa, fa)) + abs(self.s * self.fext_scale) * sim._fext_norm
        wp.launch(LK.add_scaled_kernel, dim=self.n, inputs=[f, sim._s(1.0), g], device=sim.device)
        wp.launch(LK.add_scaled_kernel, dim=self.n, inputs=[sim._fext, sim._s(-self.s * self.fext_scale), g], device=sim.device)
        wp.launch(LK.mask_kernel, dim=self.n, inputs=[self.mask, g], device=sim.device)
        return magnitude

    def resolution_scale(self, y):
        ymax = float(np.abs(y.numpy()).max())
        if self.s == 0.0:
            return ymax
        return ymax + float(np.abs(self._x_of(y).numpy()).max()) / abs(self.s)

    def assemble_hessian(self, y):
        sim = self.sim
        vals = sim._hess_values
        wp.launch(LK.scale_copy_kernel, dim=sim._pattern.nnz, inputs=[sim._mass_values, sim._s(self.a + self.cm), vals], device=sim.device)
        if self.ck != 0.0:
            wp.launch(LK.add_scaled_kernel, dim=sim._pattern.nnz, inputs=[sim._kn_values, sim._s(self.ck), vals], device=sim.device)
        sim._assemble_stiffness(self._x_of(y), self.s * self.s, vals)
        return vals


class Simulator(SimulatorState):
    """Time stepping and static solves of a model on a Warp device.

    Args:
        model: the :class:`~warpfem.model.Model`.
        device: Warp device ("cpu", "cuda:0", ...).
        precision: "float32" or "float64" (kernels, vectors and matrices; energies and dot
            products are always reduced in float64).
        dt: time step h (s). Smaller is more accurate (backward Euler damps a mode of angular
            frequency omega by 1/(1 + omega^2 h^2) in energy per step) and costs more steps.
        damping_mass, damping_stiffness: Rayleigh coefficients alpha (1/s) and beta (s).
        require_convergence: raise :class:`SolveFailed` (state untouched) instead of accepting a
            non-converged step. NaN/inf always raises and never touches the state.
        linear_solver: "auto", "pcg", "direct" or "amg": the solver of each Newton system
            (docs/linear_solvers.md); ``linear_solver_options`` (dict) go to its constructor.
        Newton options (keyword): ``tol``, ``atol``, ``max_iters``, ``cg_tol``, ``max_cg_iters``,
            ``max_line_search``, ``armijo``, ``project_hessian`` (see :class:`NewtonOptions`).
    """

    def __init__(self, model, *, device="cpu", precision="float64", dt=1.0 / 60.0, damping_mass=0.0,
                 damping_stiffness=0.0, require_convergence=False, linear_solver="auto",
                 linear_solver_options=None, **newton_options):
        types = check_simulator_options(precision, dt, damping_mass, damping_stiffness)
        unknown = set(newton_options) - set(NewtonOptions.__dataclass_fields__)
        if unknown:
            raise TypeError(f"unknown solver option(s) {sorted(unknown)}; known: {sorted(NewtonOptions.__dataclass_fields__)}")
        self.options = NewtonOptions(**newton_options)
        self.options.validate()
        self.model = model
        self.device = wp.get_device(device)
        self.precision = precision
        self._s, self._vec, self._mat, self._np = types
        self.dt = float(dt)
        self.damping_mass = float(damping_mass)
        self.damping_stiffness = float(damping_stiffness)
        self.require_convergence = require_convergence
        self.num_vertices = n = model.num_vertices
        self.time = 0.0
        self.step_count = 0

        dev, qd, mat = self.device, model.quadrature, model.material
        self._qp_count = qd.num_points
        self._elements = wp.array(qd.elements, dtype=wp.int32, device=dev)
        self._qp_element = wp.array(qd.qp_element, dtype=wp.int32, device=dev)
        self._qp_weight = wp.array(qd.qp_weight.astype(self._np), dtype=self._s, device=dev)
        self._qp_dNdX = wp.array(qd.qp_dNdX.astype(self._np), dtype=self._vec, device=dev)
        self._k = qd.nodes_per_element
        self._x_rest = wp.array(model.rest_positions.astype(self._np), dtype=self._vec, device=dev)
        self._qp_args = [self._x_rest, self._elements, self._k, self._qp_element, self._qp_weight, self._qp_dNdX,
                         int(mat.kind), self._s(mat.mu), self._s(mat.lam)]
        self._pattern = BlockPattern(qd.elements, qd.nodes_per_element, n, device=dev, block_type=self._mat)
        self._mass_values = self._pattern.values_from_scalar_matrix(model.mass)
        self._hess_values = self._pattern.new_values()
        self._kn_values = self._pattern.new_values() if damping_stiffness > 0 else None
        self._pcg = make_linear_solver(linear_solver, self._pattern, vec_type=self._vec, scalar=self._s,
                                       positions=model.rest_positions, **(linear_solver_options or {}))
        self._energy_q = wp.zeros(self._qp_count, dtype=self._s, device=dev)
        # quadrature-point sets the kernels run over: (count, args, energy buffer). Selective reduced
        # integration (qd.volumetric) runs the same material kernels with the split parameters of
        # model.volumetric_parameters (Material.volumetric_split): the remaining part on the full
        # rule, the volumetric part on the 1-point rule; energy, force and Hessian are sums over the
        # sets (the Hessian of each part SPD-projected on its own). stresses() evaluates the full
        # material at the main (full-rule) points.
        self._qp_sets = [(self._qp_count, self._qp_args, self._energy_q)]
        if getattr(qd, "volumetric", None) is not None:
            vq = qd.volumetric
            split = getattr(model, "volumetric_parameters", None) or ((mat.mu, 0.0), (0.0, mat.lam))
            (mu_f, lam_f), (mu_v, lam_v) = split
            vargs = [self._x_rest, self._elements, self._k, wp.array(vq.qp_element, dtype=wp.int32, device=dev),
                     wp.array(vq.qp_weight.astype(self._np), dtype=self._s, device=dev),
                     wp.array(vq.qp_dNdX.astype(self._np), dtype=self._vec, device=dev),
                     int(mat.kind), self._s(mu_v), self._s(lam_v)]
            main = self._qp_args[:7] + [self._s(mu_f), self._s(lam_f)]
            self._qp_sets = [(self._qp_count, main, self._energy_q),
                             (vq.num_points, vargs, wp.zeros(vq.num_points, dtype=self._s, device=dev))]

        def vec_array(a=None):
            return wp.zeros(n, dtype=self._vec, device=dev) if a is None else wp.array(np.asarray(a, dtype=self._np), dtype=self._vec, device=dev)

        self._vec_array = vec_array
        self.x = vec_array(model.rest_positions)
        self.v = vec_array()
        self._zero = vec_array()
        self._x_tmp, self._tmp2, self._tmp3 = vec_array(), vec_array(), vec_array()
        self._targets = {}  # vertex -> target position for the next step (kinematic handles)
        self.sync_model()

    # -- model changes (no pattern rebuild) -----------------------------------------------------------
    def sync_model(self):
        """Upload the model's fixed mask and external forces (call after changing them)."""
        self._mask = self._vec_array((~self.model.fixed).astype(np.float64))
        fext = self.model.external_forces()
        self._fext = self._vec_array(fext)
        self._fext_norm = float(np.linalg.norm(fext))

    # -- stages (each a function that can be timed) ------------------------------------------------
    def _bsr_mv(self, values, x, alpha, y):
        pt = self._pattern
        wp.launch(LK.bsr_mv_kernel, dim=pt.num_rows, inputs=[pt.offsets, pt.columns, values, x, self._s(alpha), y], device=self.device)

    def _elastic_energy(self, x):
        parts = []
        for count, args, buf in self._qp_sets:
            wp.launch(FK.qp_energy_kernel, dim=count, inputs=[x, *args, buf], device=self.device)
            parts.append(buf.numpy().astype(np.float64))
        e = np.concatenate(parts)
        return float(e.sum()), float(np.abs(e).sum())

    def _assemble_stiffness(self, x, scale, values):
        for count, args, _ in self._qp_sets:
            wp.launch(FK.qp_hessian_kernel, dim=count,
                      inputs=[x, *args, self._s(scale), int(self.options.project_hessian),
                              self._pattern.block_index, values], device=self.device)

    def elastic_forces(self, x=None) -> np.ndarray:
        """Internal elastic forces -dV/dx (N) at x (default: current positions), (n, 3)."""
        xa = self.x if x is None else self._vec_array(x)
        f = self._vec_array()
        for count, args, _ in self._qp_sets:
            wp.launch(FK.qp_force_kernel, dim=count, inputs=[xa, *args, self._s(1.0), f], device=self.device)
        return f.numpy().astype(np.float64)

    def stresses(self, x=None) -> np.ndarray:
        """First Piola-Kirchhoff stress (Pa) at every quadrature point, (Q, 3, 3)."""
        xa = self.x if x is None else self._vec_array(x)
        P = wp.zeros(self._qp_count, dtype=self._mat, device=self.device)
        a = self._qp_args
        wp.launch(FK.qp_stress_kernel, dim=self._qp_count, inputs=[xa, a[0], a[1], a[2], a[3], a[5], a[6], a[7], a[8], P], device=self.device)
        return P.numpy().astype(np.float64)

    def elastic_energy(self, x=None) -> float:
        """V(x) (J) at x (default: current positions)."""
        return self._elastic_energy(self.x if x is None else self._vec_array(x))[0]

    def kinetic_energy(self) -> float:
        """1/2 v^T M v (J)."""
        q = self._vec_array()
        self._bsr_mv(self._mass_values, self.v, 1.0, q)
        return 0.5 * self._pcg.dot(self.v, q)

    def total_energy(self) -> float:
        """Kinetic + elastic - x^T f_ext (J): conserved by the exact dynamics without damping."""
        return self.kinetic_energy() + self.elastic_energy() - self._pcg.dot(self.x, self._fext)

    def stiffness_matrix(self, x=None, *, project=None):
        """The assembled stiffness d2V/dx2 at x as scipy CSR (3n x 3n), for analysis and tests."""
        vals = self._pattern.new_values()
        old = self.options.project_hessian
        if project is not None:
            self.options.project_hessian = bool(project)
        try:
            self._assemble_stiffness(self.x if x is None else self._vec_array(x), 1.0, vals)
        finally:
            self.options.project_hessian = old
        return self._pattern.to_scipy(vals)

    def mass_matrix(self):
        """The (3n x 3n) mass matrix as scipy CSR."""
        return self._pattern.to_scipy(self._mass_values)

    # -- solves ----------------------------------------------------------------------------------
    def _prescribed(self, base_x, h):
        """Fixed-component values of the unknown: velocities (dynamics, h > 0) or positions (static)."""
        x0 = base_x.numpy().astype(np.float64)
        val = np.zeros_like(x0) if h > 0 else x0.copy()
        for i, p in self._targets.items():
            if h > 0:
                val[i] = (p - x0[i]) / h
            else:
                val[i] = p
        return val

    def _finish(self, stats, t0, what):
        stats.seconds = time.perf_counter() - t0
        if not stats.converged:
            if "non-finite" in stats.reason or not np.isfinite(stats.energy):
                raise SolveFailed(f"{what} diverged ({stats.reason}); state left unchanged", stats)
            if self.require_convergence:
                raise SolveFailed(f"{what} did not converge ({stats.reason}); state left unchanged", stats)
            warnings.warn(f"{what} did not converge: {stats.reason} (relative gradient {stats.residual:.2e})", RuntimeWarning, stacklevel=3)

    def step(self) -> SolveStats:
        """Advance one backward Euler step of ``dt``; returns its statistics.

        On NaN/inf (or non-convergence with ``require_convergence``) raises :class:`SolveFailed`
        and leaves positions, velocities and time as they were.
        """
        t0 = time.perf_counter()
        h = self.dt
        n = self.num_vertices
        if self._kn_values is not None:
            self._kn_values.zero_()
            self._assemble_stiffness(self.x, 1.0, self._kn_values)
        fixed_v = self._vec_array(self._prescribed(self.x, h))
        y = self._vec_array()
        # initial guess: previous velocity on free components, prescribed on fixed ones
        wp.launch(LK.select_kernel, dim=n, inputs=[self._mask, self.v, fixed_v, y], device=self.device)
        pot = _Potential(self, a=1.0, y0=self.v, cm=h * self.damping_mass, ck=h * self.damping_stiffness, s=h, xb=self.x)
        stats = newton_solve(pot, y, self.options, self._pcg)
        self._finish(stats, t0, f"step {self.step_count}")
        x_new = self._vec_array()
        wp.launch(LK.lincomb_kernel, dim=n, inputs=[self._s(1.0), self.x, self._s(h), y, x_new], device=self.device)
        self.x, self.v = x_new, y
        self._targets.clear()
        self.time += h
        self.step_count += 1
        return stats

    def solve_static(self, *, load_steps: int = 1) -> SolveStats:
        """Quasi-static equilibrium: minimise V(x) - x^T f_ext with the fixed components held.

        Loads and prescribed targets are ramped linearly over ``load_steps`` Newton solves
        (more steps: more robust for large deformation). Velocities are set to zero.
        """
        if int(load_steps) != load_steps or load_steps < 1:
            raise ValueError(f"load_steps must be a positive integer, got {load_steps!r}")
        fixed_any = self.model.fixed.any(axis=0)
        if not fixed_any.all():
            raise ValueError("a static solve needs fixed components in x, y and z to remove rigid motions; "
                             f"free axes: {[a for a, f in zip('xyz', fixed_any) if not f]}")
        t0 = time.perf_counter()
        n = self.num_vertices
        x_start = self.positions()
        targets = {i: p.copy() for i, p in self._targets.items()}
        y = self._vec_array(x_start)
        total = SolveStats(converged=True)
        for step in range(1, int(load_steps) + 1):
            frac = step / load_steps
            self._targets = {i: x_start[i] + frac * (p - x_start[i]) for i, p in targets.items()}
            fixed_x = self._vec_array(self._prescribed(self._vec_array(x_start), 0.0))
            wp.launch(LK.select_kernel, dim=n, inputs=[self._mask, y, fixed_x, y], device=self.device)
            pot = _Potential(self, a=0.0, y0=self._zero, cm=0.0, ck=0.0, s=1.0, xb=self._zero, fext_scale=frac)
            st = newton_solve(pot, y, self.options, self._pcg)
            total.newton_iterations += st.newton_iterations
            total.cg_iterations += st.cg_iterations
            total.line_search_steps += st.line_search_steps
            total.residual, total.gradient_norm, total.energy = st.residual, st.gradient_norm, st.energy
            total.reason = st.reason
            if not st.converged:
                total.converged = False
                total.reason = f"load step {step}/{load_steps}: {st.reason}"
                break
        self._targets = targets
        self._finish(total, t0, "static solve")
        self.x = y
        self.v = self._vec_array()
        self._targets.clear()
        return total
