"""Implicit time stepping and quasi-static solves of a :class:`~warpfem.model.Model` on a Warp device.

Every time integrator (backward Euler, BDF2, Newmark: :mod:`warpfem.integrators`) is one
minimisation per step of the incremental potential over the end-of-step velocity v (Gast, Schroeder, Stomakhin, Jiang & Teran 2015,
"Optimization integrator for large time steps"), e.g. for backward Euler

    E(v) = 1/2 (v - v_n)^T M (v - v_n) + h/2 v^T C v + V(x_n + h v) - h v^T f_ext,
    x_{n+1} = x_n + h v_{n+1},

with Rayleigh damping C = alpha M + beta K(x_n) (K the SPD-projected stiffness at the start of
the step, so the damping term is a fixed quadratic and E stays a potential). Its gradient is
M (v - v_n) + h C v - h f(x_n + h v) - h f_ext = 0, the backward Euler equations. BDF2 and
Newmark change the prediction (x_b, v_hat) and the scale s (h -> 2h/3, h/2). The potential is a
sum of terms (:mod:`warpfem.solvers.forms`) minimised by :func:`~warpfem.solvers.nonlinear.newton_solve`.
The quasi-static solve minimises V(x) - x^T f_ext over the free components of x.
"""

from __future__ import annotations

import time
import warnings
from typing import NamedTuple

import numpy as np
import warp as wp

from warpfem.device import get_device as _get_device
from warpfem.kernels import fem as FK
from warpfem.integrators import make_integrator
from warpfem.kernels import linalg as LK
from warpfem.kernels.generic import launch
from warpfem.kernels.structs import material_params, quadrature_points
from warpfem.model import static_supports_error
from warpfem.solvers.forms import DampingForm, ElasticForm, FullSpacePotential, InertiaForm, LoadForm, Workspace
from warpfem.solvers.nonlinear import NewtonOptions, SolveFailed, SolveStats, newton_solve
from warpfem.solvers.linear import make_linear_solver
from warpfem.solvers.linear.auto import simulator_options
from warpfem.solvers.state import SimulatorState, check_simulator_options
from warpfem.solvers.sparse import BlockPattern


class QuadratureSet(NamedTuple):
    """One set of quadrature points the element kernels run over (``Simulator._qp_sets``).

    count: number of points (the launch dimension); points: its ``QuadraturePoints32/64`` struct
    (rest positions, connectivity, nodes per element k, point -> element, weights, dN/dX);
    material: its ``MaterialParams32/64`` struct (kind, kernel mu, kernel lam; for selective
    reduced integration the split parameters of the set); energy: per-point energy buffer (J).
    The structs (``warpfem.kernels.structs``) are built once here and never changed, so the
    recorded launches of ``kernels.generic.launch`` reuse them without re-packing."""

    count: int
    points: object
    material: object
    energy: object


