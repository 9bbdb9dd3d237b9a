"""Adjoint (reverse-mode) gradients of the implicit time step of :class:`~warpfem.simulator.Simulator`.

One step solves, for the end-of-step velocity y (the Newton unknown; x_{n+1} = x_b + s y), the
stationarity of the incremental potential on the free components (docs/integrators.md)

    g(y; p) = M (y - v_hat) + s alpha M y + s grad V(x_b + s y; theta) - s c f_ext = 0,
    y_c = (p_c - x_b,c) / s                            (fixed components: targets or kept in place)

with p = (x_b, v_hat, theta = material parameters, density, f_ext, targets) and c the control's
load scale. At convergence the implicit function theorem gives dy/dp = -H^-1 dg/dp with
H = (1 + s alpha) M + s^2 K(x_{n+1}) on the free components, so a step's reverse pass is one linear
solve, not a replay of the Newton iterations: given ybar (the adjoint of y), solve

    H_ff lambda_f = ybar_f,      then  pbar = -lambda^T dg/dp,
    ybar_c - (H lambda)_c flows into the prescribed values of the fixed components.

**The Hessian.** K is the *exact* (unprojected) elastic Hessian at the converged positions,
assembled again here (``project = 0``): the forward Newton loop may SPD-project per point
(``project_hessian``, the default), which changes its iterates but not the point it converges to;
only the exact Hessian gives the exact derivative. The linear solve reuses whatever the forward
solver last prepared (the direct solver's factorisation, PCG's preconditioned matrix) as the
inner solve of an iterative refinement against the exact H (residuals r = ybar - H lambda with
the exact matrix); it prepares the solver on the exact H only when the refinement contracts
slowly (the prepared matrix is too far from H: another step's Hessian, or projection that clipped
much). The refinement runs to ``tol`` (relative residual; default :func:`default_adjoint_tol`,
the forward's Newton tolerance clipped to [1e-12, 1e-8] in float64), so the gradients are as
accurate as the forward solve's convergence allows: the forward Newton solve must be
converged tightly (``tol`` of the simulator; the FD tests use 1e-12) because the implicit
function theorem holds at the solution, not at an early-stopped iterate.

**Parameters** (names of :attr:`StepAdjoint.grads`):

* ``youngs_modulus``, ``poisson_ratio``: the whole body's material (through the kernel parameters
  of every quadrature-point set, selective reduced integration included). Every registered
  material's stress is linear in its two kernel parameters (mu, lam), so dP/dmu = P(F; 1, 0) and
  dP/dlam = P(F; 0, 1) are evaluated by the forward force kernel with unit parameters: no new
  kernel, no Warp autodiff (the kernel modules keep ``enable_backward = False``, no extra
  compile). d(mu, lam)/d(E, nu) is the material class's own parameter map (differentiated
  numerically at 1e-6 relative: a rational function, error ~1e-12).
* ``element_stiffness_scale`` (m,): per-element factors c_e on the elastic energy (an element's E
  scaled by c_e), applied in the forward run by :func:`set_element_stiffness_scale` (the
  quadrature weights of the element kernels scaled, mass untouched); the per-point contraction
  w_q P(F_q) : grad(lambda) is done on the host from the stress kernel's output.
* ``density``: mass matrix and gravity scale with it (Newmark's a_0 too).
* ``forces`` (n, 3): the model's constant applied forces (``model.forces``: per vertex, N);
  ``gravity`` (3,).
* ``initial_positions``, ``initial_velocities`` (n, 3): the state the recording started from (and
  the integrator's history of that state, ``initial_history``).
* ``targets``: {step index: {vertex: (3,)}}, the kinematic targets of fixed vertices (control).
* ``collider_translations``, ``collider_rotations``: {step index: {collider name: (3,)}}, a
  translation and an axis-angle rotation (radians, about the collider's current centre) applied to
  each collider's pose at the end of that step (key -1: at the recording's start); every collider
  type (plane, sphere, box, mesh) with an explicit stiffness, moving or not. The contact terms
  (barrier with its curvature term, lagged friction) enter H and the parameter, x_n and pose
  derivatives through :mod:`warpfem.solvers.adjoint_contact` (complex-step derivatives of the
  host contact gradient, exact to round-off);
* ``collider_friction``: {collider name: float}, the Coulomb coefficient of each collider with
  friction (lagged from the step's start: D = mu lam_n f0(|u|), u = P (x - x_n - w), lam_n and P
  from x_n in the end pose, w the collider's motion of the point over the step).
* ``contact_friction``: float, the Coulomb coefficient of surface contact (``set_contact(friction=...)``).
* Several bodies (``Model.from_bodies``): ``youngs_modulus``, ``poisson_ratio`` and ``density``
  are arrays, one per body; ``element_stiffness_scale`` numbers the elements body after body.

**Kept factorisations.** With the direct solver, each recorded step keeps the factorisation of its
last Newton iteration's matrix (``DirectSolver.keep_factor``: a PARDISO factor slot of the same
symbolic analysis, or the SuperLU / QDLDL factor object) within ``factor_budget`` bytes for all
steps together (default :data:`DEFAULT_FACTOR_BUDGET`, 1 GiB; 0 keeps none); its reverse pass
refines against the exact H with it instead of factorising again. Steps beyond the budget refine
on the solver's current factorisation or prepare it on H. ``Recording.release()`` frees them.

**Surface contact** (``set_contact``: bodies against each other, self contact): the candidate
pairs at x_{n+1} and every pair's exact barrier Hessian (the pair kernel's unprojected mode) enter
H. With friction (:mod:`warpfem.solvers.adjoint_surface`), the pairs lagged at x_n (the candidates
there within dhat) give, by complex step on a host copy of the lag and of the friction gradient,
the exact friction Hessian blocks at x_{n+1} (into H), the derivative in x_n through the lagged
normal forces, closest-point weights and normals and the explicit -x^n, and the one in mu. A
recorded step lags friction once from x_n (colliders and surface pairs alike: the simulator skips
its ``friction_iterations`` while recording).

Not supported (a clear ``NotImplementedError``): a default (E- and mass-dependent) or adaptive
(``"auto"``) barrier stiffness (colliders and surface contact); stiffness-proportional
damping (K(x_n) is SPD-projected at the step's start: its derivative in x_n would need third
derivatives), other simulators (stiffness warping, reduced). Fixed sets, loads and material must
stay as they were during a recording.

All vector algebra of the reverse pass is on the host in float64 (numpy); the device does the
Hessian assembly, the force and stress kernels and the linear solves.
"""

from __future__ import annotations

import numpy as np
import warp as wp

from warpfem.kernels import fem as FK
from warpfem.kernels import linalg as LK
from warpfem.kernels.generic import launch
from warpfem.solvers.adjoint_contact import collider_terms
from warpfem.solvers.adjoint_surface import surface_friction_terms
from warpfem.transfer import host_aliases, read, upload

__all__ = ["StepAdjoint", "default_adjoint_tol", "StepRecord", "AdjointError", "PARAMETERS", "set_element_stiffness_scale",
           "set_material_parameters", "set_density", "material_set_parameters", "check_differentiable", "Recording",
           "recorded_step", "active_tape", "tape_adjoint"]

