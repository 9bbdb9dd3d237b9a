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
from typing import NamedTuple

import numpy as np
import warp as wp

from warpfem.kernels import fem as FK
from warpfem.integrators import make_integrator
from warpfem.kernels import linalg as LK
from warpfem.kernels.generic import COUNTERS, launch, ordered_sums
from warpfem.kernels.structs import material_params, quadrature_points
from warpfem.model import static_supports_error
from warpfem.solvers.forms import (DampingForm, ElasticForm, IncrementalPotential, InertiaForm, InfeasibleStart, LoadForm,
                                   StepContext, Workspace, check_lag_below)
from warpfem.solvers.nonlinear import SolveFailed, SolveStats, newton_solve
from warpfem.solvers.state import SimulatorBase, _NoState, check_simulator_options, newton_options_from
from warpfem.solvers.sparse import PatternView
from warpfem.transfer import read, to_device, upload

#: the choices of ``Simulator(initial_guess=...)``
INITIAL_GUESSES = ("previous", "extrapolated")


class QuadratureSet(NamedTuple):
    """One set of quadrature points the element kernels run over (``Simulator.quadrature_sets``).

    count: number of points (the launch dimension); points: its ``QuadraturePoints32/64`` struct
    (rest positions, connectivity, nodes per element k, point -> element, weights, dN/dX);
    material: its ``MaterialParams32/64`` struct (kind, kernel mu, kernel lam; for selective
    reduced integration the split parameters of the set); energy: per-point energy buffer (J);
    group: the body whose elements the points belong to (``BlockPattern.block_indices[group]``).
    The structs (``warpfem.kernels.structs``) are built once here and never changed, so the
    recorded launches of ``kernels.generic.launch`` reuse them without re-packing."""

    count: int
    points: object
    material: object
    energy: object
    group: int = 0  # the body (element group) of the points: its part of the pattern's block_index


