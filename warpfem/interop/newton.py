"""warpfem as a solver of newton (the Warp physics engine): :class:`SolverFEM`.

``SolverFEM(model, **options)`` is a ``newton.solvers.SolverBase``: ``step(state_in, state_out,
control, contacts, dt)`` advances the tetrahedra of a ``newton.Model`` (``ModelBuilder.add_soft_mesh``,
``add_soft_grid``) with a warpfem :class:`~warpfem.simulator.Simulator` (Newton's method on the
backward-Euler incremental potential, barrier contact with friction) and writes ``particle_q`` and
``particle_qd`` of ``state_out``. What maps to what (docs/newton.md):

* tetrahedra and their ``tet_materials`` rows (k_mu, k_lambda, k_damp): one warpfem material per
  distinct (k_mu, k_lambda) pair, all sharing the particles (one quadrature set per material);
  newton's tetrahedral energy is the stable neo-Hookean energy without the log term with
  mu = k_mu, lambda = k_lambda + k_mu, which is :class:`warpfem.StableNeoHookean` of the Lame
  pair (k_mu, k_lambda) (E = mu (3 lambda + 2 mu) / (lambda + mu), nu = lambda / (2 (lambda + mu)));
  k_damp becomes Rayleigh stiffness damping beta = 2 k_damp / k_mu (the small-strain
  dissipation of newton's damping term, deviatoric part);
* particle masses: newton's ``particle_mass`` (lumped); a particle of zero mass or without the
  ``ParticleFlags.ACTIVE`` flag is fixed where ``state_in`` puts it (moving it between steps moves it
  kinematically);
* gravity: ``model.gravity``; external forces: ``state_in.particle_f`` (N, per particle);
* shapes that collide with particles (ground plane, planes, boxes, spheres, triangle meshes) on
  their bodies' poses of ``state_in`` -> warpfem colliders with friction (the shape material's
  ``mu``);
* with ``rigid_bodies``: free newton bodies -> warpfem rigid (affine) bodies in the same implicit
  solve (``body_q`` / ``body_qd`` / ``body_f`` read and written; their shapes are then not colliders).
* with ``shape_contact="surface"``: box and mesh shapes -> kinematic warpfem rigid bodies in the
  surface contact (edge-edge pairs too), placed each step at their pose on ``state_in.body_q``.

warpfem keeps its own state (float64 by default) between steps while the caller passes back what
the solver wrote last (the usual ``state_0, state_1 = state_1, state_0`` loop); a ``state_in`` that
differs from it (a reset, a state edited by hand or by another solver) is read again
(``resyncs`` counts those).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

try:
    import newton
    import warp as wp
    from newton.solvers import SolverBase
    from newton.solvers.experimental.coupled import CouplingInterface
except ImportError as exc:  # pragma: no cover - exercised only without newton
    raise ImportError("warpfem.interop.newton needs the newton package (the Warp physics engine): "
                      "pip install 'warpfem[newton]'") from exc

from warpfem.contact.colliders import Box, Capsule, MeshCollider, Plane, Sphere
from warpfem.elements import precompute_quadrature
from warpfem.materials import make_material
from warpfem.mesh import VolumeMesh
from warpfem.model import Model
from warpfem.simulator import Simulator

__all__ = ["SolverFEM", "NewtonInteropError", "lame_to_youngs"]

#: the shape types SolverFEM turns into colliders
SUPPORTED_SHAPES = ("plane", "sphere", "box", "capsule", "mesh")


class NewtonInteropError(ValueError):
    """A newton model or state SolverFEM cannot simulate (the message says what is supported)."""


def lame_to_youngs(k_mu: float, k_lambda: float) -> tuple[float, float]:
    """(E, nu) of the Lame pair (mu, lambda): E = mu (3 lambda + 2 mu) / (lambda + mu),
    nu = lambda / (2 (lambda + mu))."""
    mu, lam = float(k_mu), float(k_lambda)
    return mu * (3.0 * lam + 2.0 * mu) / (lam + mu), lam / (2.0 * (lam + mu))


def _rotation(qxyzw) -> np.ndarray:
    x, y, z, w = (float(c) for c in qxyzw)
    n = math.sqrt(x * x + y * y + z * z + w * w) or 1.0
    x, y, z, w = x / n, y / n, z / n, w / n
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _compose(a, b):
    """(R, p) of transform a applied after b (both (R, p))."""
    return a[0] @ b[0], a[0] @ b[1] + a[1]


def _quaternion(R) -> np.ndarray:
    """(x, y, z, w) unit quaternion of the rotation matrix R (Shepperd's method, w >= 0)."""
    R = np.asarray(R, dtype=np.float64)
    t = np.trace(R)
    if t > max(R[0, 0], R[1, 1], R[2, 2]):
        w = 0.5 * math.sqrt(1.0 + t)
        q = np.array([(R[2, 1] - R[1, 2]) / (4 * w), (R[0, 2] - R[2, 0]) / (4 * w), (R[1, 0] - R[0, 1]) / (4 * w), w])
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        r = 0.5 * math.sqrt(max(1.0 + R[i, i] - R[j, j] - R[k, k], 0.0))
        q = np.zeros(4)
        q[i] = r
        q[j] = (R[j, i] + R[i, j]) / (4 * r)
        q[k] = (R[k, i] + R[i, k]) / (4 * r)
        q[3] = (R[k, j] - R[j, k]) / (4 * r)
    q /= np.linalg.norm(q)
    return q if q[3] >= 0.0 else -q


def _polar_rotation(A) -> np.ndarray:
    """The rotation nearest to A (Frobenius norm): U V^T of A's SVD, sign-corrected to det +1."""
    U, _, Vt = np.linalg.svd(np.asarray(A, dtype=np.float64))
    if np.linalg.det(U @ Vt) < 0.0:
        U[:, -1] *= -1.0
    return U @ Vt


def _box_surface(h):
    """(8 vertices, 12 outward triangles) of the box [-h, h]."""
    V = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=np.float64) * np.asarray(h)
    F = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], dtype=np.int64)
    return V, F


class _Posed:
    """A warpfem collider built in its newton shape's own frame, placed by the shape's world
    transform of the current step (``pose`` ignores the schedule time: set by SolverFEM)."""

    def pose(self, t):
        return self.newton_pose


class _PosedPlane(_Posed, Plane):
    pass


class _PosedSphere(_Posed, Sphere):
    pass


class _PosedBox(_Posed, Box):
    pass


class _PosedCapsule(_Posed, Capsule):
    pass


class _PosedMesh(_Posed, MeshCollider):
    pass


def _np(a):
    return None if a is None else a.numpy()


# -- the taped step: newton's arrays <-> warpfem's state by Warp kernels (differentiable on a wp.Tape) ---
@wp.kernel
def _gather(idx: wp.array(dtype=wp.int32), fixed: wp.array(dtype=wp.int32), q: wp.array(dtype=wp.vec3),
            qd: wp.array(dtype=wp.vec3), x: wp.array(dtype=Any), v: wp.array(dtype=Any)):
    """warpfem's x, v (vec3 of its precision) := newton's particles idx (fixed ones at rest)."""
    i = wp.tid()
    x[i] = type(x[i])(q[idx[i]])
    if fixed[i] == 0:
        v[i] = type(v[i])(qd[idx[i]])
    else:
        v[i] = v[i] - v[i]