#: the parameter names the adjoint can differentiate
PARAMETERS = ("youngs_modulus", "poisson_ratio", "density", "element_stiffness_scale", "forces", "gravity",
              "initial_positions", "initial_velocities", "targets", "collider_translations", "collider_rotations",
              "collider_friction", "contact_friction")

#: default memory for the factorisations that recorded steps keep for their reverse pass (direct
#: solver; docs/gradients.md, "Cost"): 1 GiB
DEFAULT_FACTOR_BUDGET = 1 << 30


def default_adjoint_tol(sim) -> float:
    """The adjoint solve's default relative residual: in float64 the forward Newton tolerance
    (``sim.options.tol``) clipped to [1e-12, 1e-8], in float32 1e-6. A gradient is no more accurate
    than the forward solve it differentiates, so solving the adjoint far past it buys nothing;
    measured in docs/gradients.md ("Cost"): relative gradient errors of 1e-9 at 1e-8, against
    1e-12 at 1e-12, while the step's own error is 1e-12 (Newton's last iteration overshoots its
    tolerance quadratically), so 1e-8 is the loosest default."""
    if sim.precision != "float64":
        return 1e-6
    ftol = float(getattr(getattr(sim, "options", None), "tol", 1e-12))
    return float(min(max(ftol, 1e-12), 1e-8))


class AdjointError(RuntimeError):
    """The reverse pass could not be done (e.g. its linear solve did not converge)."""


def check_differentiable(sim):
    """Raise ``NotImplementedError`` (saying what) when gradients of ``sim``'s steps are not supported."""
    integ = getattr(sim, "integrator", None)
    name = getattr(integ, "name", None)
    if not hasattr(sim, "quadrature_sets") or not getattr(integ, "reversible", False):
        from warpfem.integrators import INTEGRATOR_NAMES, make_integrator

        names = [k for k in INTEGRATOR_NAMES if make_integrator(k).reversible]
        raise NotImplementedError(f"gradients are supported for warpfem.Simulator with {', '.join(names[:-1])} or "
                                  f"{names[-1]}, not for {type(sim).__name__} (integrator {name!r})")
    contact = getattr(sim, "contact", None)
    if contact is not None and len(contact):
        for c in contact.colliders:
            if c.stiffness is None:
                raise NotImplementedError(f"gradients with contact: collider {c.name!r} ({c.type_name}): set its "
                                          "stiffness explicitly (the default follows E and the mass)")
    sc = getattr(sim, "surface_contact", None)
    if sc is not None:
        if sc.adaptive:
            raise NotImplementedError("gradients through surface contact with an adaptive stiffness (set_contact("
                                      "stiffness='auto')) are not supported: give set_contact a stiffness in N/m^3")
        if sc.kappa == sc.default_stiffness(sc.dhat):
            raise NotImplementedError("gradients through surface contact: give set_contact a stiffness (the default "
                                      "follows E and the mass)")
    if sim.damping_stiffness != 0.0:
        raise NotImplementedError("gradients with stiffness-proportional damping (damping_stiffness > 0) are not "
                                  "supported: use damping_mass")


def material_set_parameters(material, E, nu, volumetric_integration="full", has_volumetric_set=False):
    """[(mu, lam) of each quadrature-point set] of a material of ``material``'s class with Young's
    modulus E and Poisson ratio nu (the kernel parameters the simulator gives its point sets)."""
    m = type(material)(youngs_modulus=E, poisson_ratio=nu, density=material.density)
    if volumetric_integration == "reduced":
        (mu_f, lam_f), (mu_v, lam_v) = m.volumetric_split()
        return [(mu_f, lam_f), (mu_v, lam_v)]
    if has_volumetric_set:
        return [(m.kernel_mu, 0.0), (0.0, m.kernel_lam)]
    return [(m.kernel_mu, m.kernel_lam)]


def _point_sets(model):
    """The quadrature-point sets of ``model`` in the simulator's order (``Simulator.quadrature_sets``):
    per body its main rule, then the volumetric rule of selective reduced integration. Each a dict:
    ``body``, ``element`` (the point's element, numbered over every body), ``weight``, ``dNdX``
    (float64), ``conn`` (the body's connectivity, global vertex indices)."""
    quads = list(getattr(model, "quadratures", None) or [model.quadrature])
    if getattr(model, "rigid", None) is not None:  # the soft bodies' (none for rigid bodies only)
        quads = list(model.quadratures)
    out, e0 = [], 0
    for b, qd in enumerate(quads):
        conn = np.asarray(qd.elements).reshape(-1, qd.nodes_per_element)
        for q in [qd] + ([qd.volumetric] if getattr(qd, "volumetric", None) is not None else []):
            out.append({"body": b, "element": np.asarray(q.qp_element, dtype=np.int64) + e0,
                        "weight": np.asarray(q.qp_weight, dtype=np.float64),
                        "dNdX": np.asarray(q.qp_dNdX, dtype=np.float64), "conn": conn, "e0": e0})
        e0 += conn.shape[0]
    return out


def _body_materials(model):
    if getattr(model, "rigid", None) is not None:  # the soft bodies' (none for a model of rigid bodies only)
        return list(model.materials)
    return list(getattr(model, "materials", None) or [model.material])


def _body_densities(model):
    """The density of every body in the model's order (soft bodies, then rigid ones)."""
    rigid = getattr(model, "rigid", None)
    soft = [float(m.density) for m in _body_materials(model)]
    return soft + ([float(b.density) for b in rigid.bodies] if rigid is not None else [])


def set_element_stiffness_scale(sim, scale):
    """Scale the elastic energy of element e by ``scale[e]`` (> 0; an element-wise Young's modulus
    factor) in every later step of ``sim``: the quadrature weights of the element kernels become
    w_q scale[e(q)] (the mass is not changed). ``None`` restores 1. With several bodies the
    elements are numbered body after body."""
    m = sim.model.mesh.num_elements
    c = np.ones(m) if scale is None else np.asarray(scale, dtype=np.float64).reshape(-1)
    if c.shape != (m,) or not np.all(np.isfinite(c)) or np.any(c <= 0):
        raise ValueError(f"element_stiffness_scale must be {m} finite positive numbers (one per element), "
                         f"got shape {np.shape(scale)}")
    for qs, ps in zip(sim.quadrature_sets, _point_sets(sim.model)):
        upload(qs.points.weight, (ps["weight"] * c[ps["element"]]).astype(sim.numpy_dtype))
    sim.element_stiffness_scale = c