class Simulator(SimulatorBase):
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
            non-converged step. NaN/inf always raises and never touches the state. Without it a
            non-converged step is kept, warned about (``NotConvergedWarning``, a RuntimeWarning
            with the reason and the relative gradient against ``tol``) and counted in
            ``sim.unconverged_steps``.
        linear_solver: "auto", "pcg", "direct", "amg" or "multigrid": the solver of each Newton system
            (docs/linear_solvers.md); ``linear_solver_options`` (dict) go to its constructor.
        Newton options (keyword): ``tol``, ``atol``, ``max_iters`` (not given: 30, or what the
            potential's forms ask for, ``Form.newton_iterations``: 100 with contact), ``cg_tol``, ``max_cg_iters``,
            ``max_line_search``, ``armijo``, ``project_hessian``, ``hessian_projection``, ``forcing``,
            ``friction_filter``, ``extrapolate``, ``step_tol``, ``friction_pin`` (see :class:`NewtonOptions`).
        initial_guess: where each step's Newton solve starts (free components; fixed ones always
            start at their prescribed value). "previous" (default): the previous velocity v_n.
            "extrapolated": constant acceleration from the history, v_n + h (v_n - v_{n-1}) / h_prev
            (Newmark: v_n + h a_n); the first step after a state change starts at v_n. Converges
            to the same step; the measured effect on Newton iterations is in docs/integrators.md.
        friction_iterations, friction_tol: with friction in contact (colliders or ``set_contact``),
            take the normal forces and normals again from the step's iterate, inside its Newton
            solve, at most this many times: after an iteration whose full Newton step brought the
            gradient below 1e-2 of its start (``forms.LAG_BELOW``, a form's ``lag_below``), while they
            change by more than
            ``friction_tol`` of the largest; the solve then goes on to the tolerance with them (0:
            lagged once from the step start; steps recorded for gradients lag once). Any form that
            lags a quantity (``Form.uses_lagging`` / ``update_lagging``) is updated the same way.
            Measured effect: docs/contact.md.
        friction_update_tol: > 0: the first of those updates is made only when a normal force at
            the iterate differs from its lagged value by more than this fraction of the largest
            (e.g. 0.25: a contact the step makes or loses, an impact); otherwise the step keeps the
            lag of its start, consistent to that tolerance, and needs no further Newton iteration
            for it (``SolveStats.friction_kept`` counts these). 0 (default): always update. Fewer
            Newton iterations, less accurate sliding friction where normal forces swing from step
            to step: docs/contact.md, "Friction updated only when the normal forces change".
        friction_lag_below: the relative gradient (over the step's start) at or under which an
            iterate reached by a full Newton step is taken as near enough to the solution for those
            updates; None (default): 1e-2 (``forms.LAG_BELOW``, or a form's own ``lag_below``).
            Larger (e.g. 0.1): the update comes earlier, saving Newton iterations, with normal
            forces taken further from the step's solution: docs/contact.md, "When friction's lag
            is taken again (friction_lag_below)".
    """

    def __init__(self, model, *, device="cpu", precision="float64", dt=1.0 / 60.0, integrator="backward_euler",
                 damping_mass=0.0, damping_stiffness=0.0, require_convergence=False, linear_solver="auto",
                 linear_solver_options=None, colliders=None, initial_guess="previous", friction_iterations=1,
                 friction_tol=0.01, friction_update_tol=0.0, friction_lag_below=None, **newton_options):
        types = check_simulator_options(precision, dt, damping_mass, damping_stiffness)
        if initial_guess not in INITIAL_GUESSES:
            raise ValueError(f"initial_guess must be one of {', '.join(repr(g) for g in INITIAL_GUESSES)}, "
                             f"got {initial_guess!r}")
        self.initial_guess = initial_guess
        if int(friction_iterations) != friction_iterations or friction_iterations < 0:
            raise ValueError(f"friction_iterations must be an integer >= 0, got {friction_iterations!r}")
        if not (np.isfinite(friction_tol) and friction_tol > 0.0):
            raise ValueError(f"friction_tol must be > 0, got {friction_tol!r}")
        self.friction_iterations, self.friction_tol = int(friction_iterations), float(friction_tol)
        if not (np.isfinite(friction_update_tol) and 0.0 <= friction_update_tol < 1.0):
            raise ValueError(f"friction_update_tol must be in [0, 1), got {friction_update_tol!r}")
        self.friction_update_tol = float(friction_update_tol)
        self.friction_lag_below = friction_lag_below  # (checked by the property)
        self.integrator = make_integrator(integrator)
        self.options = newton_options_from(newton_options)
        # max_iters not given: the default, raised to what the potential's forms ask for (contact),
        # while it is still the value set so (an assignment to options.max_iters is the user's)
        self._max_iters_base = None if "max_iters" in newton_options else self.options.max_iters
        self._max_iters_set = self.options.max_iters
        self._setup_base(model, device, precision, types, dt, damping_mass, damping_stiffness, require_convergence)
        n = self.num_vertices
        dev = self.device
        # one quadrature set per body (a single-mesh model: its one body); each body's own element
        # type (k), material and connectivity (global vertex indices), all in one vertex space
        rigid = getattr(model, "rigid", None)  # rigid bodies (warpfem.rigid): their nodes have no elements
        quads = list(model.quadratures) if rigid is not None else list(getattr(model, "quadratures", None)
                                                                        or [model.quadrature])
        mats = list(getattr(model, "materials", None) or [model.material])
        splits = list(getattr(model, "body_volumetric_parameters", None) or [getattr(model, "volumetric_parameters", None)])
        self._x_rest = to_device(model.rest_positions.astype(self._np), self._vec, dev)
        self._qp_sets, self._main_sets = [], []
        for group, (qd, mat, split) in enumerate(zip(quads, mats, splits)):
            elements = to_device(qd.elements, wp.int32, dev)
            points = quadrature_points(self._s, self._x_rest, elements, qd.nodes_per_element,
                                       to_device(qd.qp_element, wp.int32, dev),
                                       to_device(qd.qp_weight.astype(self._np), self._s, dev),
                                       to_device(qd.qp_dNdX.astype(self._np), self._vec, dev))
            # the kernels' shared arguments as structs (warpfem.kernels.structs): the main point set and
            # the full material (stresses() and, without selective reduced integration, everything)
            material = material_params(self._s, mat.kind, mat.kernel_mu, mat.kernel_lam)
            energy = wp.zeros(qd.num_points, dtype=self._s, device=dev)
            main = QuadratureSet(qd.num_points, points, material, energy, group)
            self._main_sets.append(main)
            if getattr(qd, "volumetric", None) is None:
                self._qp_sets.append(main)
                continue
            # selective reduced integration (qd.volumetric) runs the same material kernels with the split
            # parameters of the body's volumetric_parameters (Material.volumetric_split): the remaining part
            # on the full rule, the volumetric part on the 1-point rule; energy, force and Hessian are sums
            # over the sets (the Hessian of each part SPD-projected on its own). stresses() evaluates the
            # full material at the main (full-rule) points.
            vq = qd.volumetric
            (mu_f, lam_f), (mu_v, lam_v) = split or ((mat.kernel_mu, 0.0), (0.0, mat.kernel_lam))
            vpoints = quadrature_points(self._s, self._x_rest, elements, qd.nodes_per_element,
                                        to_device(vq.qp_element, wp.int32, dev),
                                        to_device(vq.qp_weight.astype(self._np), self._s, dev),
                                        to_device(vq.qp_dNdX.astype(self._np), self._vec, dev))
            self._qp_sets += [QuadratureSet(qd.num_points, points, material_params(self._s, mat.kind, mu_f, lam_f),
                                            energy, group),
                              QuadratureSet(vq.num_points, vpoints, material_params(self._s, mat.kind, mu_v, lam_v),
                                            wp.zeros(vq.num_points, dtype=self._s, device=dev), group)]
        first = self._main_sets[0] if self._main_sets else None  # None: rigid bodies only
        self._points, self._material = (first.points, first.material) if first else (None, None)  # the first body's
        self._elements = first.points.elements if first else None
        self._k = quads[0].nodes_per_element if quads else 4
        self._qp_count = sum(ms.count for ms in self._main_sets)
        self._energy_q = first.energy if first else None
        if rigid is not None:  # the soft bodies' patterns and each rigid body's 4 nodes as one "element"
            groups = [(q.elements, q.nodes_per_element) for q in quads] + list(model.extra_element_groups)
            self._setup_system([e for e, _ in groups], [k for _, k in groups], linear_solver, linear_solver_options)
        elif len(quads) == 1:
            self._setup_system(quads[0].elements, quads[0].nodes_per_element, linear_solver, linear_solver_options)
        else:  # the union of the bodies' element patterns (one element group per body)
            self._setup_system([q.elements for q in quads], [q.nodes_per_element for q in quads], linear_solver,
                               linear_solver_options)
        if damping_stiffness > 0:
            self.system.new_values("kn")
        v0 = model.initial_velocities() if hasattr(model, "initial_velocities") else None
        if v0 is not None:  # the bodies' initial_velocity (Model.from_bodies)
            upload(self.state.v, v0.astype(self._np))
        # the incremental potential: one list of weighted forms, built once (solvers/forms.py)
        system, ops = self.system, self.ops
        pattern = PatternView(system)  # forms follow the pattern when it grows
        self._elastic = ElasticForm(ops, self._qp_sets, pattern, self.options)
        self._inertia = InertiaForm(ops, pattern, lambda: system.values["mass"])
        self._load = LoadForm(ops, self._fext, self._fext_norm)
        forms = [self._inertia]
        if self.damping_mass != 0.0 or self.damping_stiffness != 0.0:
            forms.append(DampingForm(ops, pattern, lambda: system.values["mass"], self.damping_mass,
                                     lambda: system.values["kn"], self.damping_stiffness))
        forms += [self._elastic, self._load]
        self._builtin_forms = forms  # the potential's own terms; add_form's come after (self._forms)
        self._forms = []
        self._work = Workspace(ops)
        self._y = ops.new_vector()  # the unknown of the step's Newton solve
        self._fixed_v = ops.new_vector()
        self._start = ops.new_vector()  # the feasible start of a step whose forms bound it
        self._prediction_work = {}  # the integrator's prediction buffers (made on first use)
        self._potential = IncrementalPotential(ops, forms, system=system, mask=self._mask,
                                               linear_solve=lambda *a, **kw: self._linear_solve(*a, **kw), work=self._work)
        self._potential.iterative_solve = lambda: bool(getattr(self._pcg, "iterative", True))
        # the body size of the step test (NewtonOptions.step_tol): the rest mesh's bounding-box diagonal
        rest = np.asarray(model.rest_positions, dtype=np.float64)
        self._potential.body_size = float(np.linalg.norm(np.ptp(rest, axis=0))) if len(rest) else 0.0
        self._static_potential = None
        self._contact_form = None  # the colliders' ContactForm (its ContactSet: self.contact)
        self._surface_form = None  # the SurfaceContactForm of set_contact(...)
        self._rigid = None  # the rigid bodies' map and vertex space (warpfem.rigid.embedding)
        if rigid is not None:
            from warpfem.rigid.embedding import attach

            self._rigid = attach(self)
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
        if self.contact is None:  # its form joins the potential once it holds a collider
            self.contact = ContactSet(self if self._rigid is None else self._rigid.space)  # rigid: vertex space
        self.contact.add(collider)
        return collider

    @property
    def contact(self):
        """The colliders (:class:`warpfem.contact.ContactSet`), None before the first ``add_collider``.
        Assignable (None drops the colliders' form from the potential)."""
        return None if self._contact_form is None else self._contact_form.contact

    @contact.setter
    def contact(self, contact_set):
        from warpfem.contact import ContactForm

        new = None if contact_set is None else ContactForm(contact_set)
        if self._rigid is not None:
            new = self._rigid.wrap(new)
        self._replace_form(self._contact_form, new)
        self._contact_form = new

    def set_contact(self, /, *, bodies=None, friction=0.0, dhat=None, stiffness=None, friction_velocity=None, **flags):
        """Contact between the model's bodies and of each with itself (docs/contact.md): a barrier
        on point-triangle and edge-edge distances of the boundary surface, lagged friction and a
        continuous-collision bound on every line search. Keys (those of a scene's ``[contact]``):
        ``bodies`` (different connected components / bodies; default True when the model has two
        or more), ``self`` (within one; default False), ``friction`` (mu), ``dhat`` (m),
        ``stiffness`` (kappa of the squared-distance barrier, N/m^3; ``"auto"``: adaptive), ``friction_velocity`` (m/s).
        ``sim.set_contact(bodies=False)`` (and no ``self``) turns it off. Returns the
        :class:`warpfem.contact.SurfaceContact` (or None when off). Raises
        :class:`warpfem.contact.CollisionError` naming a pair when surface primitives touch now."""
        from warpfem.contact.surface import SurfaceContact

        on = self if self._rigid is None else self._rigid.space  # rigid bodies: the vertex space
        sc = SurfaceContact(on, bodies=bodies, friction=friction, dhat=dhat, stiffness=stiffness,
                            friction_velocity=friction_velocity, **flags)
        if not (sc.bodies or sc.self_contact):
            sc.detach()
            sc = None
        self.surface_contact = sc
        return sc

    @property
    def surface_contact(self):
        """The :class:`warpfem.contact.SurfaceContact` of ``set_contact`` (None when off)."""
        return None if self._surface_form is None else self._surface_form.contact

    @surface_contact.setter
    def surface_contact(self, surface_contact):
        from warpfem.contact.surface import SurfaceContactForm

        old = self._surface_form
        if old is not None and old.contact is not surface_contact:
            old.contact.detach()
        new = None if surface_contact is None else SurfaceContactForm(surface_contact)
        if self._rigid is not None:
            new = self._rigid.wrap(new)
        self._replace_form(old, new)
        self._surface_form = new

    @property
    def surface_contact_form(self):
        """The form of the surface contact in the potential (None when off)."""
        return self._surface_form

    def add_form(self, form):
        """Add a term (a :class:`warpfem.solvers.forms.Form`) to the incremental potential of every
        later step (weight ``form.weight``; a form of x gets the chain factors s, s^2), placed by
        its ``order``. Its life-cycle hooks (``enabled``, ``begin_step``, ``check_start``,
        ``max_step``, ``update_lagging``, ``static_error``: warpfem.solvers.forms) are called
        like those of the built-in contact forms."""
        if all(f is not form for f in self._forms):
            self._forms.append(form)
        self._sync_forms()
        return form

    def remove_form(self, form):
        """Remove a term that ``add_form`` added (nothing if it is not there)."""
        self._replace_form(form, None)

    @property
    def forms(self):
        """The terms added to the potential (``add_form``, the contact forms), enabled or not."""
        return list(self._forms)

    def _replace_form(self, old, new):
        """``new`` in place of ``old`` among the added forms (either may be None)."""
        forms = [new if f is old else f for f in self._forms] if old is not None else list(self._forms)
        if new is not None and all(f is not new for f in forms):
            forms.append(new)
        self._forms = [f for f in forms if f is not None]
        self._sync_forms()

    def _sync_forms(self):
        """The potential holds its own forms and the added forms that are enabled now (a form may
        switch itself on or off: the colliders' form without colliders is off)."""
        want = IncrementalPotential.ordered(self._builtin_forms + [f for f in self._forms if f.enabled()])
        if want != self._potential.forms:
            self._potential.set_forms(want)
        if getattr(self, "_max_iters_base", None) is not None and self.options.max_iters == self._max_iters_set:
            self.options.max_iters = self._max_iters_set = max(
                [self._max_iters_base] + [int(f.newton_iterations) for f in self._forms
                                          if getattr(f, "newton_iterations", None)])

    def _form_parts(self, view=None):
        """(``"form/NAME"``, form) of every form of the potential, the added ones enabled or not
        (NAME: the form's ``name``, ``NAME#2`` ... for repeated names): each form's
        ``state_dict`` / ``load_state_dict`` (:class:`~warpfem.solvers.forms.Form`)."""
        parts, seen = [], {}
        for f in self._builtin_forms + self._forms:
            name = str(getattr(f, "name", "form"))
            seen[name] = seen.get(name, 0) + 1
            key = name if seen[name] == 1 else f"{name}#{seen[name]}"
            parts.append((f"form/{key}", f if hasattr(f, "state_dict") else _NoState()))
        return parts

    # -- stages (each a function that can be timed) ------------------------------------------------
    @property
    def _hess_values(self):
        return self.system.values["hessian"]

    @property
    def _kn_values(self):
        return self.system.values.get("kn")

    def _elastic_energy(self, x):
        if not self._qp_sets:  # rigid bodies only
            return 0.0, 0.0
        parts = []
        for count, points, material, buf, _ in self._qp_sets:
            launch(FK.qp_energy_kernel, dim=count, inputs=[x, points, material, buf], device=self.device)
            parts.append(read(buf).astype(np.float64))
        e = np.concatenate(parts)
        return float(e.sum()), float(np.abs(e).sum())

    def _assemble_stiffness(self, x, scale, values):
        self._elastic.assemble(x, scale, values)

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
        self.system.solver = solver  # re-analyses a grown pattern

    @property
    def quadrature_points(self):
        """The main quadrature-point set as the kernels take it (``kernels.structs.QuadraturePoints``)."""
        return self._points

    @property
    def quadrature_sets(self):
        """The quadrature-point sets the element kernels run over (:class:`QuadratureSet`: the main
        set first, then the one-point volumetric set of selective reduced integration)."""
        return list(self._qp_sets)

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
    def rigid(self):
        """The rigid bodies' :class:`warpfem.rigid.embedding.RigidSystem` (the map from the unknown to
        the vertices, ``vertex_positions``), or None for a model without rigid bodies."""
        return self._rigid

    def vertex_positions(self, state=None) -> np.ndarray:
        """(n, 3) positions of every body's vertices in body order (``model.body_offsets``): the
        same as :meth:`positions` without rigid bodies; with them, a rigid body's vertices at
        p + A X (the unknown, :meth:`positions`, holds p and A's columns: docs/rigid.md)."""
        x = self.x if state is None else state.x
        return read(x).astype(np.float64) if self._rigid is None else self._rigid.vertex_positions(x)

    def vertex_velocities(self, state=None) -> np.ndarray:
        """(n, 3) velocities of every body's vertices in body order (see :meth:`vertex_positions`)."""
        v = self.v if state is None else state.v
        return read(v).astype(np.float64) if self._rigid is None else self._rigid.vertex_positions(v)

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
        self._add_elastic_force(xa, f)
        return read(f).astype(np.float64)

    def stresses(self, x=None) -> np.ndarray:
        """First Piola-Kirchhoff stress (Pa) at every quadrature point, (Q, 3, 3)."""
        xa = self.x if x is None else self._vec_array(x)
        parts = []
        for ms in self._main_sets:  # one per body, in body order
            P = wp.zeros(ms.count, dtype=self._mat, device=self.device)
            launch(FK.qp_stress_kernel, dim=ms.count, inputs=[xa, ms.points, ms.material, P], device=self.device)
            parts.append(read(P).astype(np.float64))
        if not parts:  # rigid bodies only: no quadrature point
            return np.zeros((0, 3, 3))
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def elastic_energy(self, x=None) -> float:
        """V(x) (J) at x (default: current positions)."""
        return self._elastic_energy(self.x if x is None else self._vec_array(x))[0]

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
        x0 = read(base_x).astype(np.float64)
        val = np.zeros_like(x0) if h > 0 else x0.copy()
        for i, p in self._targets.items():
            if h > 0:
                val[i] = (p - x0[i]) / h
            else:
                val[i] = p
        return val

    def _elastic_force_for_acceleration(self, x, out):
        """out := f(x), the elastic force; the stiffness damping's K(x_n) (assembled at the start
        of the step) for the equation-of-motion acceleration (SimulatorBase)."""
        out.zero_()
        self._add_elastic_force(x, out)
        return self._kn_values

    def _add_elastic_force(self, x, f):
        """f += the elastic force at x: on the CPU one launch per point set scattering with atomics
        (a launch's threads run in order there), elsewhere (``generic.ORDERED_SUMS``) the
        gradient's per-vertex gather in a fixed order."""
        if ordered_sums(self.device):
            self._elastic.add_force(x, f)
            return
        for qs in self._qp_sets:
            launch(FK.qp_force_kernel, dim=qs.count, inputs=[x, qs.points, qs.material, self._s(1.0), f], device=self.device)

    def potential(self, state=None, control=None, dt=None):
        """The incremental potential of a step of ``dt`` from ``state`` (default: the simulator's
        own), as the Newton loop sees it (:class:`warpfem.solvers.forms.IncrementalPotential`),
        with the prediction applied; for tests and tools."""
        state = self.state if state is None else state
        control = self.control if control is None else control
        dt = self.dt if dt is None else float(dt)
        self._step_control = control
        if self._kn_values is not None:
            self._kn_values.zero_()
            self._assemble_stiffness(state.x, 1.0, self._kn_values)
        xb, vh, s = self.integrator.predict(state, dt, self.ops, self._prediction_work)
        self._inertia.set_prediction(vh)
        self._sync_forms()
        pot = self._potential.begin(xb, s, self._weights(s, control))
        fixed_v = self._prescribed_velocity(state, xb, s, control, self._fixed_v)
        ctx = self._step_context(state, dt, xb, s, fixed_v)
        for f in pot.forms:
            f.begin_step(ctx)
        return pot

    def _step(self, state_in, state_out, control, dt) -> SolveStats:
        t0 = time.perf_counter()
        n, ops = self.num_vertices, self.ops
        self._step_control = control
        syncs0, launches0 = self._potential.host_syncs, COUNTERS["launches"]
        if self._kn_values is not None:
            self._kn_values.zero_()
            self._assemble_stiffness(state_in.x, 1.0, self._kn_values)
        prediction = self.integrator.predict(state_in, dt, ops, self._prediction_work)
        xb, vh, s = prediction
        fixed_v = self._prescribed_velocity(state_in, xb, s, control, self._fixed_v)
        y = self._y
        # initial guess: previous (or extrapolated) velocity on free components, prescribed on fixed ones
        launch(LK.select_kernel, dim=n, inputs=[self._mask, self._guess(state_in, dt), fixed_v, y],
               device=self.device)
        self._inertia.set_prediction(vh)
        self._sync_forms()
        pot = self._potential.begin(xb, s, self._weights(s, control))
        self._begin_forms(pot, self._step_context(state_in, dt, xb, s, fixed_v), y)
        # adaptive parameters (a barrier stiffness "auto"): kept to be restored if the step fails
        kept = [(f, f.stiffness_state()) for f in pot.adaptive_forms()]
        if kept:
            pot.begin_adaptive(y)
        # the forms' lagged quantities (friction) taken again inside the solve, near its solution
        lags = any(f.uses_lagging() for f in pot.forms)
        iterate = lags and not self._differentiating()
        pot.set_lag_updates(self.friction_iterations if iterate else 0, self.friction_tol,
                            self.friction_update_tol if iterate else 0.0, self.friction_lag_below)
        pot.time_step = float(dt)  # the step test's h (NewtonOptions.step_tol)
        stats = newton_solve(pot, y, self.options)
        stats.friction_iterations, stats.friction_kept = pot.lag_updates, pot.lags_kept
        pot.set_lag_updates(0, self.friction_tol)
        stats.newton_syncs = pot.host_syncs - syncs0
        stats.launches = COUNTERS["launches"] - launches0
        try:
            self._finish(stats, t0, f"step {self.step_count}")
        except Exception:
            for f, state in kept:  # a failed step leaves the stiffness as it was, with the state
                f.restore_stiffness(state)
            raise
        keep = state_out.history.get("guess_v_prev")  # the buffer, kept across the integrator's clear()
        self.integrator.advance(state_in, y, prediction, dt, ops, state_out)
        if self.initial_guess == "extrapolated":
            vp = state_out.history["guess_v_prev"] = keep if keep is not None else ops.new_vector()
            ops.copy(vp, state_in.v)
            state_out.history["guess_h"] = dt
        state_out.time = state_in.time + dt
        return stats

    @property
    def friction_lag_below(self):
        """The relative gradient at which friction's lag update may be made (None: the forms' own,
        1e-2); set it to None or a number in (0, 1), checked on assignment."""
        return self._friction_lag_below

    @friction_lag_below.setter
    def friction_lag_below(self, value):
        self._friction_lag_below = check_lag_below(value)

    def _differentiating(self):
        """Whether this step is recorded for gradients (the adjoint differentiates friction lagged
        once from the step start, so differentiated steps do not iterate the lagging)."""
        from warpfem.solvers.adjoint import active_tape

        return getattr(self, "step_recorder", None) is not None or active_tape() is not None

    def _guess(self, state, dt):
        """The free components of the Newton solve's start: v_n ("previous"), or v_n extrapolated
        at constant acceleration ("extrapolated", when the history has what it needs)."""
        hist = state.history
        if self.initial_guess != "extrapolated":
            return state.v
        out = self._prediction_work.get("guess")
        if out is None:
            out = self._prediction_work["guess"] = self.ops.new_vector()
        if "a" in hist:  # Newmark: the scheme's own a_n
            self.ops.lincomb(1.0, state.v, dt, hist["a"], out)
        elif "guess_v_prev" in hist and hist.get("guess_h"):
            self.ops.lincomb(1.0, state.v, -1.0, hist["guess_v_prev"], out)
            self.ops.lincomb(1.0, state.v, dt / hist["guess_h"], out, out)
        else:
            return state.v
        return out

    def _step_context(self, state_in, dt, xb, s, fixed):
        """The :class:`~warpfem.solvers.forms.StepContext` of a step of dt from ``state_in``."""
        t = state_in.time
        return StepContext(state=state_in, t0=t, t1=t + dt, dt=dt, xb=xb, s=s, fixed=fixed, mask=self._mask, ops=self.ops,
                           label=f"step {self.step_count}")

    def _begin_forms(self, pot, ctx, y):
        """Every form's ``begin_step``; when a form bounds the step, ``y`` (the initial guess)
        becomes a feasible start: the unknown that keeps every vertex where it is (fixed ones at
        their targets), checked by the forms' ``check_start``, moved towards the guess as far as
        ``max_step`` allows."""
        for f in pot.forms:
            f.begin_step(ctx)
        if not pot.bounds_step():
            return
        ops, xb, s = self.ops, ctx.xb, ctx.s
        y0 = self._start
        ops.lincomb(1.0, ctx.state.x, -1.0, xb, y0)
        ops.lincomb(1.0 / s, y0, 0.0, y0, y0)
        launch(LK.select_kernel, dim=self.num_vertices, inputs=[self._mask, y0, ctx.fixed, y0], device=self.device)
        x0 = self._work.x
        ops.lincomb(1.0, xb, s, y0, x0)
        self._check_start(pot, x0, ctx)
        # y := y0 + alpha (y - y0), alpha the step bound along the direction from the feasible start
        ops.lincomb(1.0, y, -1.0, y0, y)
        alpha = min(1.0, pot.max_step(y0, y))
        launch(LK.lincomb_kernel, dim=self.num_vertices, inputs=[self._s(1.0), y0, self._s(alpha), y, y],
               device=self.device)

    @staticmethod
    def _check_start(pot, x0, ctx):
        """The forms' ``check_start`` at the start positions x0: an infeasible start fails the
        step (``SolveFailed``, before anything is written)."""
        for f in pot.forms:
            try:
                f.check_start(x0, ctx)
            except InfeasibleStart as e:
                raise SolveFailed(f"{ctx.label}: {e}; state left unchanged", SolveStats(reason=e.reason)) from e

    def solve_static(self, *, load_steps: int = 1) -> SolveStats:
        """Quasi-static equilibrium: minimise V(x) - x^T f_ext with the fixed components held.

        Loads and prescribed targets are ramped linearly over ``load_steps`` Newton solves
        (more steps: more robust for large deformation). Velocities are set to zero.
        """
        extra = [f for f in self._forms if f.enabled()]
        problems = [p for p in (f.static_error() for f in extra) if p]
        if problems:
            raise ValueError("; ".join(problems))
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
        if self._static_potential is None:
            self._static_forms = [ElasticForm(self.ops, self._qp_sets, PatternView(self.system), self.options),
                                  LoadForm(self.ops, self._fext, self._fext_norm)]
            self._static_potential = IncrementalPotential(
                self.ops, self._static_forms, system=self.system, mask=self._mask,
                linear_solve=lambda *a, **kw: self._linear_solve(*a, **kw), work=self._work)
        pot = self._static_potential
        want = IncrementalPotential.ordered(self._static_forms + extra)  # the added forms that allow it
        if want != pot.forms:
            pot.set_forms(want)
        pot.form("load").norm = self._fext_norm
        try:
            for step in range(1, int(load_steps) + 1):
                frac = step / load_steps
                self._targets = {i: x_start[i] + frac * (p - x_start[i]) for i, p in targets.items()}
                fixed_x = self._vec_array(self._prescribed(self._vec_array(x_start), 0.0))
                launch(LK.select_kernel, dim=n, inputs=[self._mask, y, fixed_x, y], device=self.device)
                pot.begin(None, 1.0, {"elastic": 1.0, "load": frac * self.load_scale})
                if extra:  # the added forms' life cycle: x = y, the start is y itself
                    t = self.state.time
                    ctx = StepContext(state=self.state, t0=t, t1=t, dt=0.0, xb=None, s=1.0, fixed=fixed_x, mask=self._mask,
                                      ops=self.ops, static=True, label=f"static solve, load step {step}/{load_steps}")
                    for f in pot.forms:
                        f.begin_step(ctx)
                    if pot.bounds_step():
                        self._check_start(pot, y, ctx)
                st = newton_solve(pot, y, self.options)
                total.add_counts(st)
                total.residual, total.gradient_norm, total.energy = st.residual, st.gradient_norm, st.energy
                total.initial_gradient, total.tolerance = st.initial_gradient, st.tolerance  # each load step its own
                total.reason = st.reason
                if not st.converged:
                    total.converged = False
                    total.reason = f"load step {step}/{load_steps}: {st.reason}"
                    break
        finally:
            self._targets = targets
        self._finish(total, t0, "static solve", stacklevel=4)
        wp.copy(self.state.x, y)
        self.state.v.zero_()
        self.state.history.clear()  # a new state: BDF2 / Newmark restart their history
        self._targets.clear()
        return total