class Simulator(SimulatorState):
    """Time stepping and static solves of a model on a Warp device.

    Args:
        model: the :class:`~warpfem.model.Model`.
        device: Warp device ("cpu", "cuda:0", ..., or "auto": CUDA when present, else the CPU).
        precision: "float32" or "float64" (kernels, vectors and matrices; energies and dot
            products are always reduced in float64).
        dt: time step h (s). Smaller is more accurate (backward Euler damps a mode of angular
            frequency omega by 1/(1 + omega^2 h^2) in energy per step) and costs more steps.
        integrator: "backward_euler" (default), "bdf2" or "newmark" (average acceleration), or an
            instance from :mod:`warpfem.integrators` (see there and docs/integrators.md).
        damping_mass, damping_stiffness: Rayleigh coefficients alpha (1/s) and beta (s).
        require_convergence: raise :class:`SolveFailed` (state untouched) instead of accepting a
            non-converged step. NaN/inf always raises and never touches the state.
        linear_solver: "auto", "pcg", "direct", "amg" or "multigrid": the solver of each Newton system
            (docs/linear_solvers.md); ``linear_solver_options`` (dict) go to its constructor.
        Newton options (keyword): ``tol``, ``atol``, ``max_iters``, ``cg_tol``, ``max_cg_iters``,
            ``max_line_search``, ``armijo``, ``project_hessian`` (see :class:`NewtonOptions`).
    """

    def __init__(self, model, *, device="cpu", precision="float64", dt=1.0 / 60.0, integrator="backward_euler",
                 damping_mass=0.0, damping_stiffness=0.0, require_convergence=False, linear_solver="auto",
                 linear_solver_options=None, colliders=None, **newton_options):
        types = check_simulator_options(precision, dt, damping_mass, damping_stiffness)
        self.integrator = make_integrator(integrator)
        unknown = set(newton_options) - set(NewtonOptions.__dataclass_fields__)
        if unknown:
            raise TypeError(f"unknown solver option(s) {sorted(unknown)}; known: {sorted(NewtonOptions.__dataclass_fields__)}")
        self.options = NewtonOptions(**newton_options)
        self.options.validate()
        self.model = model
        self.device = _get_device(device)
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
        # the kernels' shared arguments as structs (warpfem.kernels.structs): the main point set and
        # the full material (stresses() and, without selective reduced integration, everything)
        self._points = quadrature_points(self._s, self._x_rest, self._elements, self._k, self._qp_element,
                                         self._qp_weight, self._qp_dNdX)
        self._material = material_params(self._s, mat.kind, mat.kernel_mu, mat.kernel_lam)
        self._pattern = BlockPattern(qd.elements, qd.nodes_per_element, n, device=dev, block_type=self._mat)
        self._mass_values = self._pattern.values_from_scalar_matrix(model.mass)
        self._hess_values = self._pattern.new_values()
        self._kn_values = self._pattern.new_values() if damping_stiffness > 0 else None
        self._pcg = make_linear_solver(linear_solver, self._pattern, vec_type=self._vec, scalar=self._s,
                                       positions=model.rest_positions, **simulator_options(linear_solver, linear_solver_options))
        self._energy_q = wp.zeros(self._qp_count, dtype=self._s, device=dev)
        # quadrature-point sets the kernels run over: (count, points, material, energy buffer). Selective reduced
        # integration (qd.volumetric) runs the same material kernels with the split parameters of
        # model.volumetric_parameters (Material.volumetric_split): the remaining part on the full
        # rule, the volumetric part on the 1-point rule; energy, force and Hessian are sums over the
        # sets (the Hessian of each part SPD-projected on its own). stresses() evaluates the full
        # material at the main (full-rule) points.
        self._qp_sets = [QuadratureSet(self._qp_count, self._points, self._material, self._energy_q)]
        if getattr(qd, "volumetric", None) is not None:
            vq = qd.volumetric
            split = getattr(model, "volumetric_parameters", None) or ((mat.kernel_mu, 0.0), (0.0, mat.kernel_lam))
            (mu_f, lam_f), (mu_v, lam_v) = split
            vpoints = quadrature_points(self._s, self._x_rest, self._elements, self._k,
                                        wp.array(vq.qp_element, dtype=wp.int32, device=dev),
                                        wp.array(vq.qp_weight.astype(self._np), dtype=self._s, device=dev),
                                        wp.array(vq.qp_dNdX.astype(self._np), dtype=self._vec, device=dev))
            self._qp_sets = [QuadratureSet(self._qp_count, self._points, material_params(self._s, mat.kind, mu_f, lam_f),
                                           self._energy_q),
                             QuadratureSet(vq.num_points, vpoints, material_params(self._s, mat.kind, mu_v, lam_v),
                                           wp.zeros(vq.num_points, dtype=self._s, device=dev))]

        def vec_array(a=None):
            return wp.zeros(n, dtype=self._vec, device=dev) if a is None else wp.array(np.asarray(a, dtype=self._np), dtype=self._vec, device=dev)

        self._vec_array = vec_array
        self.x = vec_array(model.rest_positions)
        self.v = vec_array()
        self._zero = vec_array()
        self._work = Workspace(self)
        self._targets = {}  # vertex -> target position for the next step (kinematic handles)
        #: control: the external forces (gravity + applied) act scaled by this (load ramps); the
        #: model itself is never rescaled
        self.load_scale = 1.0
        self.sync_model()
        self.contact = None  # warpfem.contact.ContactSet once a collider is added
        for c in colliders or ():
            self.add_collider(c)

    def add_collider(self, collider=None, **kw):
        """Add a kinematic collider (a :class:`warpfem.contact.Plane`, ``Sphere``, ``Box``,
        ``MeshCollider``, or ``type="plane"`` and its keywords): barrier + friction contact with the
        body's surface vertices in every step (docs/contact.md). Raises
        :class:`warpfem.contact.CollisionError` naming it if it intersects the body now."""
        from warpfem.contact import ContactSet, make_collider

        if collider is None:
            collider = make_collider(**kw)
        elif kw:
            raise TypeError("add_collider takes a collider object or keywords, not both")
        if self.contact is None:
            self.contact = ContactSet(self)
        self.contact.add(collider)
        return collider

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
        launch(LK.bsr_mv_kernel, pt.num_rows, [pt.offsets, pt.columns, values, x, self._s(alpha), y], self.device)

    def _linear_solve(self, values, rhs, out, opts):
        """out ~ A^-1 rhs on the free components (A the masked block matrix ``values``, rhs masked):
        the Newton systems' linear solver (block-Jacobi PCG); returns a result with ``iterations``."""
        return self._pcg.solve(values, self._mask, rhs, out, tol=opts.cg_tol, maxiter=opts.max_cg_iters)

    def _elastic_energy(self, x):
        parts = []
        for count, points, material, buf in self._qp_sets:
            launch(FK.qp_energy_kernel, dim=count, inputs=[x, points, material, buf], device=self.device)
            parts.append(buf.numpy().astype(np.float64))
        e = np.concatenate(parts)
        return float(e.sum()), float(np.abs(e).sum())

    def _assemble_stiffness(self, x, scale, values):
        for qs in self._qp_sets:
            launch(FK.qp_hessian_kernel, qs.count, [x, qs.points, qs.material, self._s(scale),
                                                    int(self.options.project_hessian), self._pattern.block_index, values],
                   self.device)

    # -- public hooks for benchmarks and tools (device arrays, no copies) ----------------------------
    @property
    def pattern(self):
        """The block-sparse pattern of the Hessian (:class:`warpfem.solvers.sparse.BlockPattern`)."""
        return self._pattern

    @property
    def linear_solver(self):
        """The linear solver of the Newton systems (``warpfem.solvers.linear``). Assignable: a
        benchmark may put another object with the same analyse / prepare / solve methods in its place."""
        return self._pcg

    @linear_solver.setter
    def linear_solver(self, solver):
        self._pcg = solver

    @property
    def quadrature_points(self):
        """The main quadrature-point set as the kernels take it (``kernels.structs.QuadraturePoints``)."""
        return self._points

    @property
    def material_params(self):
        """The material as the kernels take it (``kernels.structs.MaterialParams``: kind, kernel mu, lam)."""
        return self._material

    @property
    def scalar_type(self):
        """The Warp scalar type of the simulator's precision (``wp.float32`` / ``wp.float64``)."""
        return self._s

    @property
    def vector_type(self):
        """The Warp vec3 type of the simulator's precision."""
        return self._vec

    @property
    def numpy_dtype(self):
        """The numpy dtype of the simulator's precision."""
        return self._np

    @property
    def mass_values(self):
        """The mass matrix in the Hessian's block pattern (device array of 3x3 blocks)."""
        return self._mass_values

    @property
    def free_mask(self):
        """Per vertex (1, 1, 1) where free and 0 where fixed (device vec3 array), or None before the
        first step built it."""
        return getattr(self, "_mask", None)

    @property
    def num_points(self) -> int:
        """Quadrature points of the main (full-rule) set."""
        return self._qp_count

    def new_vector(self, a=None):
        """A device array of vec3 in the simulator's precision: zeros, or a copy of ``a`` (n, 3)."""
        return self._vec_array(a)

    def new_matrix_values(self):
        """Zeroed block values (3x3 per block) in the Hessian's pattern."""
        return self._pattern.new_values()

    def assemble_stiffness(self, x=None, values=None, *, scale=1.0):
        """Add ``scale`` x the elastic Hessian at ``x`` (device vec3 array, default the current
        positions; SPD-projected if the options say so) into ``values`` (default new zeroed values
        in :attr:`pattern`), in place; returns ``values``."""
        values = self.new_matrix_values() if values is None else values
        self._assemble_stiffness(self.x if x is None else x, scale, values)
        return values

    def elastic_forces(self, x=None) -> np.ndarray:
        """Internal elastic forces -dV/dx (N) at x (default: current positions), (n, 3)."""
        xa = self.x if x is None else self._vec_array(x)
        f = self._vec_array()
        for qs in self._qp_sets:
            launch(FK.qp_force_kernel, dim=qs.count, inputs=[xa, qs.points, qs.material, self._s(1.0), f], device=self.device)
        return f.numpy().astype(np.float64)

    def stresses(self, x=None) -> np.ndarray:
        """First Piola-Kirchhoff stress (Pa) at every quadrature point, (Q, 3, 3)."""
        xa = self.x if x is None else self._vec_array(x)
        P = wp.zeros(self._qp_count, dtype=self._mat, device=self.device)
        launch(FK.qp_stress_kernel, dim=self._qp_count, inputs=[xa, self._points, self._material, P], device=self.device)
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
        """Kinetic + elastic - x^T f_ext (J, f_ext times ``load_scale``): conserved by the exact
        dynamics without damping."""
        return self.kinetic_energy() + self.elastic_energy() - self.load_scale * self._pcg.dot(self.x, self._fext)

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

    def _prescribed_velocity(self, xb, s):
        """Device array: the end-of-step velocity that puts fixed components at their target (or
        keeps them where they are), (p - x_b) / s; only its fixed components are used."""
        out = self._vec_array()
        if not self._targets:
            if xb is not self.x:  # (x - x_b) first, then the scale: exact zero where x_b = x
                launch(LK.lincomb_kernel, dim=self.num_vertices, inputs=[self._s(1.0), self.x, self._s(-1.0), xb, out],
                          device=self.device)
                launch(LK.lincomb_kernel, dim=self.num_vertices, inputs=[self._s(1.0 / s), out, self._s(0.0), out, out],
                          device=self.device)
            return out
        p = self.positions()
        for i, t in self._targets.items():
            p[i] = t
        out.assign(((p - xb.numpy().astype(np.float64)) / s).astype(self._np))
        return out

    def _equation_of_motion_acceleration(self, out):
        """out = a with M a = f(x) + f_ext - C v on the free components (0 on fixed ones), C the
        Rayleigh damping alpha M + beta K(x): the acceleration of the current state (Newmark's a_0)."""
        n = self.num_vertices
        rhs = self._vec_array()
        for qs in self._qp_sets:
            launch(FK.qp_force_kernel, dim=qs.count, inputs=[self.x, qs.points, qs.material, self._s(1.0), rhs],
                   device=self.device)
        launch(LK.axpy_kernel, dim=n, inputs=[self._s(self.load_scale), self._fext, rhs], device=self.device)
        if self.damping_mass != 0.0:
            self._bsr_mv(self._mass_values, self.v, -self.damping_mass, rhs)
        if self.damping_stiffness != 0.0:
            kn = self._pattern.new_values()
            self._assemble_stiffness(self.x, 1.0, kn)
            self._bsr_mv(kn, self.v, -self.damping_stiffness, rhs)
        launch(LK.mask_kernel, dim=n, inputs=[self._mask, rhs], device=self.device)
        res = self._pcg.solve(self._mass_values, self._mask, rhs, out, tol=1e-12, maxiter=max(self.options.max_cg_iters, 100))
        if not np.isfinite(res.residual):
            raise SolveFailed("the initial acceleration M a = f + f_ext - C v is not finite; state left unchanged",
                              SolveStats(reason="non-finite initial acceleration"))

    def step(self) -> SolveStats:
        """Advance one step of ``dt`` with the simulator's integrator; returns its statistics.

        On NaN/inf (or non-convergence with ``require_convergence``) raises :class:`SolveFailed`
        and leaves positions, velocities, time and the integrator's history as they were.
        """
        t0 = time.perf_counter()
        n = self.num_vertices
        if self._kn_values is not None:
            self._kn_values.zero_()
            self._assemble_stiffness(self.x, 1.0, self._kn_values)
        prediction = self.integrator.predict(self)
        xb, y0, s = prediction
        fixed_v = self._prescribed_velocity(xb, s)
        y = self._vec_array()
        # initial guess: previous velocity on free components, prescribed on fixed ones
        launch(LK.select_kernel, dim=n, inputs=[self._mask, self.v, fixed_v, y], device=self.device)
        quadratic = [InertiaForm(self, y0)]
        if self.damping_mass != 0.0 or self.damping_stiffness != 0.0:
            quadratic.append(DampingForm(self, s * self.damping_mass, s * self.damping_stiffness))
        contact = None
        if self.contact is not None and len(self.contact):
            contact = self._begin_contact_step(xb, s, fixed_v, y)
        pot = FullSpacePotential(self, xb=xb, s=s, quadratic=quadratic, elastic=ElasticForm(self, s),
                                 load=LoadForm(self, s * self.load_scale), contact=contact)
        if contact is not None:  # start where no vertex is inside a collider (the previous velocity, cut)
            alpha = min(1.0, pot.max_step(self._contact_start, y))
            launch(LK.lincomb_kernel, dim=n, inputs=[self._s(1.0), self._contact_start, self._s(alpha), y, y],
                   device=self.device)
        stats = newton_solve(pot, y, self.options)
        self._finish(stats, t0, f"step {self.step_count}")
        self.integrator.advance(self, y, prediction)
        self._targets.clear()
        self.time += self.dt
        self.step_count += 1
        return stats

    def _begin_contact_step(self, xb, s, fixed_v, y):
        """Contact data of the coming step; ``y`` becomes the direction from a feasible start."""
        from warpfem.contact import ContactForm
        from warpfem.contact.contact import CollisionError
        from warpfem.solvers.forms import _E_CONTACT

        n = self.num_vertices
        self.contact.begin_step(self.time, self.time + self.dt, self.dt)
        # the unknown that keeps every vertex where it is (fixed ones at their targets): feasible
        # unless a collider moved into the body
        y0 = self._vec_array()
        launch(LK.lincomb_kernel, dim=n, inputs=[self._s(1.0), self.x, self._s(-1.0), xb, y0], device=self.device)
        launch(LK.lincomb_kernel, dim=n, inputs=[self._s(1.0 / s), y0, self._s(0.0), y0, y0], device=self.device)
        launch(LK.select_kernel, dim=n, inputs=[self._mask, y0, fixed_v, y0], device=self.device)
        x0 = self._vec_array()
        launch(LK.lincomb_kernel, dim=n, inputs=[self._s(1.0), xb, self._s(s), y0, x0], device=self.device)
        try:
            self.contact.check(x0, self.time + self.dt, what="moved into the body within one step (reduce dt or "
                               "slow the collider)")
        except CollisionError as e:
            raise SolveFailed(f"step {self.step_count}: {e}; state left unchanged",
                              SolveStats(reason="collider intersects the body")) from e
        self.contact.set_poses(self.time, self.time + self.dt)
        # y := y - y0 (the direction from the feasible start), cut by the step bound in step()
        launch(LK.lincomb_kernel, dim=n, inputs=[self._s(1.0), y, self._s(-1.0), y0, y], device=self.device)
        self._contact_start = y0
        return ContactForm(self.contact, s, _E_CONTACT, xb=xb)

    def solve_static(self, *, load_steps: int = 1) -> SolveStats:
        """Quasi-static equilibrium: minimise V(x) - x^T f_ext with the fixed components held.

        Loads and prescribed targets are ramped linearly over ``load_steps`` Newton solves
        (more steps: more robust for large deformation). Velocities are set to zero.
        """
        if self.contact is not None and len(self.contact):
            raise ValueError("solve_static does not handle colliders (contact is a dynamic term here); "
                             "use a damped time integration to reach rest on a collider")
        if int(load_steps) != load_steps or load_steps < 1:
            raise ValueError(f"load_steps must be a positive integer, got {load_steps!r}")
        problem = static_supports_error(self.model, "model.fix(...)")
        if problem:
            raise ValueError(problem)
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
            launch(LK.select_kernel, dim=n, inputs=[self._mask, y, fixed_x, y], device=self.device)
            pot = FullSpacePotential(self, xb=None, s=1.0, elastic=ElasticForm(self, 1.0), load=LoadForm(self, frac * self.load_scale))
            st = newton_solve(pot, y, self.options)
            total.newton_iterations += st.newton_iterations
            total.cg_iterations += st.cg_iterations
            total.line_search_steps += st.line_search_steps
            total.singular_solves += st.singular_solves
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
        self.integrator.reset()  # a new state: BDF2 / Newmark restart their history
        self._targets.clear()
        return total