class StepRecord:
    """What the reverse pass needs of one forward step (host float64 copies): the kind of step
    (the integrator's variant, ``Integrator.reverse_record``: "be", "bdf2_first", "bdf2",
    "newmark_a0", "newmark"), dt, s, the input state (x, v and the history it used), the converged
    y (= v_{n+1}), x_{n+1}, v_hat (Newmark), the free mask, the control's targets and load scale."""

    def __init__(self, kind, dt, s, x, v, hist, mask, targets, load_scale):
        self.kind, self.dt, self.s = kind, float(dt), float(s)
        self.x, self.v, self.hist, self.mask = x, v, hist, mask
        self.targets = {int(i): np.array(p, dtype=np.float64) for i, p in targets.items()}
        self.load_scale = float(load_scale)
        self.y = self.x_next = self.v_hat = None
        self.factor = None  # the direct solver's factorisation of the step's last Newton matrix, when kept

    @property
    def factor_nbytes(self) -> int:
        return 0 if self.factor is None else int(self.factor.nbytes)

    def release(self):
        """Free the kept factorisation (the reverse pass then refactorises this step)."""
        if self.factor is not None:
            self.factor.release()
            self.factor = None

    @property
    def nbytes(self) -> int:
        arrays = [self.x, self.v, self.mask, self.y, self.x_next, self.v_hat, *self.hist.values()]
        return int(sum(a.nbytes for a in arrays if isinstance(a, np.ndarray)))


def _host(a):
    return read(a).astype(np.float64)