@wp.kernel
def _scatter(vertex: wp.array(dtype=wp.int32), x: wp.array(dtype=Any), v: wp.array(dtype=Any),
             q_in: wp.array(dtype=wp.vec3), qd_in: wp.array(dtype=wp.vec3), q: wp.array(dtype=wp.vec3),
             qd: wp.array(dtype=wp.vec3)):
    """newton's q, qd := warpfem's x, v where a particle is one of its vertices, else state_in's."""
    i = wp.tid()
    k = vertex[i]
    if k < 0:
        q[i] = q_in[i]
        qd[i] = qd_in[i]
    else:
        q[i] = wp.vec3(x[k])
        qd[i] = wp.vec3(v[k])


for _vec in (wp.vec3, wp.vec3d):
    wp.overload(_gather, {"x": wp.array(dtype=_vec), "v": wp.array(dtype=_vec)})
    wp.overload(_scatter, {"x": wp.array(dtype=_vec), "v": wp.array(dtype=_vec)})


class SolverFEM(SolverBase, CouplingInterface):
    """warpfem's implicit FEM as a newton solver of the model's tetrahedra.

    Args:
        model: a ``newton.Model`` (or a coupled framework's ``ModelView`` of one) with tetrahedra.
        precision: warpfem's precision, "float64" (default) or "float32"; newton's arrays stay float32.
        integrator: "backward_euler" (default), "bdf2", "newmark" or a :mod:`warpfem.integrators` instance.
        material: the warpfem material each (k_mu, k_lambda) group becomes: "stable_neo_hookean"
            (default: newton's tetrahedral energy), "stable_neo_hookean_log", "corotated", "stvk",
            "linear" (the same Lame pair, another energy).
        damping_mass: Rayleigh alpha (1/s). damping_stiffness: Rayleigh beta (s); None (default):
            2 k_damp / k_mu from the tetrahedra (one value: tetrahedra whose ratios differ need it given).
        friction: "shape" (default: each shape material's ``mu``), "average" (the mean of it and
            ``model.soft_contact_mu``, newton's particle-shape rule) or a number (every shape).
        contact: dict of warpfem contact options for every collider: ``dhat`` (m), ``stiffness``
            (N/m or "auto"), ``friction_velocity`` (m/s); warpfem's defaults otherwise (docs/contact.md).
        soft_contact: None (default: none) or a dict of ``Simulator.set_contact`` keys: contact
            between the soft bodies (``bodies``) and of each with itself (``self``).
        unsupported_shapes: "error" (default) or "ignore": what to do with a colliding shape
            SolverFEM cannot represent (cylinder, cone, ellipsoid, height field, convex hull).
        shapes: which shapes become colliders: "all" (default: every shape with
            ``ShapeFlags.COLLIDE_PARTICLES``), "static" (those of them on no body: the ground, fixed
            obstacles; in a coupled scene the rigid solver handles the moving ones) or a list of shape indices.
        rigid_bodies: None (default: none, except the proxy bodies a ``SolverCoupledProxy`` gives this solver
            to move: those flagged ``BodyFlags.PROXY``), False (none), True (every dynamic body of mass > 0) or a
            list of newton body indices: free bodies stepped as warpfem rigid (affine) bodies in the
            same implicit solve as the tetrahedra (docs/newton.md, "Rigid bodies"): their box, sphere
            and triangle-mesh shapes make their surface, newton's ``body_mass``, ``body_com`` and
            ``body_inertia`` their mass; ``body_q`` / ``body_qd`` / ``body_f`` are read and
            ``body_q`` / ``body_qd`` written. A body in a joint other than its FREE joint is refused.
        rigid_stiffness: kappa (Pa) of the rigid bodies' orthogonality energy (:class:`warpfem.RigidBody`).
        shape_contact: "collider" (default: every colliding shape is a warpfem collider, which keeps
            the soft bodies' vertices out of it) or "surface": the box and triangle-mesh shapes (not on
            a ``rigid_bodies`` body) become *kinematic* rigid bodies in warpfem's surface contact
            (point-triangle and edge-edge pairs: their edges stay out of the soft faces too), their
            four affine nodes prescribed each step at the shape's pose on ``state_in.body_q``; one
            friction coefficient for all surface contact (the largest ``mu`` of those shapes and
            of the rigid bodies'); planes, spheres and capsules stay colliders (docs/newton.md,
            "Shapes in surface contact").
        linear_solver, linear_solver_options, require_convergence, tol, atol, max_iters, ... :
            warpfem's :class:`~warpfem.simulator.Simulator` options (docs/linear_solvers.md,
            :class:`~warpfem.NewtonOptions`).

    Attributes:
        simulator: the warpfem :class:`~warpfem.simulator.Simulator`.
        particles: the newton particle index of each of its vertices.
        materials: one warpfem material per (k_mu, k_lambda) group.
        resyncs: how many steps read ``state_in`` again.
        body_reads: how many steps read only the rigid bodies of ``state_in`` again (their ``body_q`` /
            ``body_qd`` changed, the particles did not: a coupler syncing its proxy bodies).
        last_stats: the last step's :class:`~warpfem.SolveStats`.
        last_particle_force: the sum (N) of the ``particle_f`` the last step applied to the simulated
            particles (in a coupled scene: the coupling forces).
        rigid_bodies: the newton body indices stepped as rigid bodies (``[]`` without).
        kinematic_shapes: the newton shape indices stepped as kinematic rigid bodies
            (``shape_contact="surface"``; ``[]`` without).
        last_orthogonality_error: the largest entry of |A^T A - I| over the rigid bodies after the last
            step (A the affine body's matrix; ``body_q`` gets its nearest rotation).
        rigid_surface_properties: per rigid body (mass, centre of mass, inertia tensor) of its
            shapes' surface at uniform density ``body_mass`` / volume, in its body frame (to compare
            with newton's ``body_com`` and ``body_inertia``; overlapping shapes count twice here).
    """

    def __init__(self, model, *, precision="float64", integrator="backward_euler", material="stable_neo_hookean",
                 damping_mass=0.0, damping_stiffness=None, friction="shape", contact=None, soft_contact=None,
                 unsupported_shapes="error", shapes="all", rigid_bodies=None, rigid_stiffness=1e8,
                 shape_contact="collider", linear_solver="auto", linear_solver_options=None, require_convergence=False, **newton_options):
        super().__init__(model)
        self._options = dict(precision=precision, integrator=integrator, material=material, damping_mass=damping_mass,
                             damping_stiffness=damping_stiffness, friction=friction, contact=contact,
                             soft_contact=soft_contact, unsupported_shapes=unsupported_shapes, shapes=shapes,
                             rigid_bodies=rigid_bodies, rigid_stiffness=rigid_stiffness, shape_contact=shape_contact,
                             linear_solver=linear_solver,
                             linear_solver_options=linear_solver_options, require_convergence=require_convergence,
                             **newton_options)
        self.rigid_bodies = self._rigid_selection(model, rigid_bodies)
        self.rigid_surface_properties, self._rigid_frames = {}, []
        if unsupported_shapes not in ("error", "ignore"):
            raise ValueError(f"unsupported_shapes must be 'error' or 'ignore', got {unsupported_shapes!r}")
        if not (friction in ("shape", "average") or (isinstance(friction, (int, float)) and friction >= 0)):
            raise ValueError(f"friction must be 'shape', 'average' or a number >= 0, got {friction!r}")
        self.friction = friction
        self.contact_options = dict(contact or {})
        bad = set(self.contact_options) - {"dhat", "stiffness", "friction_velocity"}
        if bad:
            raise TypeError(f"contact options are dhat, stiffness, friction_velocity; got {sorted(bad)}")
        self.unsupported_shapes = unsupported_shapes
        if not (shapes in ("all", "static") or (not isinstance(shapes, str) and all(
                isinstance(i, (int, np.integer)) for i in shapes))):
            raise ValueError(f"shapes must be 'all', 'static' or a list of shape indices, got {shapes!r}")
        self.shapes = shapes if isinstance(shapes, str) else [int(i) for i in shapes]
        if shape_contact not in ("collider", "surface"):
            raise ValueError(f"shape_contact must be 'collider' or 'surface', got {shape_contact!r}")
        self.shape_contact = shape_contact
        self.kinematic_shapes = self._kinematic_selection(model)
        q0 = self._checked_positions(_np(model.particle_q), "model.particle_q")
        tets, groups = self._tetrahedra(model)
        self.particles = np.unique(tets).astype(np.int64)  # newton index of each warpfem vertex
        local = np.searchsorted(self.particles, tets)
        mass = _np(model.particle_mass).astype(np.float64)[self.particles]
        flags = _np(model.particle_flags)
        active = np.ones(len(self.particles), dtype=bool) if flags is None else \
            (flags[self.particles] & int(newton.ParticleFlags.ACTIVE)) != 0
        fixed = (mass <= 0.0) | ~active
        mesh = VolumeMesh(q0[self.particles], local, "tet4", remove_unreferenced=False, name="newton tetrahedra")
        volume = mesh.total_volume()
        density = float(mass[~fixed].sum() / volume) if np.any(~fixed) and volume > 0 else 1.0
        self.materials = []
        for key, rows in groups:
            E, nu = lame_to_youngs(key[0], key[1])
            try:
                self.materials.append(make_material(material, youngs_modulus=E, poisson_ratio=nu, density=max(density, 1e-12)))
            except (ValueError, KeyError) as e:
                raise NewtonInteropError(f"tet_materials (k_mu={key[0]:g}, k_lambda={key[1]:g}) of {len(rows)} "
                                         f"tetrahedra (first: {int(rows[0])}): {e}") from None
        kd = _np(model.tet_materials)[:, 2].astype(np.float64)
        km = _np(model.tet_materials)[:, 0].astype(np.float64)
        used = np.concatenate([rows for _, rows in groups])
        if damping_stiffness is None:
            ratios = np.unique(2.0 * kd[used] / km[used])
            if len(ratios) > 1:
                raise NewtonInteropError("tet_materials: k_damp / k_mu differs between tetrahedra "
                                         f"({ratios.min():g} to {ratios.max():g} s); warpfem's stiffness damping is one "
                                         "value: give SolverFEM(damping_stiffness=...)")
            damping_stiffness = float(ratios[0])
        has_rigid = bool(self.rigid_bodies or self.kinematic_shapes)
        self._kinematic_frames = []  # per kinematic shape (R0, its centre of mass in the shape's frame)
        if has_rigid:
            from warpfem.model import Body

            rigid = [self._rigid_body(model, b, rigid_stiffness) for b in self.rigid_bodies]
            rb = self.rigid_bodies
            self._inertial = [_np(model.body_mass)[rb], _np(model.body_inertia)[rb], _np(model.body_com)[rb]]
            rigid += [self._kinematic_body(model, s) for s in self.kinematic_shapes]
            from warpfem.mesh.intersect import BodyOverlapError

            try:
                wf = Model.from_bodies([Body(mesh, self.materials[0], name="newton tetrahedra")] + rigid,
                                       gravity=self._gravity(model))
            except BodyOverlapError as e:
                if not self.kinematic_shapes:
                    raise
                raise NewtonInteropError(f"SolverFEM(shape_contact='surface'): {e}; shapes that touch or overlap cannot "
                                         "both be kinematic bodies: keep shape_contact='collider' or leave one out "
                                         "with shapes=[...]") from None
        else:
            wf = Model(mesh, self.materials[0], gravity=self._gravity(model))
        n_soft = len(self.particles)
        if len(groups) > 1:  # one quadrature set per material, all on the same vertices
            wf.quadratures = [precompute_quadrature(wf.rest_positions, mesh.elements[r], "tet4")
                              for r in self._group_rows(groups)]
            wf.materials = list(self.materials)
            wf.body_volumetric_parameters = [None] * len(groups)
            if isinstance(getattr(wf, "volumetric_integration", None), list):
                wf.volumetric_integration = [wf.volumetric_integration[0]] * len(groups)
            wf.material = max(self.materials, key=lambda m: m.youngs_modulus)
        # newton's particle masses (the fixed ones keep warpfem's lumped mass: they do not move)
        m = np.where(fixed, wf.lumped_mass[:n_soft], mass)
        import scipy.sparse

        wf.lumped_mass = np.concatenate([m, wf.lumped_mass[n_soft:]])
        wf.gravity_mass = np.concatenate([m, wf.gravity_mass[n_soft:]])
        wf.mass = scipy.sparse.block_diag([scipy.sparse.diags(m), wf.mass[n_soft:, n_soft:]], format="csr") \
            if has_rigid else scipy.sparse.diags(m).tocsr()
        self._fixed = np.flatnonzero(fixed)
        if len(self._fixed):
            wf.fix(self._fixed)
        # a kinematic shape's four nodes are fixed; each step prescribes them (Control.targets)
        self._kinematic_nodes = n_soft + 4 * len(self.rigid_bodies) + 4 * np.arange(len(self.kinematic_shapes))
        for k in self._kinematic_nodes:
            wf.fixed[k:k + 4] = True
        self.warpfem_model = wf
        self.device_name = str(model.device)
        self.simulator = Simulator(wf, device=self.device_name, precision=precision, integrator=integrator,
                                   damping_mass=damping_mass, damping_stiffness=damping_stiffness,
                                   linear_solver=linear_solver, linear_solver_options=linear_solver_options,
                                   require_convergence=require_convergence, **newton_options)
        qd0 = _np(model.particle_qd)
        if qd0 is not None and np.any(qd0[self.particles] != 0):
            v = qd0[self.particles].astype(np.float64)
            v[self._fixed] = 0.0
            if has_rigid:
                v = np.concatenate([v, self.simulator.velocities()[n_soft:]])
            self.simulator.set_velocities(v)
        self._n_soft = n_soft
        self._last_body = None
        self.last_orthogonality_error = 0.0
        self._forces_on = False
        self._last_q = self._last_qd = None
        self.resyncs = 0
        self.body_reads = 0
        self.last_stats = None
        self._setup_colliders(model)
        if has_rigid:  # the rigid bodies touch the soft ones (and each other) through warpfem's contact
            rc = {"bodies": True, "friction": self._rigid_friction(model)}
            if len(self.kinematic_shapes):  # dhat from the soft surface, as the colliders' (not the shapes' edges)
                faces = mesh.boundary_faces()
                E = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
                rc["dhat"] = 0.1 * float(np.linalg.norm(q0[self.particles][E[:, 0]] - q0[self.particles][E[:, 1]],
                                                        axis=1).mean())
            rc.update({k: v for k, v in self.contact_options.items() if k in ("dhat", "friction_velocity")})
            if isinstance(self.contact_options.get("stiffness"), (int, float)):
                rc["stiffness"] = self.contact_options["stiffness"]
            rc.update(dict(soft_contact or {}))
            self.simulator.set_contact(**rc)
        elif soft_contact:
            self.simulator.set_contact(**dict(soft_contact))

    # -- set-up ------------------------------------------------------------------------------------
    @staticmethod
    def _checked_positions(q, what):
        if q is None or len(q) == 0:
            raise NewtonInteropError(f"SolverFEM: {what} is empty; it simulates the tetrahedra of soft bodies "
                                     "(ModelBuilder.add_soft_mesh / add_soft_grid)")
        bad = np.flatnonzero(~np.isfinite(q).all(axis=1))
        if bad.size:
            raise NewtonInteropError(f"SolverFEM: {what} of particle {int(bad[0])} is not finite ({q[bad[0]].tolist()}); "
                                     f"{bad.size} particles with NaN/inf")
        return q.astype(np.float64)

    @staticmethod
    def _tetrahedra(model):
        """(tets (m, 4) newton particle indices of the simulated tetrahedra, [((k_mu, k_lambda), rows)])."""
        n_tet = int(getattr(model, "tet_count", 0) or 0)
        if n_tet == 0:
            n_tri = int(getattr(model, "tri_count", 0) or 0)
            what = (f"it has {n_tri} triangles and no tetrahedra (cloth and shells: use SolverVBD or SolverStyle3D)"
                    if n_tri else "it has no tetrahedra")
            raise NewtonInteropError(f"SolverFEM simulates volumetric soft bodies made of tetrahedra "
                                     f"(ModelBuilder.add_soft_mesh / add_soft_grid); {what}")
        tets = _np(model.tet_indices).reshape(-1, 4).astype(np.int64)
        mats = _np(model.tet_materials).astype(np.float64)
        # newton's solvers skip tetrahedra with k_mu <= 0 and k_lambda <= 0 (no energy): so does SolverFEM
        live = (mats[:, 0] > 0.0) | (mats[:, 1] > 0.0)
        if not live.any():
            raise NewtonInteropError("SolverFEM: every tetrahedron has k_mu <= 0 and k_lambda <= 0 (no elastic energy)")
        bad = np.flatnonzero(live & ~(mats[:, 0] > 0.0))
        if bad.size:
            raise NewtonInteropError(f"SolverFEM: tetrahedron {int(bad[0])} has k_mu = {mats[bad[0], 0]:g}; warpfem's "
                                     "materials need k_mu > 0 (and k_lambda > -2/3 k_mu)")
        keys, inverse = np.unique(mats[:, :2], axis=0, return_inverse=True)
        inverse = inverse.ravel()
        groups = [((float(k[0]), float(k[1])), np.flatnonzero((inverse == g) & live)) for g, k in enumerate(keys)]
        groups = [(k, r) for k, r in groups if r.size]
        order = np.concatenate([r for _, r in groups])
        # the simulated tetrahedra in group order (rows of the warpfem mesh)
        return tets[order], groups

    @staticmethod
    def _group_rows(groups):
        """Rows of each group in the warpfem mesh (the tetrahedra concatenated in group order)."""
        out, start = [], 0
        for _, rows in groups:
            out.append(np.arange(start, start + len(rows)))
            start += len(rows)
        return out

    @staticmethod
    def _gravity(model):
        g = _np(model.gravity)
        g = np.asarray(g, dtype=np.float64).reshape(-1, 3)
        if len(g) > 1 and not np.allclose(g, g[0]):
            raise NewtonInteropError(f"SolverFEM: the worlds' gravity differs ({g.tolist()}); it supports one gravity")
        return g[0]

    def _shape_pose(self, s, body_q):
        X = self._shape_tf[s]
        local = (_rotation(X[3:7]), X[:3].astype(np.float64))
        b = int(self._shape_body[s])
        if b < 0 or body_q is None:
            return local
        B = body_q[b]
        return _compose((_rotation(B[3:7]), B[:3].astype(np.float64)), local)

    # -- rigid bodies ---------------------------------------------------------------------------------
    @staticmethod
    def _rigid_selection(model, rigid_bodies):
        """The newton body indices stepped as warpfem rigid bodies: None/False (none), True (every
        body of mass > 0) or a list; each must be free (a FREE joint or none) and have mass > 0."""
        if rigid_bodies is False:
            return []
        n = int(getattr(model, "body_count", 0) or 0)
        mass = _np(model.body_mass) if n else np.zeros(0)
        flags = _np(getattr(model, "body_flags", None)) if n else None
        kinematic = int(getattr(getattr(newton, "BodyFlags", None), "KINEMATIC", 0) or 0)
        proxy = int(getattr(getattr(newton, "BodyFlags", None), "PROXY", 0) or 0)
        if rigid_bodies is None:  # a coupler's proxy bodies (SolverCoupledProxy: this solver moves them)
            if flags is None or not proxy:
                return []
            rigid_bodies = [b for b in range(n) if int(flags[b]) & proxy]
        if rigid_bodies is True:  # the dynamic ones (kinematic bodies stay colliders)
            chosen = [b for b in range(n) if mass[b] > 0.0 and not (flags is not None and int(flags[b]) & kinematic)]
        elif not isinstance(rigid_bodies, str) and all(isinstance(b, (int, np.integer)) for b in rigid_bodies):
            chosen = [int(b) for b in rigid_bodies]
        else:
            raise ValueError(f"rigid_bodies must be None, True or a list of body indices, got {rigid_bodies!r}")
        if len(set(chosen)) != len(chosen):
            raise NewtonInteropError(f"SolverFEM: rigid_bodies lists a body twice ({chosen})")
        jt = _np(model.joint_type) if int(getattr(model, "joint_count", 0) or 0) else np.zeros(0, np.int32)
        jp = _np(model.joint_parent) if len(jt) else np.zeros(0, np.int32)
        jc = _np(model.joint_child) if len(jt) else np.zeros(0, np.int32)
        for b in chosen:
            if not 0 <= b < n:
                raise NewtonInteropError(f"SolverFEM: rigid body index {b} out of range [0, {n})")
            if not mass[b] > 0.0:
                raise NewtonInteropError(f"SolverFEM: body {b} has mass {float(mass[b]):g}; rigid_bodies are dynamic "
                                         "bodies (mass > 0)")
            if flags is not None and kinematic and int(flags[b]) & kinematic:
                raise NewtonInteropError(f"SolverFEM: body {b} is kinematic; rigid_bodies are dynamic bodies")
            bad = np.flatnonzero(((jc == b) & (jt != int(newton.JointType.FREE))) | (jp == b))
            if bad.size:
                j = int(bad[0])
                raise NewtonInteropError(f"SolverFEM: body {b} is in joint {j} ({newton.JointType(int(jt[j])).name}); "
                                         "rigid_bodies steps free bodies only (add_body, no other joints)")
        return chosen

    def _body_surface(self, model, b):
        """(vertices, triangles) of body b's collision shapes, in its body frame (one closed
        surface per shape: box, sphere, triangle mesh)."""
        GeoType = newton.GeoType
        types, flags = _np(model.shape_type), _np(model.shape_flags)
        scale = _np(model.shape_scale).astype(np.float64)
        tf = _np(model.shape_transform).astype(np.float64)
        sb = _np(model.shape_body)
        source = getattr(model, "shape_source", None)
        collide = int(newton.ShapeFlags.COLLIDE_SHAPES) | int(newton.ShapeFlags.COLLIDE_PARTICLES)
        Vs, Fs, n = [], [], 0
        for s in np.flatnonzero(sb == b):
            if not int(flags[s]) & collide:
                continue
            t = GeoType(int(types[s]))
            if t == GeoType.BOX:
                V, F = _box_surface(scale[s])
            elif t == GeoType.SPHERE:
                from warpfem.mesh.box import icosphere_surface

                V, F = icosphere_surface(float(scale[s][0]), 2)
            elif t == GeoType.MESH and source is not None and source[s] is not None:
                V = np.asarray(source[s].vertices, dtype=np.float64).reshape(-1, 3) * scale[s]
                F = np.asarray(source[s].indices, dtype=np.int64).reshape(-1, 3)
            else:
                raise NewtonInteropError(f"SolverFEM: shape {int(s)} of rigid body {b} is a {t.name.lower()}; a rigid "
                                         "body's shapes must be boxes, spheres or triangle meshes")
            R = _rotation(tf[s][3:7])
            Vs.append(V @ R.T + tf[s][:3])
            Fs.append(F + n)
            n += len(V)
        if not Vs:
            raise NewtonInteropError(f"SolverFEM: rigid body {b} has no colliding shape (box, sphere, mesh) to "
                                     "build its surface from")
        return np.concatenate(Vs), np.concatenate(Fs)

    def _rigid_body(self, model, b, stiffness):
        """A warpfem RigidBody of newton body b at its pose of ``model.body_q`` (A = I there), with
        newton's mass, centre of mass and inertia (``body_mass``, ``body_com``, ``body_inertia``)."""
        from warpfem.rigid.body import RigidBody, mass_properties

        Vb, F = self._body_surface(model, b)
        B = _np(model.body_q)[b].astype(np.float64)
        R0, t0 = _rotation(B[3:7]), B[:3]
        mass = float(_np(model.body_mass)[b])
        com_b = _np(model.body_com)[b].astype(np.float64)
        I_b = _np(model.body_inertia)[b].astype(np.float64)
        V = mass_properties(Vb, F, 1.0)[3]
        qd = _np(model.body_qd)[b].astype(np.float64) if model.body_qd is not None else np.zeros(6)
        Xw = Vb @ R0.T + t0
        try:
            rb = RigidBody((Xw, F), density=mass / V if V > 0 else 1.0, name=f"newton body {b}",
                           initial_velocity=qd[:3], initial_angular_velocity=qd[3:], stiffness=stiffness)
        except ValueError as e:
            raise NewtonInteropError(f"SolverFEM: rigid body {b}: {e}") from None
        # the surface's own mass properties (uniform density): kept to compare with newton's
        self.rigid_surface_properties[b] = (rb.mass, R0.T @ (rb.center_of_mass - t0), R0.T @ rb.inertia_tensor @ R0)
        com_w = R0 @ com_b + t0
        S_b = 0.5 * np.trace(I_b) * np.eye(3) - I_b  # the second moment of the inertia tensor tr(S) I - S
        rb.mass, rb.center_of_mass, rb.second_moment = mass, com_w, R0 @ S_b @ R0.T
        rb.local_positions = Xw - com_w
        self._rigid_frames.append((R0, com_b))
        return rb

    def _rigid_friction(self, model):
        """One friction coefficient for contact with the rigid bodies: the largest ``mu`` of their shapes
        (``friction`` a number: that number)."""
        if isinstance(self.friction, (int, float)):
            return float(self.friction)
        sb, mu = _np(model.shape_body), _np(model.shape_material_mu)
        on = np.isin(sb, self.rigid_bodies)
        on[self.kinematic_shapes] = True
        mu = mu[on].astype(np.float64)
        if self.friction == "average":
            mu = 0.5 * (mu + float(model.soft_contact_mu))
        return float(max(mu.max(initial=0.0), 0.0))

    def _kinematic_selection(self, model):
        """The shapes stepped as kinematic rigid bodies (``shape_contact="surface"``): the colliding
        boxes and triangle meshes that are not on a simulated rigid body, in shape order."""
        if self.shape_contact != "surface":
            return []
        n_shapes = int(getattr(model, "shape_count", 0) or 0)
        if n_shapes == 0:
            return []
        types, flags, sb = _np(model.shape_type), _np(model.shape_flags), _np(model.shape_body)
        source = getattr(model, "shape_source", None)
        chosen = range(n_shapes) if isinstance(self.shapes, str) else self.shapes
        out = []
        for s in chosen:
            if not 0 <= s < n_shapes or not int(flags[s]) & int(newton.ShapeFlags.COLLIDE_PARTICLES):
                continue
            if (self.shapes == "static" and int(sb[s]) >= 0) or int(sb[s]) in self.rigid_bodies:
                continue
            t = newton.GeoType(int(types[s]))
            if t == newton.GeoType.BOX or (t == newton.GeoType.MESH and source is not None and source[s] is not None):
                out.append(int(s))
        return out

    def _kinematic_body(self, model, s):
        """A warpfem RigidBody of shape s's surface at its pose of ``model.body_q`` (its nodes are
        prescribed each step); keeps (R0, the centre of mass in the shape's frame) to place it."""
        from warpfem.rigid.body import RigidBody

        t = newton.GeoType(int(_np(model.shape_type)[s]))
        scale = _np(model.shape_scale)[s].astype(np.float64)
        if t == newton.GeoType.BOX:
            V, F = _box_surface(scale)
        else:
            src = model.shape_source[s]
            V = np.asarray(src.vertices, dtype=np.float64).reshape(-1, 3) * scale
            F = np.asarray(src.indices, dtype=np.int64).reshape(-1, 3)
        self._shape_tf = _np(model.shape_transform).astype(np.float64)
        self._shape_body = _np(model.shape_body)
        body_q = _np(model.body_q) if int(getattr(model, "body_count", 0) or 0) else None
        R0, t0 = self._shape_pose(s, body_q)
        try:
            rb = RigidBody((V @ R0.T + t0, F), density=1000.0, name=f"shape{s}")
        except ValueError as e:
            raise NewtonInteropError(f"SolverFEM: shape {s} cannot be a kinematic body of shape_contact='surface' "
                                     f"({e}); use shape_contact='collider'") from None
        self._kinematic_frames.append((R0, R0.T @ (rb.center_of_mass - t0)))
        return rb

    def _kinematic_pose_nodes(self, s, body_q, frame):
        """(4, 3) the nodes (p, a_1, a_2, a_3) of kinematic shape s at its pose on ``body_q``:
        A = R R0^T, p = R c + t (c the centre of mass in the shape's frame)."""
        R0, c = frame
        R, t = self._shape_pose(s, body_q)
        A = R @ R0.T
        return np.vstack([R @ c + t, A.T])

    def _rigid_nodes(self, body_q, body_qd):
        """(4 k, 3) positions and velocities of the rigid nodes (p, a_1, a_2, a_3 per body) of newton's
        body_q / body_qd: p = the world COM, A = R R0^T (R0 the body's rotation when the solver was
        built), p-dot = the COM velocity, A-dot = [w]x A."""
        x, v = [], []
        for b, (R0, com_b) in zip(self.rigid_bodies, self._rigid_frames):
            B, V = body_q[b].astype(np.float64), body_qd[b].astype(np.float64)
            R = _rotation(B[3:7])
            A = R @ R0.T
            x += [B[:3] + R @ com_b, *A.T]
            v += [V[:3], *np.cross(V[3:], A.T)]
        return np.asarray(x), np.asarray(v)

    def _rigid_state(self, x, v):
        """(body_q rows, body_qd rows, largest |A^T A - I|) of the rigid nodes in warpfem's unknown x, v."""
        lay = self.warpfem_model.rigid
        q_out, qd_out, err = [], [], 0.0
        for r, (R0, com_b) in enumerate(self._rigid_frames):
            p, A = lay.pose(x, r)
            pd, Ad = lay.pose(v, r)
            err = max(err, float(np.abs(A.T @ A - np.eye(3)).max()))
            Q = _polar_rotation(A)
            R = Q @ R0
            W = Ad @ np.linalg.inv(A)  # A-dot A^-1 = [w]x for a rotation
            w = 0.5 * np.array([W[2, 1] - W[1, 2], W[0, 2] - W[2, 0], W[1, 0] - W[0, 1]])
            q_out.append(np.concatenate([p - R @ com_b, _quaternion(R)]))
            qd_out.append(np.concatenate([pd, w]))
        return np.asarray(q_out), np.asarray(qd_out), err

    def _setup_colliders(self, model):
        GeoType = newton.GeoType
        n_shapes = int(getattr(model, "shape_count", 0) or 0)
        self._colliders = []  # (shape index, collider)
        if n_shapes == 0:
            return
        types = _np(model.shape_type)
        flags = _np(model.shape_flags)
        scale = _np(model.shape_scale).astype(np.float64)
        mu = _np(model.shape_material_mu).astype(np.float64)
        self._shape_tf = _np(model.shape_transform).astype(np.float64)
        self._shape_body = _np(model.shape_body)
        source = getattr(model, "shape_source", None)
        body_q = _np(model.body_q) if int(getattr(model, "body_count", 0) or 0) else None
        collide = int(newton.ShapeFlags.COLLIDE_PARTICLES)
        chosen = range(n_shapes) if isinstance(self.shapes, str) else self.shapes
        for s in chosen:
            if not 0 <= s < n_shapes:
                raise NewtonInteropError(f"SolverFEM: shape index {s} out of range [0, {n_shapes})")
            if not (int(flags[s]) & collide) or (self.shapes == "static" and int(self._shape_body[s]) >= 0):
                continue
            if int(self._shape_body[s]) in self.rigid_bodies or s in self.kinematic_shapes:  # simulated as a body
                continue
            t = GeoType(int(types[s]))
            if self.friction == "shape":
                f = float(mu[s])
            elif self.friction == "average":
                f = 0.5 * (float(model.soft_contact_mu) + float(mu[s]))
            else:
                f = float(self.friction)
            kw = dict(friction=f, name=f"shape{s}", **self.contact_options)
            if t == GeoType.PLANE:
                c = _PosedPlane(point=(0.0, 0.0, 0.0), normal=(0.0, 0.0, 1.0), **kw)
            elif t == GeoType.SPHERE:
                c = _PosedSphere(center=(0.0, 0.0, 0.0), radius=float(scale[s][0]), **kw)
            elif t == GeoType.BOX:
                c = _PosedBox(box_min=-scale[s], box_max=scale[s], **kw)
            elif t == GeoType.CAPSULE:  # newton's: radius scale[0], half height scale[1], along local z
                c = _PosedCapsule(center=(0.0, 0.0, 0.0), radius=float(scale[s][0]), half_length=float(scale[s][1]),
                                  axis="z", **kw)
            elif t == GeoType.MESH and source is not None and source[s] is not None:
                src = source[s]
                V = np.asarray(src.vertices, dtype=np.float64).reshape(-1, 3) * scale[s]
                T = np.asarray(src.indices, dtype=np.int64).reshape(-1, 3)
                c = _PosedMesh(vertices=V, triangles=T, **kw)
            else:
                if self.unsupported_shapes == "ignore":
                    continue
                raise NewtonInteropError(f"SolverFEM: shape {s} is a {t.name.lower()}; its colliders are "
                                         f"{', '.join(SUPPORTED_SHAPES)} (pass unsupported_shapes='ignore' to leave "
                                         "the others out)")
            c.newton_pose = self._shape_pose(s, body_q)
            if self.simulator.contact is None and len(self.kinematic_shapes):  # colliders leave kinematic shapes out
                from warpfem.contact import ContactSet

                cs = ContactSet(self.simulator.rigid.space)
                lay = self.warpfem_model.rigid
                cs.exclude_vertices(np.flatnonzero(lay.vertex_body >= len(self.rigid_bodies)))
                self.simulator.contact = cs
            self.simulator.add_collider(c)
            self._colliders.append((s, c))

    # -- the step ----------------------------------------------------------------------------------
    def notify_model_changed(self, flags):
        """Gravity (``ModelFlags.MODEL_PROPERTIES``) is read again; with ``rigid_bodies``, new
        ``body_mass`` / ``body_inertia`` / ``body_com`` (``ModelFlags.BODY_INERTIAL_PROPERTIES``: a
        coupler's proxy masses) rebuild the warpfem model, keeping its state. Other changes need a new solver."""
        if self.rigid_bodies and int(flags) & int(newton.ModelFlags.BODY_INERTIAL_PROPERTIES):
            rb = self.rigid_bodies
            now = [_np(self.model.body_mass)[rb], _np(self.model.body_inertia)[rb], _np(self.model.body_com)[rb]]
            if any(not np.array_equal(a, b) for a, b in zip(now, self._inertial)):
                self._rebuild()
        if int(flags) & int(newton.ModelFlags.MODEL_PROPERTIES):
            self.warpfem_model.gravity = self._gravity(self.model)
            self.simulator.sync_model()

    def _rebuild(self):
        """A new warpfem model and simulator from ``self.model`` (its masses changed), continuing
        from the current positions and velocities (the integrator's history restarts)."""
        x, v = self.simulator.positions(), self.simulator.velocities()
        last = (self._last_q, self._last_qd, self._last_body, self.resyncs, self.body_reads)
        SolverFEM.__init__(self, self.model, **self._options)
        self.simulator.set_positions(x)
        self.simulator.set_velocities(v)
        self._last_q, self._last_qd, self._last_body, self.resyncs, self.body_reads = last

    def _sync_bodies(self, body):
        """Read only the rigid bodies of a newton state (``body`` = (body_q, body_qd)): the soft
        particles keep warpfem's own state (a coupler moving its proxy bodies between steps)."""
        n = self._n_soft
        xr, vr = self._rigid_nodes(*body)
        x, v = self.simulator.positions(), self.simulator.velocities()
        x[n:n + len(xr)], v[n:n + len(xr)] = xr, vr
        self.simulator.set_positions(x)
        self.simulator.set_velocities(v)
        self.body_reads += 1

    def _sync_from(self, q, qd, body=None):
        """Read the simulated particles (and rigid bodies: ``body`` = (body_q, body_qd)) of a newton
        state into warpfem's state."""
        x = q.astype(np.float64)
        v = qd.astype(np.float64)
        v[self._fixed] = 0.0
        if self.rigid_bodies:
            xr, vr = self._rigid_nodes(*body)
            x, v = np.concatenate([x, xr]), np.concatenate([v, vr])
        if len(self.kinematic_shapes):  # kinematic shapes stay where they are (this step moves them)
            tail = self.simulator.positions()[len(x):]
            x, v = np.concatenate([x, tail]), np.concatenate([v, np.zeros_like(tail)])
        self.simulator.set_positions(x)
        self.simulator.set_velocities(v)
        self.resyncs += 1

    def step(self, state_in, state_out, control, contacts, dt, *, observables=None):
        """Advance the tetrahedra's particles by ``dt`` from ``state_in`` into ``state_out``
        (``particle_q``, ``particle_qd``; other particles are copied). ``contacts`` is not used:
        SolverFEM finds its own contacts with the colliding shapes each Newton iteration.

        Raises :class:`warpfem.SolveFailed` (nothing written, warpfem's state as before) when the
        step produced NaN/inf or, with ``require_convergence``, did not converge. On a ``wp.Tape`` the
        step is differentiable with respect to ``state_in.particle_q`` / ``particle_qd`` / ``particle_f`` (warpfem's
        adjoint; docs/newton.md, "Gradients")."""
        del contacts, observables
        from warpfem.solvers.adjoint import active_tape

        sim, idx = self.simulator, self.particles
        q_all = state_in.particle_q.numpy()
        qd_all = state_in.particle_qd.numpy()
        q, qd = q_all[idx], qd_all[idx]
        self._checked_positions(q, "state_in.particle_q")
        if not np.all(np.isfinite(qd)):
            bad = int(idx[np.flatnonzero(~np.isfinite(qd).all(axis=1))[0]])
            raise NewtonInteropError(f"SolverFEM: state_in.particle_qd of particle {bad} is not finite")
        free = np.ones(len(idx), dtype=bool)
        free[self._fixed] = False
        body = None
        if self.rigid_bodies:
            body = (state_in.body_q.numpy(), state_in.body_qd.numpy())
            rb = self.rigid_bodies
            if not (np.all(np.isfinite(body[0][rb])) and np.all(np.isfinite(body[1][rb]))):
                raise NewtonInteropError("SolverFEM: state_in.body_q / body_qd of a rigid body is not finite")
            moved = self._last_body is None or not (np.array_equal(body[0][rb], self._last_body[0])
                                                    and np.array_equal(body[1][rb], self._last_body[1]))
        else:
            moved = False
        if (self._last_q is None or not np.array_equal(q[free], self._last_q[free])
                or not np.array_equal(qd[free], self._last_qd[free])):
            self._sync_from(q, qd, body)
        else:
            if moved:
                self._sync_bodies(body)
            if len(self._fixed) and not np.array_equal(q[self._fixed], self._last_q[self._fixed]):
                sim.set_targets(self._fixed, q[self._fixed].astype(np.float64))  # kinematic particles moved
        # external forces: state_in.particle_f
        f_all = state_in.particle_f.numpy() if state_in.particle_f is not None else None
        f = None if f_all is None else f_all[idx]
        self.last_particle_force = np.zeros(3) if f is None else f.astype(np.float64).sum(axis=0)
        n = self._n_soft
        fr = None
        if self.rigid_bodies and getattr(state_in, "body_f", None) is not None:
            fr = self._rigid_forces(state_in.body_f.numpy())
        if (f is not None and np.any(f != 0)) or fr is not None or self._forces_on:
            forces = self.warpfem_model.forces
            forces[:] = 0.0
            if f is not None:
                forces[:n] = f.astype(np.float64)
            if fr is not None:
                forces[n:n + len(fr)] = fr
            sim.sync_model()
            self._forces_on = bool(np.any(forces != 0))
        if self._colliders or len(self.kinematic_shapes):
            body_q = state_in.body_q.numpy() if getattr(state_in, "body_q", None) is not None else None
            for s, c in self._colliders:
                c.newton_pose = self._shape_pose(s, body_q)
            for s, k, frame in zip(self.kinematic_shapes, self._kinematic_nodes, self._kinematic_frames):
                nodes = self._kinematic_pose_nodes(s, body_q, frame)
                for j in range(4):  # the step moves the shape from where it is to this pose
                    sim.control.targets[int(k) + j] = nodes[j]
        if active_tape() is not None:
            if self.rigid_bodies or len(self.kinematic_shapes):
                raise NewtonInteropError("SolverFEM: steps on a wp.Tape do not support rigid_bodies or "
                                         "shape_contact='surface' yet (body_q / body_qd are not mapped to warpfem's "
                                         "state on the tape)")
            self._taped_step(state_in, state_out, float(dt))
            return
        self.last_stats = sim.step(dt=float(dt))
        X, Vel = sim.positions(), sim.velocities()
        x = X[:n].astype(np.float32)
        v = Vel[:n].astype(np.float32)
        q_out, qd_out = q_all.copy(), qd_all.copy()
        q_out[idx], qd_out[idx] = x, v
        state_out.particle_q.assign(q_out)
        state_out.particle_qd.assign(qd_out)
        self._last_q, self._last_qd = x, v
        if self.rigid_bodies:
            bq, bqd, self.last_orthogonality_error = self._rigid_state(X, Vel)
            body_q, body_qd = body[0].copy(), body[1].copy()
            body_q[self.rigid_bodies], body_qd[self.rigid_bodies] = bq, bqd
            state_out.body_q.assign(body_q)
            state_out.body_qd.assign(body_qd)
            self._last_body = (body_q[self.rigid_bodies], body_qd[self.rigid_bodies])
        elif state_out is not state_in:  # bodies are not SolverFEM's: passed through
            for name in ("body_q", "body_qd"):
                a, b = getattr(state_in, name, None), getattr(state_out, name, None)
                if a is not None and b is not None and a.shape == b.shape and a.size:
                    wp.copy(b, a)

    def _rigid_forces(self, body_f):
        """(4 k, 3) generalised forces on the rigid nodes of newton's ``body_f`` (world wrench
        (f, tau) at the COM): f on p and tau x a_k / 2 on a_k (sum_k a_k x (tau x a_k) / 2 = tau
        for a rotation A), at the start-of-step A; None when every wrench is zero."""
        w = body_f[self.rigid_bodies].astype(np.float64)
        if not np.any(w != 0):
            return None
        x = self.simulator.positions()
        out = []
        for r in range(len(self.rigid_bodies)):
            _, A = self.warpfem_model.rigid.pose(x, r)
            out += [w[r, :3], *(0.5 * np.cross(w[r, 3:], A.T))]
        return np.asarray(out)

    def _taped_step(self, state_in, state_out, dt):
        """The step on a ``wp.Tape``: newton's arrays into a new warpfem state and back by Warp
        kernels (taped), the warpfem step in between with its own recorded backward (docs/gradients.md)."""
        from warpfem.solvers.adjoint import active_tape, tape_adjoint

        sim = self.simulator
        dev = sim.device
        if getattr(self, "_tape_maps", None) is None:
            vertex = np.full(int(self.model.particle_count), -1, dtype=np.int32)
            vertex[self.particles] = np.arange(len(self.particles), dtype=np.int32)
            fixed = np.zeros(len(self.particles), dtype=np.int32)
            fixed[self._fixed] = 1
            self._tape_maps = (wp.array(self.particles.astype(np.int32), dtype=wp.int32, device=dev),
                               wp.array(fixed, dtype=wp.int32, device=dev), wp.array(vertex, dtype=wp.int32, device=dev))
            self.tape_states = []
        idx, fixed, vertex = self._tape_maps
        wf_in, wf_out = sim.new_state(requires_grad=True), sim.new_state(requires_grad=True)
        wf_in.history.clear()
        wf_out.history.clear()
        wp.launch(_gather, dim=len(self.particles),
                  inputs=[idx, fixed, state_in.particle_q, state_in.particle_qd], outputs=[wf_in.x, wf_in.v], device=dev)
        tape = active_tape()
        f_in = getattr(state_in, "particle_f", None)
        if f_in is not None and f_in.requires_grad:  # d loss / d particle_f: warpfem's "forces" gradient of this step
            f_wf = wp.zeros_like(wf_in.x, requires_grad=True)
            wp.launch(_gather, dim=len(self.particles), inputs=[idx, fixed, f_in, f_in],
                      outputs=[f_wf, wp.zeros_like(wf_in.v)], device=dev)
            adj, n, before = tape_adjoint(sim), self._n_soft, {}

            def forces_grad():  # runs after the step's backward: what it added to the forces' gradient
                delta = adj.grads["forces"][:n] - before.pop("forces")
                f_wf.grad.assign(f_wf.grad.numpy() + delta.astype(f_wf.grad.numpy().dtype))

            def forces_before():  # runs before the step's backward
                before["forces"] = adj.grads["forces"][:n].copy()

            tape.record_func(forces_grad, [f_wf])
            self.last_stats = sim.step(wf_in, wf_out, None, dt)
            tape.record_func(forces_before, [])
        else:
            self.last_stats = sim.step(wf_in, wf_out, None, dt)
        wp.launch(_scatter, dim=int(self.model.particle_count),
                  inputs=[vertex, wf_out.x, wf_out.v, state_in.particle_q, state_in.particle_qd],
                  outputs=[state_out.particle_q, state_out.particle_qd], device=dev)
        self.tape_states.append((wf_in, wf_out))  # alive as long as the tape may need them
        self._last_q = self._last_qd = None  # the next untaped step reads state_out again

    def coupling_harvest_proxy_wrenches(self, body_local_to_proxy_global, out_body_f, *, body_qd_before, state,
                                        state_out, contacts, dt):
        """The coupler's feedback on its proxy bodies: newton's momentum change m (v' - v) / dt and
        R I R^T (w' - w) / dt, plus what ``damping_mass`` took from them (alpha m v', alpha R I R^T w':
        warpfem's mass damping acts on the rigid bodies too and is not a contact force)."""
        super().coupling_harvest_proxy_wrenches(body_local_to_proxy_global, out_body_f, body_qd_before=body_qd_before,
                                                state=state, state_out=state_out, contacts=contacts, dt=dt)
        alpha = float(self.simulator.damping_mass)
        if alpha == 0.0 or not self.rigid_bodies:
            return
        gid = _np(body_local_to_proxy_global)
        qd, q = state_out.body_qd.numpy(), state_out.body_q.numpy()
        mass, inertia = _np(self.model.body_mass), _np(self.model.body_inertia)
        out = out_body_f.numpy()
        for b in self.rigid_bodies:
            if b < len(gid) and gid[b] >= 0:
                R = _rotation(q[b][3:7])
                out[gid[b], :3] += alpha * mass[b] * qd[b][:3]
                out[gid[b], 3:] += alpha * (R @ inertia[b] @ R.T @ qd[b][3:])
        out_body_f.assign(out)

    def tet_material_gradients(self) -> np.ndarray:
        """(1, 2) d loss / d(k_mu, k_lambda) of the model's ``tet_materials`` (one change to every
        tetrahedron: one (k_mu, k_lambda) group) from the ``wp.Tape`` backward of the taped steps
        (warpfem's Young's modulus and Poisson ratio gradients through :func:`lame_to_youngs`;
        ``simulator.adjoint.zero_grad()`` clears them). Several groups: not supported."""
        adj = getattr(self.simulator, "adjoint", None)
        if adj is None:
            raise NewtonInteropError("SolverFEM.tet_material_gradients: no taped step yet (step on a wp.Tape, "
                                     "then tape.backward(loss))")
        if len(self.materials) != 1:
            raise NewtonInteropError(f"SolverFEM.tet_material_gradients: {len(self.materials)} (k_mu, k_lambda) "
                                     "groups; only a model of one group is supported")
        g = adj.parameter_gradients()
        gE, gn = float(np.ravel(g["youngs_modulus"])[0]), float(np.ravel(g["poisson_ratio"])[0])
        m = self.materials[0]
        mu, lam = float(m.mu_lame), float(m.lam_lame)
        s2 = (lam + mu) ** 2
        dE = ((3 * lam * lam + 4 * lam * mu + 2 * mu * mu) / s2, mu * mu / s2)  # dE/dmu, dE/dlam
        dn = (-lam / (2 * s2), mu / (2 * s2))  # dnu/dmu, dnu/dlam
        return np.array([[gE * dE[0] + gn * dn[0], gE * dE[1] + gn * dn[1]]])

    # -- reading back --------------------------------------------------------------------------------
    def positions(self) -> np.ndarray:
        """warpfem's current positions (float64, one row per simulated particle, ``particles`` order)."""
        return self.simulator.positions()[:self._n_soft]

    def contact_forces(self) -> np.ndarray:
        """(particles, 3) the colliders' contact forces (barrier + friction, N) on the simulated
        particles at warpfem's current state (zeros without colliders)."""
        c = self.simulator.contact
        if c is None:
            return np.zeros((len(self.particles), 3))
        return c.forces()[:self._n_soft]

    def rigid_contact_forces(self) -> np.ndarray:
        """(rigid bodies, 3) the colliders' contact forces (N) summed over each rigid body's
        vertices at warpfem's current state (``rigid_bodies`` order)."""
        c, lay = self.simulator.contact, getattr(self.warpfem_model, "rigid", None)
        out = np.zeros((len(self.rigid_bodies), 3))
        if c is None or lay is None:
            return out
        F = c.forces()
        for r in range(len(self.rigid_bodies)):
            out[r] = F[lay.vertex_body == r].sum(axis=0)
        return out

