"""Reduced implicit time stepping on a subspace x = X + U q with cubature forces (An, Kim & James 2008,
"Optimizing cubature for efficient integration of subspace deformations").

Incremental potential over the reduced velocity v (r-vector); for backward Euler (s = h; BDF2 and
Newmark change the prediction and s, see :mod:`warpfem.integrators`):

    E(v) = 1/2 (v - v_n)^T M_r (v - v_n) + h/2 v^T C_r v + V_c(q_n + h v) - h v^T U^T f_ext,

M_r = U^T M U (= I for a mass-orthonormal basis), C_r = alpha M_r + beta K_r(q_n) (projected),
V_c the cubature energy. Newton with an Armijo backtracking line search and a dense r x r solve
(numpy); the reduced force and stiffness come from the Warp cubature kernels
(``warpfem.kernels.subspace``), touching only cubature elements.
"""

from __future__ import annotations

import time
import warnings

import numpy as np
import warp as wp

from warpfem.device import get_device as _get_device
from warpfem.kernels import subspace as RK
from warpfem.kernels.generic import launch
from warpfem.kernels.structs import material_params, quadrature_points
from warpfem.integrators import make_integrator
from warpfem.solvers.nonlinear import NewtonOptions, SolveFailed, SolveStats, newton_solve
from warpfem.solvers.state import PRECISIONS, check_simulator_options



def _basis_array(U, n, vec, npdt, device):
    r = U.shape[1]
    return wp.array(np.ascontiguousarray(U.reshape(n, 3, r).transpose(0, 2, 1)).astype(npdt), dtype=vec, device=device)


class CubatureForces:
    """Reduced energy (J), force U^T f (r,) and stiffness U^T K U (r, r) by cubature on a device.

    Args:
        model: the Model (tet4).
        U: (3n, r) basis.
        elements, weights: cubature elements and dimensionless weights (weight 1 for every element
            gives the exact reduced quantities).
    """

    def __init__(self, model, U, elements, weights, *, device="cpu", precision="float64"):
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
        self._q = wp.zeros(r, dtype=self._s, device=dev)
        self._energy = wp.zeros(c, dtype=self._s, device=dev)
        self._f = wp.zeros(4 * c, dtype=vec, device=dev)
        self._H = wp.zeros(16 * c, dtype=mat, device=dev)
        self._force = wp.zeros(r, dtype=self._s, device=dev)
        self._K = wp.zeros((r, r), dtype=self._s, device=dev)
        self._npdt = npdt

    def evaluate(self, q, *, hessian: bool = False, project: bool = True):
        """(energy J, force (r,), stiffness (r, r) or None) at q, float64 numpy."""
        self._q.assign(np.asarray(q, dtype=self._npdt))
        wh = int(bool(hessian))
        launch(RK.cubature_element_kernel, dim=self.c,
                  inputs=[self.U, self._q, self.points, self.material, wh, int(bool(project)), self._energy, self._f,
                          self._H], device=self.device)
        self._force.zero_()
        if hessian:
            self._K.zero_()
        launch(RK.cubature_project_kernel, dim=(self.c, self.r),
                  inputs=[self.U, self.points, self._f, self._H, wh, self._force, self._K],
                  device=self.device)
        E = float(self._energy.numpy().astype(np.float64).sum())
        f = self._force.numpy().astype(np.float64)
        K = self._K.numpy().astype(np.float64) if hessian else None
        return E, f, K