class StepAdjoint:
    """The reverse pass of ``sim``'s steps (see the module docstring).

    ``record_before(state_in, control, dt)`` and ``record_after(record, state_out)`` around a
    forward step give a :class:`StepRecord`; ``backward(record, xbar, vbar, hbar)`` returns the
    adjoints of the step's input (x_n, v_n, history dict) given those of its output, and adds the
    parameter gradients into :attr:`grads` (``zero_grad()`` clears them).

    Args:
        sim: a :class:`~warpfem.simulator.Simulator` (backward Euler, BDF2 or Newmark; colliders,
            surface contact, with or without friction).
        params: parameter names to accumulate (default: all of :data:`PARAMETERS`); the per-element
            contraction is done only when ``element_stiffness_scale`` is asked for.
        tol: relative residual of the adjoint solve (default :func:`default_adjoint_tol`: the
            forward Newton tolerance clipped to [1e-12, 1e-8] in float64, 1e-6 in float32).
        max_refinements: cap on refinement rounds of the adjoint solve.
        factor_budget: bytes of direct-solver factorisations the recorded steps may keep for their
            reverse pass, all steps together (default :data:`DEFAULT_FACTOR_BUDGET`, 1 GiB; 0: none,
            each reverse step refines on the solver's last factorisation or refactorises; measured
            in docs/gradients.md, "Cost").
    """

    def __init__(self, sim, params=None, *, tol=None, max_refinements=40, factor_budget=None):
        check_differentiable(sim)
        self.sim = sim
        params = PARAMETERS if params is None else tuple(params)
        unknown = [p for p in params if p not in PARAMETERS]
        if unknown:
            raise ValueError(f"unknown parameter(s) {unknown}; known: {', '.join(PARAMETERS)}")
        self.params = params
        self.tol = float(tol) if tol is not None else default_adjoint_tol(sim)
        self.max_refinements = int(max_refinements)
        model = sim.model
        self.n = n = sim.num_vertices
        self.integrator = sim.integrator  # its reverse: reverse_record, advance_reverse, predict_reverse
        self._M = sim.mass_matrix().tocsr()
        mats = _body_materials(model)
        self._mats = mats
        #: rigid bodies (docs/rigid.md): the layout of the unknown (4 nodes per rigid body) and E, else None
        self._rigid = getattr(model, "rigid", None)
        self._num_soft = len(mats)  # bodies with a material (E, nu)
        dens = _body_densities(model)
        self.bodies = len(dens)
        # each node's body: the unknown's body offsets (with rigid bodies, dof_offsets)
        offs = np.asarray(getattr(model, "dof_offsets" if self._rigid is not None else "body_offsets", [0, n]),
                          dtype=np.int64)
        self._vertex_body = np.repeat(np.arange(self.bodies), np.diff(offs))
        self._rho_v = np.array(dens)[self._vertex_body]  # density of each vertex
        if self._rigid is not None:
            self._Emat = self._rigid.matrix()  # X = E q (host, float64)
            self._Et = self._Emat.T.tocsr()
        # gravity per unit density (each vertex's body's)
        self._fgrav_unit = (model.gravity_mass[:, None] * model.gravity[None, :]) / self._rho_v[:, None]
        self._fext = model.external_forces()
        self._sets = sim.quadrature_sets
        self._psets = _point_sets(model)
        self._work_bufs = [None] * len(self._sets)  # (Q, 2) outputs of qp_parameter_work_kernel, per set
        self._param_jac = self._material_jacobian()
        pat = sim.pattern
        self._K = pat.new_values()
        self._H = pat.new_values()
        self._dev = [sim.new_vector() for _ in range(6)]  # b, r, dl, lam, tmp, x
        self._csr_map = None
        self._mass_gathered = None
        #: bytes of factorisations the direct solver may keep for the reverse pass (all recorded
        #: steps together; beyond it a step's reverse pass refactorises)
        self.factor_budget = int(DEFAULT_FACTOR_BUDGET if factor_budget is None else factor_budget)
        self.kept_solves = 0  # adjoint solves done with a factorisation kept by the forward step
        self.solves = 0  # adjoint solves done
        self.refinements = 0  # refinement rounds (inner solves) done
        self.prepares = 0  # times the solver was prepared on the exact Hessian
        self._stale_ok = True  # whether the last reuse of a factorisation of another matrix converged
        self.zero_grad()

    # -- parameters -------------------------------------------------------------------------------------
    def _material_jacobian(self):
        """d(mu_s, lam_s)/d(E_b, nu_b) of every point set s (of body b): (sets, 2 [mu, lam], 2 [E, nu])."""
        model = self.sim.model
        vis = getattr(model, "volumetric_integration", "full")
        rows = []
        for b, mat in enumerate(self._mats):
            vi = vis[b] if isinstance(vis, (list, tuple)) else vis
            has_vol = sum(ps["body"] == b for ps in self._psets) > 1
            E, nu = float(mat.youngs_modulus), float(mat.poisson_ratio)

            def f(E_, nu_):
                return np.asarray(material_set_parameters(mat, E_, nu_, vi, has_vol), dtype=np.float64)

            hE, hn = 1e-6 * E, 1e-6 * max(abs(nu), 0.1)
            J = np.zeros((2 if has_vol else 1, 2, 2))
            J[:, :, 0] = (f(E + hE, nu) - f(E - hE, nu)) / (2 * hE)
            J[:, :, 1] = (f(E, nu + hn) - f(E, nu - hn)) / (2 * hn)
            rows.append(J)
        return np.concatenate(rows) if rows else np.zeros((0, 2, 2))

    def zero_grad(self):
        """Clear the accumulated parameter gradients."""
        m = self.sim.model.mesh.num_elements
        self._stale_ok = True  # a reverse pass starts at the last forward step: its factorisation is current
        self._mass_gathered = None  # the mass's CSR entries (gathered again: set_density may have changed it)
        # the density of each vertex's body now (M_w is of the current mass; self._M and _rho_v of the first)
        self._rho_now = np.array(_body_densities(self.sim.model))[self._vertex_body]
        self._mulam_bar = np.zeros((len(self._sets), 2))
        self.grads = {"density": np.zeros(self.bodies), "element_stiffness_scale": np.zeros(m), "forces": np.zeros((self.n, 3)),
                      "targets": {}, "collider_translations": {}, "collider_rotations": {}, "collider_friction": {},
                      "contact_friction": 0.0}

    def parameter_gradients(self) -> dict:
        """The accumulated gradients by parameter name (numpy; see the module docstring)."""
        g = dict(self.grads)
        EN = np.einsum("sk,skp->sp", self._mulam_bar, self._param_jac)  # per point set
        body = np.array([ps["body"] for ps in self._psets])
        EN = np.stack([EN[body == b].sum(axis=0) for b in range(self._num_soft)] +  # (bodies, 2); rigid bodies: 0
                      [np.zeros(2)] * (self.bodies - self._num_soft))
        g["gravity"] = self.sim.model.gravity_mass @ g["forces"]
        if self.bodies == 1:
            g["youngs_modulus"], g["poisson_ratio"] = float(EN[0, 0]), float(EN[0, 1])
            g["density"] = float(g["density"][0])
        else:  # several bodies: one per body (Model.from_bodies order)
            g["youngs_modulus"], g["poisson_ratio"] = EN[:, 0].copy(), EN[:, 1].copy()
            g["density"] = np.array(g["density"], dtype=np.float64)
        return {k: v for k, v in g.items() if k in self.params or k in ("youngs_modulus", "poisson_ratio")}

    # -- recording ------------------------------------------------------------------------------------------
    def record_before(self, state_in, control, dt) -> StepRecord:
        """Copy what the reverse pass of a step from ``state_in`` needs (call before the step)."""
        check_differentiable(self.sim)
        dt = float(dt)
        kind, s, h = self.integrator.reverse_record(state_in, dt, _host)
        rec = StepRecord(kind, dt, s, _host(state_in.x), _host(state_in.v), h, _host(self.sim.free_mask),
                         control.targets, control.load_scale)
        rec.t0 = float(state_in.time)
        solver = self.sim.linear_solver
        if self.factor_budget > 0 and hasattr(solver, "reserve_factors"):
            solver.reserve_factors(self.factor_budget - solver.kept_bytes)
        return rec

    def record_after(self, rec: StepRecord, state_out):
        """Complete ``rec`` with the converged step written into ``state_out``."""
        rec.y = _host(state_out.v)
        rec.x_next = _host(state_out.x)
        solver = self.sim.linear_solver
        if self.factor_budget > 0 and hasattr(solver, "keep_factor"):
            # the factorisation of the step's last Newton iteration, solved with in the reverse pass
            # (refined against the exact Hessian) instead of factorising again
            rec.factor = solver.keep_factor(self.factor_budget - solver.kept_bytes)
        self.integrator.reverse_complete(rec, state_out, _host)
        return rec

    # -- device helpers ---------------------------------------------------------------------------------------
    def _upload(self, buf, a):
        return upload(buf, a)

    def _assemble_K(self, x_host):
        """Exact elastic Hessian at x into self._K (device)."""
        sim = self.sim
        xd = self._upload(self._dev[5], x_host)
        self._K.zero_()
        old = sim.options.project_hessian
        sim.options.project_hessian = False
        try:
            sim.assemble_stiffness(xd, self._K, scale=1.0)
        finally:
            sim.options.project_hessian = old
        return xd

    def _store_K(self, K):
        """Write host blocks ``K`` (from ``read(self._K)``, changed) back to the device: on the CPU
        outside strict device mode that array is the device memory itself, nothing to copy."""
        if not host_aliases(self._K.device):
            upload(self._K, K)

    def _follow_pattern(self):
        """The block arrays on the simulator's current pattern (surface contact may have grown it)."""
        pat = self.sim.pattern
        if self._K.shape[0] != pat.nnz:
            self._K, self._H = pat.new_values(), pat.new_values()

    def _mv(self, values, a_host):
        """values @ a (device block matrix, host vectors)."""
        sim = self.sim
        a = self._upload(self._dev[3], a_host)
        out = self._dev[4]
        out.zero_()
        pt = sim.pattern
        launch(LK.bsr_mv_kernel, pt.num_rows, [pt.offsets, pt.columns, values, a, sim.scalar_type(1.0), out], sim.device)
        return _host(out)

    def _host_H(self, values, mass_scale, scale):
        """The float64 host matrix (3n x 3n, full; scipy BSR of 3 x 3 blocks in the simulator's
        current pattern) of ``scale`` x the device block values plus ``mass_scale`` x the mass
        blocks. One matrix object is kept per pattern and its blocks replaced (no construction, no
        gather per step); the mass blocks are read once per reverse pass (:meth:`zero_grad`)."""
        import scipy.sparse

        pt = self.sim.pattern
        if self._csr_map is None or self._csr_map[0] is not pt:
            n = pt.num_rows
            offsets = read(pt.offsets, n + 1).astype(np.int64)
            cols = np.asarray(pt.cols_np, dtype=np.int64)
            H = scipy.sparse.bsr_matrix((np.zeros((pt.nnz, 3, 3)), cols, offsets), shape=(3 * n, 3 * n))
            self._csr_map = (pt, H)
            self._mass_gathered = None
        _, H = self._csr_map
        if self._mass_gathered is None:
            self._mass_gathered = read(self.sim.mass_values).reshape(-1, 3, 3)[: pt.nnz].astype(np.float64)
            # the same mass blocks as a matrix: M lambda consistent with H's (K lambda is taken from
            # their difference, divided by s^2)
            self._Mc = scipy.sparse.bsr_matrix((self._mass_gathered, H.indices, H.indptr), shape=H.shape)
        v = read(values).reshape(-1, 3, 3)[: pt.nnz].astype(np.float64)  # a copy (float64 or float32 blocks)
        v *= scale
        v += mass_scale * self._mass_gathered
        H.data = v
        return H

    def _solve_kept(self, factor, Hmv, b, bn, mask):
        """lambda by refinement against the exact H with a factorisation the forward step kept (of
        its last Newton iteration's matrix); None when that contracts slowly (then the caller
        prepares the solver on H)."""
        lam = np.zeros_like(b)
        r = b
        prev = bn
        for _ in range(self.max_refinements):
            self.refinements += 1
            d = factor.solve(r.reshape(-1)).reshape(-1, 3) * mask
            lam = lam + d  # (a non-finite d makes the residual's norm non-finite: caught below)
            Hl = Hmv(lam)
            r = b - mask * Hl
            rn = float(np.linalg.norm(r))
            if rn <= self.tol * bn:
                self.kept_solves += 1
                self._last_Hlam = Hl
                return lam
            if not np.isfinite(rn) or rn > 0.2 * prev:
                return None
            prev = rn
        return None

    def _solve(self, H, b_host, mask, Hmv, factor=None):
        """lambda with (P H P + I - P) lambda = P b, to self.tol, by refinement on a factorisation
        the step kept (``factor``), or on the solver's prepared matrix (prepared on H when that
        contracts slowly). ``H()`` gives the device values of H, ``Hmv(a)`` its host product."""
        sim = self.sim
        solver = sim.linear_solver
        b = mask * b_host
        bn = float(np.linalg.norm(b))
        if bn == 0.0:
            return np.zeros_like(b)
        self.solves += 1
        if factor is not None:
            lam = self._solve_kept(factor, Hmv, b, bn, mask)
            if lam is not None:
                return lam
        H = H()
        mask_d = sim.free_mask
        rd, dl = self._dev[1], self._dev[2]
        direct = getattr(solver, "name", "") == "direct"
        # a factorisation is worth reusing (refinement against H) while that converges fast; a
        # preconditioner (PCG, AMG, multigrid) is cheap to set up on H itself, then solved to tol
        maxiter = max(sim.options.max_cg_iters, 10 * sim.num_vertices)
        prepared = False
        if not direct or not self._stale_ok or not getattr(solver, "has_factor", True):
            solver.prepare(H, mask_d)
            self.prepares += 1
            prepared = True
        lam = np.zeros_like(b)
        r = b.copy()
        prev = np.inf
        for _ in range(self.max_refinements):
            rn0 = float(np.linalg.norm(r))
            # an iterative solver is asked for the outer tolerance relative to b (not to r)
            inner = 0.5 if direct else min(0.5, 0.5 * self.tol * bn / max(rn0, 1e-300))
            self._upload(rd, r)
            self.refinements += 1
            try:
                res = solver.solve(rd, dl, tol=inner, maxiter=maxiter)
                ok = not getattr(res, "failed", "")
            except Exception:  # nothing prepared yet (no Newton iteration ran): prepare on H
                ok = False
            d = _host(dl) * mask if ok else None
            if d is None or not np.all(np.isfinite(d)):
                if prepared:
                    break
                solver.prepare(H, mask_d)
                self.prepares += 1
                prepared = True
                continue
            lam_new = lam + d
            r_new = b - mask * Hmv(lam_new)
            rn = float(np.linalg.norm(r_new))
            if rn < prev or not prepared:
                lam, r = lam_new, r_new
            if rn <= self.tol * bn:
                if direct and not prepared:
                    self._stale_ok = True
                return lam
            if not prepared and (rn > 0.2 * min(prev, bn) or not np.isfinite(rn)):
                solver.prepare(H, mask_d)  # the prepared matrix is too far from H: prepare on H itself
                self.prepares += 1
                prepared = True
                self._stale_ok = False  # the next step prepares at once (until a stale one works again)
            elif prepared and rn >= prev:
                break
            prev = min(prev, rn)
        rel = float(np.linalg.norm(b - mask * Hmv(lam)) / bn)
        if rel <= max(100.0 * self.tol, 1e-9 if sim.precision == "float64" else 1e-4):
            return lam
        raise AdjointError(f"the adjoint solve did not converge (relative residual {rel:.2e} > {self.tol:.1e}); "
                           "the step's exact Hessian may be singular or indefinite")

    def _parameter_work(self, x_dev, w_host, per_element):
        """(sets, 2): w . grad_x V_s(x; mu=1, lam=0) and (0, 1) for every point set s, and with
        ``per_element`` (m,): sum over each element's points of w0_q P(F_q) : grad(w)_q (d/dc_e of
        w . grad V), else None. One launch per set (``qp_parameter_work_kernel``: the two
        unit-parameter stresses' work on w per point), the sums on the host."""
        sim = self.sim
        wd = self._upload(self._dev[3], w_host)
        out = np.zeros((len(self._sets), 2))
        m = sim.model.mesh.num_elements
        elem = np.zeros(m) if per_element else None
        c = getattr(sim, "element_stiffness_scale", None)
        bufs = self._work_bufs
        for i, (qs, ps) in enumerate(zip(self._sets, self._psets)):
            if bufs[i] is None:
                bufs[i] = wp.zeros((qs.count, 2), dtype=sim.scalar_type, device=sim.device)
            launch(FK.qp_parameter_work_kernel, qs.count, [x_dev, qs.points, qs.material, wd, bufs[i]], sim.device)
            ab = read(bufs[i]).astype(np.float64)  # (Q, 2) unweighted works
            w0 = ps["weight"]
            wq = w0 if c is None else w0 * c[ps["element"]]  # the kernels' weights (element scale included)
            out[i] = wq @ ab
            if per_element:  # P = mu P(F; 1, 0) + lam P(F; 0, 1)
                mu, lam = float(qs.material.mu), float(qs.material.lam)
                elem += np.bincount(ps["element"], weights=w0 * (mu * ab[:, 0] + lam * ab[:, 1]), minlength=m)
        return out, elem

    def _add_contact_hessian(self, rec, x_next=None, x_n=None, values=None, pattern=None):
        """Add the exact Hessian of every collider's contact (barrier with its curvature term, lagged
        friction) at x_{n+1} into self._K (diagonal blocks); returns [(collider, ColliderTerms)] of
        the colliders in contact (``adjoint_contact``: complex-step derivatives) or None. With rigid
        bodies the caller gives the vertex-space positions and Hessian values (``values``, ``pattern``)."""
        contact = getattr(self.sim, "contact", None)
        if contact is None or not len(contact):
            return None
        x_next = rec.x_next if x_next is None else x_next
        x_n = rec.x if x_n is None else x_n
        values = self._K if values is None else values
        pattern = self.sim.pattern if pattern is None else pattern
        surf = np.asarray(contact.surface)
        t0, t1 = rec.t0, rec.t0 + rec.dt
        out = []
        blocks = np.zeros((len(x_next), 3, 3))
        for j, c in enumerate(contact.colliders):
            terms = collider_terms(c, surf, x_next, x_n, c.pose(t1), c.pose(t0), float(contact.kappa[j]),
                                   float(contact.dhat[j]), float(contact.epsv[j]) * rec.dt)
            if terms is None:
                continue
            np.add.at(blocks, terms.verts, terms.H)
            out.append((c, terms))
        touched = np.flatnonzero(np.abs(blocks).sum(axis=(1, 2)) > 0)
        if len(touched):
            K = read(values)
            diag = np.asarray(pattern.diag_index)
            K[diag[touched]] += blocks[touched].astype(K.dtype)
            if not host_aliases(values.device):
                upload(values, K)
        return out

    # -- rigid bodies (docs/rigid.md): the unknown q, the vertices X = E q --------------------------------------
    def _E(self, q):
        """E q (host): the vertex-space values of the unknown's values q."""
        return (self._Emat @ q.reshape(-1)).reshape(-1, 3)

    def _Et_(self, gv):
        """E^T gv (host): a vertex-space adjoint pulled back to the unknown."""
        return (self._Et @ gv.reshape(-1)).reshape(-1, 3)

    def _rigid_hessian(self, rec, x_dev, sc, sfric):
        """With rigid bodies: add to self._K the orthogonality form's exact Hessian at x_{n+1} (no PSD
        clamp) and the contact terms written in vertex space (colliders, surface barrier, surface
        friction) mapped through E (``RigidSystem.map_hessian``); returns the colliders' terms."""
        sim = self.sim
        rs = sim.rigid
        form = rs.form
        old = form.project
        form.project = False
        try:
            form.hessian(None, x_dev, 1.0, self._K)
        finally:
            form.project = old
        space = rs.space
        hv = space.system.hessian_values
        hv.zero_()
        planes = self._add_contact_hessian(rec, self._xv_next, self._xv_n, hv, space.system.pattern)
        if sc is not None:
            sc.exact_hessian(upload(self._vbuf, self._xv_next), hv)
        if sfric is not None:
            Kv = read(hv)
            sfric.add_hessian(Kv, space.system.pattern)
            if not host_aliases(hv.device):
                upload(hv, Kv)
        rs.map_hessian(hv, self._K)
        return planes

    def _surface_friction(self, rec, sc):
        """Surface friction's complex-step terms of the step (``adjoint_surface``) from its pairs
        lagged at x_n (the surface contact's candidates there), or None (with rigid bodies: in
        vertex space)."""
        if sc is None or not sc.has_friction():
            return None
        if self._rigid is not None:
            pairs, kinds = sc.candidates(upload(self._vbuf, self._xv_n))
            rest = self.sim.model.vertex_rest_positions
            return surface_friction_terms(pairs, kinds, self._xv_next, self._xv_n, rest, kappa=sc.kappa, dhat=sc.dhat,
                                          mu=sc.friction, eps=sc.friction_velocity * rec.dt)
        pairs, kinds = sc.candidates(self._upload(self._dev[5], rec.x))
        return surface_friction_terms(pairs, kinds, rec.x_next, rec.x, self.sim.model.rest_positions, kappa=sc.kappa,
                                      dhat=sc.dhat, mu=sc.friction, eps=sc.friction_velocity * rec.dt)

    # -- the reverse pass of one step -------------------------------------------------------------------------
    def backward(self, rec: StepRecord, xbar, vbar, hbar=None, step_index=None):
        """Adjoints (xbar_n, vbar_n, hbar_n) of a step's input from those of its output (x_{n+1},
        v_{n+1}, history dict: "x_prev", "v_prev" (BDF2), "a" (Newmark)); parameter gradients are
        added to :attr:`grads` (targets under ``step_index``)."""
        sim, n = self.sim, self.n
        hbar = hbar or {}
        zero = np.zeros((n, 3))
        xbar = zero if xbar is None else np.asarray(xbar, dtype=np.float64).reshape(n, 3)
        vbar = zero if vbar is None else np.asarray(vbar, dtype=np.float64).reshape(n, 3)
        s, P = rec.s, rec.mask
        alpha, c = sim.damping_mass, rec.load_scale
        y = rec.y
        integ = self.integrator
        v_hat = integ.recorded_v_hat(rec)
        # outputs: x_{n+1} = x_b + s y, v_{n+1} = y, history (the integrator's transposed advance)
        ybar, xb_bar, vhat_bar, xn_bar, vn_bar = integ.advance_reverse(rec, xbar, vbar, hbar)
        # the implicit solve: H lambda = ybar on the free components
        sc = getattr(sim, "surface_contact", None)
        rigid = self._rigid is not None
        if rigid:  # the contact terms live in vertex space: X = E q
            self._xv_n, self._xv_next = self._E(rec.x), self._E(rec.x_next)  # this step's, host
            if getattr(self, "_vbuf", None) is None:
                self._vbuf = sim.rigid.space.ops.new_vector()
        sfric = self._surface_friction(rec, sc)  # lagged at x_n: its broad phase there first
        if sc is not None:  # its candidate pairs at x_{n+1} (the pattern may grow for them)
            sc.update_pairs(upload(self._vbuf, self._xv_next) if rigid else self._upload(self._dev[5], rec.x_next))
            self._follow_pattern()
        x_dev = self._assemble_K(rec.x_next)
        if rigid:
            planes = self._rigid_hessian(rec, x_dev, sc, sfric)
        else:
            planes = self._add_contact_hessian(rec)
            if sc is not None:  # the exact (unprojected) Hessian of every pair's barrier at x_{n+1}
                sc.exact_hessian(x_dev, self._K)
            if sfric is not None:  # surface friction's exact Hessian blocks at x_{n+1}
                K = read(self._K)
                sfric.add_hessian(K, sim.pattern)
                self._store_K(K)
        cm, ck = 1.0 + s * alpha, s * s
        Hc = self._host_H(self._K, cm, ck)

        def Hmv(a):
            return (Hc @ a.reshape(-1)).reshape(-1, 3)

        def H():  # the device values of H (only when the solver must be prepared on it)
            pt = sim.pattern
            self._H.zero_()
            launch(LK.add_scaled_kernel, pt.nnz, [sim.mass_values, sim.scalar_type(cm), self._H], sim.device)
            launch(LK.add_scaled_kernel, pt.nnz, [self._K, sim.scalar_type(ck), self._H], sim.device)
            return self._H

        self._last_Hlam = None
        lam = self._solve(H, ybar, P, Hmv, getattr(rec, "factor", None))
        if np.any(lam):
            M_lam = (self._Mc @ lam.reshape(-1)).reshape(n, 3)  # the mass blocks of H (as the forward's)
            H_lam = Hmv(lam) if self._last_Hlam is None else self._last_Hlam  # the refinement's last product
            K_lam = (H_lam - cm * M_lam) / ck
        else:
            M_lam = K_lam = H_lam = np.zeros((n, 3))
        yc_bar = (1.0 - P) * (ybar - H_lam)
        vhat_bar += M_lam
        xb_bar -= s * K_lam
        # fixed components: y_c = (p_c - x_b,c) / s, p = targets or x_n
        p_bar = yc_bar / s
        xb_bar -= p_bar
        tgt = np.zeros(n, dtype=bool)
        if rec.targets:
            idx = np.fromiter(rec.targets.keys(), dtype=np.int64)
            tgt[idx] = True
            if "targets" in self.params:
                store = self.grads["targets"].setdefault(step_index, {})
                for i in idx.tolist():
                    store[i] = store.get(i, 0.0) + p_bar[i]
        xn_bar[~tgt] += p_bar[~tgt]
        if rigid and (planes or sfric is not None) and np.any(lam):
            # contact terms of vertex positions: their adjoint is E lambda, their x_n adjoint maps back by E^T
            lam_c, xn_c = self._E(lam), np.zeros((len(self._xv_n), 3))
        else:
            lam_c, xn_c = lam, xn_bar
        if planes and np.any(lam):  # -s lambda^T d(grad E_c)/d(x_n, poses, mu), per collider in contact
            G = self.grads
            end = G["collider_translations"].setdefault(step_index, {}), G["collider_rotations"].setdefault(step_index, {})
            k0 = -1 if step_index is None else step_index - 1
            start = G["collider_translations"].setdefault(k0, {}), G["collider_rotations"].setdefault(k0, {})
            for col, tm in planes:
                lv = lam_c[tm.verts]
                np.add.at(xn_c, tm.verts, -s * np.einsum("vik,vi->vk", tm.D_xn, lv))
                par = -s * np.einsum("vip,vi->p", tm.D_par, lv)
                for store, sl in ((end[0], par[0:3]), (end[1], par[3:6]), (start[0], par[6:9]), (start[1], par[9:12])):
                    store[col.name] = store.get(col.name, 0.0) + sl
                if col.friction != 0.0:
                    G["collider_friction"][col.name] = G["collider_friction"].get(col.name, 0.0) + float(par[12])
        if sfric is not None and np.any(lam):  # -s lambda^T d(grad D)/d(x_n, mu) of surface friction
            xn_c -= s * sfric.xn_product(lam_c)
            self.grads["contact_friction"] -= s * sfric.mu_product(lam_c)
        if xn_c is not xn_bar:
            xn_bar += self._Et_(xn_c)
        # parameters at the converged step
        if np.any(lam):
            self._accumulate_params(x_dev, lam, -s, y=y, v_hat=v_hat, s=s, c=c, alpha=alpha, M_w=M_lam)
        # the prediction (x_b, v_hat) from (x_n, v_n, history): the integrator's transposed predict
        h_in = integ.predict_reverse(rec, xb_bar, vhat_bar, xn_bar, vn_bar, self)
        return xn_bar, vn_bar, h_in

    def _accumulate_params(self, x_dev, w, sign, *, y=None, v_hat=None, s=1.0, c=1.0, alpha=0.0, a0=None, v_n=None,
                           M_w=None):
        """Parameter gradients of sign * w . dR/dtheta terms shared by the step and Newmark's a_0
        (``M_w``: M w when the caller has it; M is symmetric and block diagonal over the bodies, so
        each body's w . M u is its (M w) . u: no product with M here)."""
        per_element = "element_stiffness_scale" in self.params
        work, elem = self._parameter_work(x_dev, w, per_element)
        self._mulam_bar += sign * work
        if per_element:
            self.grads["element_stiffness_scale"] += sign * elem
        # dM/d(rho_b): the body's rows of M over rho_b (M is block diagonal over the bodies)
        M1 = lambda a: (self._M @ a.reshape(-1)).reshape(self.n, 3) / self._rho_v[:, None]  # noqa: E731
        nb = self.bodies

        def per_body(t):  # sum of w . t over each body's vertices
            return np.bincount(self._vertex_body, weights=np.sum(w * t, axis=1), minlength=nb)

        if a0 is None:  # the step: g = M (y - v_hat) + s alpha M y + s grad V - s c f_ext
            self.grads["forces"] += (-sign) * c * w  # sign = -s: s c w
            if M_w is None:
                self.grads["density"] -= per_body(M1((1.0 + s * alpha) * y - v_hat) - s * c * self._fgrav_unit)
            else:  # w . M1(u) = (M w / rho) . u per body
                u = ((1.0 + s * alpha) * y - v_hat) / self._rho_now[:, None]
                self.grads["density"] -= np.bincount(self._vertex_body, weights=np.sum(M_w * u, axis=1), minlength=nb)
                self.grads["density"] -= per_body(-s * c * self._fgrav_unit)
        else:  # a_0: R = M a_0 + grad V(x_n) - c f_ext + alpha M v_n
            self.grads["forces"] += c * w
            self.grads["density"] -= per_body(M1(a0) - c * self._fgrav_unit + alpha * M1(v_n))

    def acceleration_reverse(self, rec, a_bar, xn_bar, vn_bar, v_hat):
        """The reverse of ``VectorOps.acceleration`` (M a_0 = f(x_n) + c f_ext - alpha M v_n on the free
        components, Newmark's first step): adds its adjoint into ``xn_bar`` / ``vn_bar`` and the
        parameter gradients (``a_bar``: the adjoint of a_0)."""
        n, P = self.n, rec.mask
        a_bar = P * a_bar
        if not np.any(a_bar):
            return
        diag = self._M.diagonal().reshape(n, 3)
        a0 = 2.0 * (v_hat - rec.v) / rec.dt
        # mu = M_ff^-1 a_bar (a lumped mass is diagonal; a consistent one is solved on the host)
        if self._M.nnz == 3 * n:
            mu = np.where(P > 0, a_bar / np.where(diag > 0, diag, 1.0), 0.0)
        else:
            import scipy.sparse.linalg as spla

            free = P.reshape(-1) > 0
            mu = np.zeros(3 * n)
            mu[free] = spla.spsolve(self._M[free][:, free].tocsc(), a_bar.reshape(-1)[free])
            mu = mu.reshape(n, 3)
        x_dev = self._assemble_K(rec.x)
        alpha = self.sim.damping_mass
        xn_bar -= self._mv(self._K, mu)
        vn_bar -= alpha * (self._M @ mu.reshape(-1)).reshape(n, 3)
        self._accumulate_params(x_dev, mu, -1.0, c=rec.load_scale, alpha=alpha, a0=a0, v_n=rec.v)


# -- recording steps: a plain-Python recording, and steps on a wp.Tape ---------------------------------------------
def _warp_runtime():
    """Warp's runtime object, where an active ``wp.Tape`` is kept (``runtime.tape``): Warp has no
    public call that says whether a tape is recording, or that pauses it."""
    return wp._src.context.runtime


def active_tape():
    """The ``wp.Tape`` being recorded (inside ``with tape:``), or None."""
    return getattr(_warp_runtime(), "tape", None)


class Recording:
    """Record the steps of ``sim`` (every ``sim.step(...)`` while the recording is active, as a
    context manager) for :meth:`backward`: the plain-Python form of the adjoint (no Warp code).

    ``backward(x_grads, v_grads)`` takes the adjoints of the positions / velocities of the states
    0..N of the recording (dicts: state index -> (n, 3); state k is the one after k recorded
    steps) and returns the gradients by parameter name (:data:`PARAMETERS`; ``targets`` by step
    index; ``initial_history`` the adjoint of the first state's integrator history). With rigid
    bodies the states are the unknown q (a loss on vertex positions: ``model.rigid.pull_back``
    maps its gradient to q), ``density`` has one entry per body (rigid ones last) and
    ``rigid_initial_velocity`` / ``rigid_initial_angular_velocity`` ((k, 3), one row per rigid
    body) are the gradients of each rigid body's initial velocity and angular velocity.

    With the direct solver each recorded step keeps its factorisation within ``factor_budget``
    bytes (:class:`StepAdjoint`); ``backward`` may be called again (another loss) and reuses them;
    :meth:`release` frees them."""

    def __init__(self, sim, params=None, *, tol=None, factor_budget=None):
        self.sim = sim
        self.adjoint = StepAdjoint(sim, params, tol=tol, factor_budget=factor_budget)
        self.records = []
        self.stats = []

    def __enter__(self):
        if getattr(self.sim, "step_recorder", None) is not None:
            raise RuntimeError("this simulator is already being recorded")
        self.sim.step_recorder = self
        return self

    def __exit__(self, *exc):
        self.sim.step_recorder = None

    @property
    def steps(self) -> int:
        return len(self.records)

    @property
    def nbytes(self) -> int:
        """Host memory the recorded steps' vectors hold (bytes; kept factorisations: :attr:`factor_nbytes`)."""
        return int(sum(r.nbytes for r in self.records))

    @property
    def factor_nbytes(self) -> int:
        """Memory of the factorisations the recorded steps keep (bytes; direct solver, ``factor_budget``)."""
        return int(sum(r.factor_nbytes for r in self.records))

    def release(self):
        """Free the kept factorisations (later ``backward`` calls refactorise; the records stay)."""
        for r in self.records:
            r.release()

    def record(self, run, state_in, state_out, control, dt):
        """Run one step (``run()``) and keep its record."""
        rec = self.adjoint.record_before(state_in, control, dt)
        stats = run()
        self.adjoint.record_after(rec, state_out)
        self.records.append(rec)
        self.stats.append(stats)
        return stats

    def backward(self, x_grads=None, v_grads=None) -> dict:
        """Gradients of a loss L(x_0..x_N, v_0..v_N) given dL/dx_k (``x_grads``) and dL/dv_k."""
        n, N = self.sim.num_vertices, len(self.records)
        x_grads, v_grads = x_grads or {}, v_grads or {}

        def get(d, k):
            return np.asarray(d[k], dtype=np.float64).reshape(n, 3) if k in d else np.zeros((n, 3))

        adj = self.adjoint
        adj.zero_grad()
        xbar, vbar, hbar = get(x_grads, N), get(v_grads, N), {}
        for k in range(N - 1, -1, -1):
            xbar, vbar, hbar = adj.backward(self.records[k], xbar, vbar, hbar, step_index=k)
            xbar = xbar + get(x_grads, k)
            vbar = vbar + get(v_grads, k)
        g = adj.parameter_gradients()
        g["initial_positions"], g["initial_velocities"], g["initial_history"] = xbar, vbar, hbar
        layout = getattr(self.sim.model, "rigid", None)
        if layout is not None:  # per rigid body: its initial velocity and angular velocity (docs/rigid.md)
            g["rigid_initial_velocity"], g["rigid_initial_angular_velocity"] = layout.initial_velocity_gradients(vbar)
        return g