class ReducedSimulator:
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

    Fixed vertices stay where the basis puts them (at rest: fixed rows of U are zero). State: the
    reduced coordinates ``q`` and velocities ``qdot`` (numpy float64, r).
    """

    def __init__(self, model, subspace, *, device="cpu", precision="float64", dt=1.0 / 60.0, damping_mass=0.0,
                 damping_stiffness=0.0, require_convergence=False, integrator="backward_euler", **newton_options):
        self._s, self._vec, _, self._np = check_simulator_options(precision, dt, damping_mass, damping_stiffness)
        self.integrator = make_integrator(integrator)
        unknown = set(newton_options) - set(NewtonOptions.__dataclass_fields__)
        if unknown:
            raise TypeError(f"unknown solver option(s) {sorted(unknown)}; known: {sorted(NewtonOptions.__dataclass_fields__)}")
        subspace.check(model)
        lifting = subspace.lifting if subspace.lifting is not None and subspace.lifting.size else None
        self.options = NewtonOptions(**newton_options)
        self.options.validate()
        self.model, self.subspace = model, subspace
        self.device = _get_device(device)
        self.precision = precision
        self.dt, self.damping_mass, self.damping_stiffness = float(dt), float(damping_mass), float(damping_stiffness)
        self.require_convergence = require_convergence
        U = subspace.U
        self.r = U.shape[1]
        self.num_vertices = n = model.num_vertices
        cub = subspace.cubature
        # kinematic handles: x = X + U q + L a (a prescribed); the kernels see the basis B = [U | L]
        self.lifting = lifting
        self.p = 0 if lifting is None else lifting.size
        self._B = U if lifting is None else np.hstack([U, lifting.L])
        if lifting is not None:
            lifting.bind(model.rest_positions)
        self.forces = CubatureForces(model, self._B, cub.elements, cub.weights, device=device, precision=precision)
        self.mass_r = self._reduced_mass(U)
        self.mass_ul = U.T @ (self._mass3() @ lifting.L) if lifting is not None else np.zeros((self.r, 0))
        self.a = np.zeros(self.p)      # handle coordinates (prescribed)
        self.adot = np.zeros(self.p)
        self._a_target = {}            # handle group -> coordinates for the end of the next step
        self._X = wp.array(model.rest_positions.astype(self._np), dtype=self._vec, device=self.device)
        self._x = wp.zeros(n, dtype=self._vec, device=self.device)
        self._qdev = wp.zeros(self.r + self.p, dtype=self._s, device=self.device)
        self._surface = None
        self.q = np.zeros(self.r)
        self.qdot = np.zeros(self.r)
        self.time = 0.0
        self.step_count = 0
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
        self.fext_r = self.subspace.U.T @ self.model.external_forces().reshape(-1)

    # -- state ------------------------------------------------------------------------------------
    def _reconstruct(self, X, U, q, out):
        self._qdev.assign(np.asarray(q, dtype=self._np))
        launch(RK.reconstruct_kernel, dim=len(X), inputs=[X, U, self._qdev, out], device=self.device)
        return out

    @property
    def z(self) -> np.ndarray:
        """Coordinates in the kernel basis [U | L]: [q; a]."""
        return np.concatenate([self.q, self.a])

    def positions_device(self):
        """x = X + U q (+ L a) as a device array of vec3 (computed on the device only when asked)."""
        return self._reconstruct(self._X, self.forces.U, self.z, self._x)

    @property
    def x(self):
        """Full-mesh positions on the device (a reconstruction; prefer :meth:`surface_positions`)."""
        return self.positions_device()

    def positions(self) -> np.ndarray:
        """Full-mesh positions (n, 3), m, float64."""
        return self.positions_device().numpy().astype(np.float64)

    def velocities(self) -> np.ndarray:
        """Full-mesh velocities U qdot (+ L adot) (n, 3), m/s."""
        return (self._B @ np.concatenate([self.qdot, self.adot])).reshape(-1, 3)

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
            self._a_target[g] = self.lifting.group_coords(g, pos[[lookup[i] for i in ids.tolist()]])
            covered.update(ids.tolist())
        stray = [i for i in lookup if i not in covered]
        if stray:
            raise ValueError(f"vertices {stray[:5]} are not handle vertices of this subspace")

    def _next_handle_coords(self):
        a = self.a.copy()
        for g, val in self._a_target.items():
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
        return self._reconstruct(WX, WU, self.z, out).numpy().astype(np.float64)

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
        return self.forces.evaluate(self.z)[0]

    # -- the interface time integrators use (warpfem.integrators): z = [q; a], z' = [qdot; adot] ----------
    def _istate(self):
        return np.concatenate([self.q, self.a]), np.concatenate([self.qdot, self.adot])

    def _iset_state(self, z, zdot):
        r = self.r
        self.q, self.a = np.array(z[:r]), np.array(z[r:])
        self.qdot, self.adot = np.array(zdot[:r]), np.array(zdot[r:])

    def _ivec(self):
        return np.zeros(self.r + self.p)

    @staticmethod
    def _ilincomb(a, x, b, y, out):
        out[:] = a * x + b * y

    def set_state(self, q=None, qdot=None):
        """Set reduced coordinates / velocities (r,); time integrators restart their history."""
        for name, val in (("q", q), ("qdot", qdot)):
            if val is not None:
                a = np.asarray(val, dtype=np.float64)
                if a.shape != (self.r,) or not np.all(np.isfinite(a)):
                    raise ValueError(f"{name} must be {self.r} finite numbers, got shape {a.shape}")
                setattr(self, name, a.copy())
        self.integrator.reset()

    def _damping(self, z):
        """Rows r of the reduced Rayleigh damping C = alpha B^T M B + beta B^T K(z) B: (C_rr, C_rl)."""
        r = self.r
        C = self.damping_mass * self.mass_r
        C_ul = self.damping_mass * self.mass_ul
        if self.damping_stiffness > 0:
            Kn = self.forces.evaluate(z, hessian=True, project=True)[2]
            C = C + self.damping_stiffness * Kn[:r, :r]
            C_ul = C_ul + self.damping_stiffness * Kn[:r, r:]
        return C, C_ul

    def _equation_of_motion_acceleration(self, out):
        """out = [a_q; 0]: M_r a_q = U^T f(z) + U^T f_ext - (C z')_q (handles start unaccelerated)."""
        r = self.r
        z, zdot = self._istate()
        C, C_ul = self._damping(z)
        f = self.forces.evaluate(z)[1][:r]
        rhs = f + self.fext_r - C @ self.qdot - C_ul @ self.adot
        out[:] = 0.0
        out[:r] = np.linalg.solve(self.mass_r, rhs)
        if not np.all(np.isfinite(out)):
            raise SolveFailed("the initial acceleration is not finite; state left unchanged",
                              SolveStats(reason="non-finite initial acceleration"))

    # -- step ---------------------------------------------------------------------------------------
    def add_collider(self, *args, **kw):
        """Not supported: a reduced simulator (x = X + U q) does not handle contact; use :class:`warpfem.Simulator`."""
        raise ValueError("a reduced simulator (x = X + U q) does not handle colliders; use warpfem.Simulator (Newton, any integrator) for contact")

    def step(self) -> SolveStats:
        """One reduced step of ``dt`` with the simulator's integrator (the same Newton loop as the
        full-space simulators, :func:`~warpfem.solvers.nonlinear.newton_solve`, with a dense r x r
        solve); raises SolveFailed on NaN (state untouched)."""
        t0 = time.perf_counter()
        r = self.r
        prediction = self.integrator.predict(self)
        zb, zhat, s = prediction
        # handles: a_{n+1} prescribed, so their end-of-step velocity is (a_{n+1} - a_b) / s; the
        # kinetic and damping energies of V = U v + L adot couple through M_ul = U^T M L (and beta K_ul)
        a_next = self._next_handle_coords()
        adot = (a_next - zb[r:]) / s
        pot = _ReducedPotential(self, zb=zb, v_hat=zhat[:r], adot_hat=zhat[r:], adot=adot, s=s)
        v = self.qdot.copy()
        st = newton_solve(pot, v, self.options)
        st.seconds = time.perf_counter() - t0
        what = f"reduced step {self.step_count}"
        if not st.converged:
            if "non-finite" in st.reason or not np.isfinite(st.energy) or not np.all(np.isfinite(v)):
                raise SolveFailed(f"{what} diverged ({st.reason}); state left unchanged", st)
            if self.require_convergence:
                raise SolveFailed(f"{what} did not converge ({st.reason}); state left unchanged", st)
            warnings.warn(f"{what} did not converge: {st.reason} (relative gradient {st.residual:.2e})", RuntimeWarning, stacklevel=2)
        self.integrator.advance(self, np.concatenate([v, adot]), prediction)
        self.a = a_next  # exactly the prescribed coordinates
        self._a_target = {}
        self.time += self.dt
        self.step_count += 1
        return st


class _ReducedPotential:
    """The incremental potential of a reduced step, the same terms as the full-space forms
    (:mod:`warpfem.solvers.forms`) projected on the basis B = [U | L] (L: handle lifting):

        inertia    1/2 (v - v_hat)^T M_r (v - v_hat) + v^T M_ul (adot - adot_hat)
        damping    s/2 v^T C_r v + s v^T C_ul adot        (C frozen at the step start)
        elastic    V_c(z_b + s [v; adot])                 (cubature)
        loads      -s v^T U^T f_ext

    over the reduced velocity v (r numbers); the Newton system is dense (r x r, numpy)."""

    gradient_test_below = 1e-9  # float64 dense sums of cubature terms resolve no finer energy change

    def __init__(self, sim, *, zb, v_hat, adot_hat, adot, s):
        self.sim, self.zb, self.v_hat, self.adot, self.s = sim, zb, v_hat, adot, float(s)
        C, C_ul = sim._damping(np.concatenate([sim.q, sim.a]))
        self.C = C
        self.A = sim.mass_r + s * C
        self.lin = sim.mass_ul @ (adot - adot_hat) + s * (C_ul @ adot)  # constant part of the gradient
        self.eps = float(np.finfo(sim._np).eps)
        self.opts = sim.options
        self._K, self._K_at = None, None

    def coords(self, v):
        return self.zb + self.s * np.concatenate([v, self.adot])

    def new_vector(self):
        return np.zeros(self.sim.r)

    @staticmethod
    def trial(y, alpha, d, out):
        out[:] = y + alpha * d

    @staticmethod
    def assign(dst, src):
        dst[:] = src

    def energy(self, v):
        sim, s = self.sim, self.s
        E, _, _ = sim.forces.evaluate(self.coords(v))
        dv = v - self.v_hat
        quad = 0.5 * dv @ (sim.mass_r @ dv) + 0.5 * s * v @ (self.C @ v) + v @ self.lin
        work = s * v @ sim.fext_r
        return quad + E - work, abs(quad) + abs(E) + abs(work)

    def gradient(self, v, g):
        sim, s, r = self.sim, self.s, self.sim.r
        _, f, K = sim.forces.evaluate(self.coords(v), hessian=True, project=self.opts.project_hessian)
        terms = (sim.mass_r @ (v - self.v_hat) + self.lin, s * (self.C @ v), s * f[:r], s * sim.fext_r)
        g[:] = terms[0] + terms[1] - terms[2] - terms[3]
        self._K, self._K_at = K[:r, :r], v.copy()
        return float(sum(np.linalg.norm(t) for t in terms)), float(np.linalg.norm(g))

    def solve_newton_system(self, v, g, d, opts):
        if self._K_at is None or not np.array_equal(self._K_at, v):
            self.gradient(v, self.new_vector())
        H = self.A + self.s * self.s * self._K
        try:
            d[:] = np.linalg.solve(H, -g)
        except np.linalg.LinAlgError:
            d[:] = -g
        return 0

    @staticmethod
    def fallback_direction(g, d):
        d[:] = -g

    def direction_check(self, v, g, d):
        scale = np.abs(v).max() + np.abs(self.coords(v)).max() / abs(self.s)
        return float(g @ d), bool(np.abs(d).max() <= 8.0 * self.eps * scale)