def tape_adjoint(sim) -> StepAdjoint:
    """The :class:`StepAdjoint` that steps of ``sim`` recorded on a ``wp.Tape`` use (made on first
    use, kept as ``sim.adjoint``): its ``parameter_gradients()`` are the parameter gradients of
    ``tape.backward()``, ``zero_grad()`` clears them (``tape.zero()`` clears the state arrays' grads)."""
    adj = getattr(sim, "adjoint", None)
    if adj is None:
        adj = sim.adjoint = StepAdjoint(sim)
        adj.history_grads = {}
        adj.taped_steps = 0
    return adj


def _add_grad(arr, value):
    if value is not None and arr.requires_grad and np.any(value):
        g = arr.grad
        upload(g, read(g).astype(np.float64) + value)


def recorded_step(sim, run, state_in, state_out, control, dt, *, own):
    """A step of ``sim`` (``run()``) while a :class:`Recording` is active or a ``wp.Tape``
    records. On a tape the step's own launches are not recorded (the tape is paused during the
    forward solve) and a custom backward is recorded instead (``Tape.record_func``): it reads the
    grads of ``state_out.x`` / ``.v`` and adds the step's adjoints to those of ``state_in`` (and
    the parameter gradients to ``sim.adjoint``)."""
    tape = active_tape()
    recording = getattr(sim, "step_recorder", None)
    if tape is None:
        return recording.record(run, state_in, state_out, control, dt)
    check_differentiable(sim)
    if own:
        raise ValueError("on a wp.Tape, step with states of their own: sim.step(state_in, state_out, control, dt) "
                         "with a new state per step (sim.new_state(requires_grad=True)); sim.step() reuses two "
                         "buffers, so their gradients would mix")
    adj = tape_adjoint(sim)
    runtime = _warp_runtime()
    runtime.tape = None  # the forward's own launches are not taped: the step has its own backward
    try:
        if recording is not None:
            stats = recording.record(run, state_in, state_out, control, dt)
            rec = recording.records[-1]
        else:
            rec = adj.record_before(state_in, control, dt)
            stats = run()
            adj.record_after(rec, state_out)
    finally:
        runtime.tape = tape
    index = adj.taped_steps
    adj.taped_steps += 1

    def backward():
        xbar = read(state_out.x.grad).astype(np.float64) if state_out.x.requires_grad else None
        vbar = read(state_out.v.grad).astype(np.float64) if state_out.v.requires_grad else None
        hbar = adj.history_grads.pop(id(state_out), {})
        xn, vn, h_in = adj.backward(rec, xbar, vbar, hbar, step_index=index)
        _add_grad(state_in.x, xn)
        _add_grad(state_in.v, vn)
        if h_in:
            adj.history_grads[id(state_in)] = h_in

    tape.record_func(backward, [a for a in (state_in.x, state_in.v, state_out.x, state_out.v) if a.requires_grad])
    return stats


def set_material_parameters(sim, youngs_modulus=None, poisson_ratio=None):
    """Change the whole body's Young's modulus and Poisson ratio of a built ``sim`` in place (the
    kernel parameters of every point set; ``sim.model.material`` becomes a material of the same
    class with the new values), for runs that differentiate or fit them without rebuilding."""
    model = sim.model
    if getattr(model, "num_bodies", 1) > 1:
        raise NotImplementedError(f"set_material_parameters: a model of {model.num_bodies} bodies has a material per body; "
                                  "change a body's material and build the simulator again")
    old = model.material
    E = float(old.youngs_modulus if youngs_modulus is None else youngs_modulus)
    nu = float(old.poisson_ratio if poisson_ratio is None else poisson_ratio)
    new = type(old)(youngs_modulus=E, poisson_ratio=nu, density=old.density)
    sets = sim.quadrature_sets
    vi = getattr(model, "volumetric_integration", "full")
    pairs = material_set_parameters(new, E, nu, vi, len(sets) > 1)
    for qs, (mu, lam) in zip(sets, pairs):
        qs.material.mu, qs.material.lam = sim.scalar_type(mu), sim.scalar_type(lam)
    if vi == "reduced":
        model.volumetric_parameters = tuple((float(a), float(b)) for a, b in pairs)
    model.material = new
    return new


def set_density(sim, density):
    """Change the density of a built ``sim`` in place: the model's mass matrices and gravity (all
    proportional to it), the simulator's mass blocks and external forces (``sync_model``)."""
    model = sim.model
    if getattr(model, "num_bodies", 1) > 1:
        raise NotImplementedError(f"set_density: a model of {model.num_bodies} bodies has a material per body; "
                                  "change a body's material and build the simulator again")
    old = model.material
    rho = float(density)
    if not (np.isfinite(rho) and rho > 0):
        raise ValueError(f"density must be a positive number of kg/m^3, got {density!r}")
    r = rho / float(old.density)
    if r == 1.0:
        return old
    new = type(old)(youngs_modulus=old.youngs_modulus, poisson_ratio=old.poisson_ratio, density=rho)
    model.mass = model.mass * r
    model.lumped_mass = model.lumped_mass * r
    model.gravity_mass = model.gravity_mass * r
    model.material = new
    mv = sim.mass_values
    h = read(mv)
    upload(mv, h * h.dtype.type(r))
    sim.sync_model()
    return new
