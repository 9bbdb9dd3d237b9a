"""The physical model: a mesh, a material, boundary conditions and loads (device independent)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import scipy.sparse

from warpfem.elements import precompute_quadrature
from warpfem.mesh.mass import MASS_MATRIX_KINDS, mass_matrices

_COMPONENTS = {"x": 0, "y": 1, "z": 2}


def parse_components(components: str) -> list[int]:
    """'xyz', 'z', 'xz', ... -> axis indices; raises ValueError for anything else."""
    if not isinstance(components, str) or not components or any(c not in _COMPONENTS for c in components) \
            or len(set(components)) != len(components):
        raise ValueError(f"components must be a non-empty subset of 'xyz' without repeats, got {components!r}")
    return sorted(_COMPONENTS[c] for c in components)


def rigid_body_modes(positions, *, normalize: bool = True) -> np.ndarray:
    """(3n, 6) translations and rotations about the centroid of ``positions`` (n, 3), DOF-major
    per vertex (x0, y0, z0, x1, ...): column a < 3 the unit translation along axis a, column 3 + a
    the rotation e_a x (X - c); each column scaled to unit norm unless ``normalize=False``."""
    X = np.asarray(positions, dtype=np.float64)
    n = len(X)
    d = X - X.mean(axis=0)
    B = np.zeros((n, 3, 6))
    for a in range(3):
        B[:, a, a] = 1.0
    # rotation about axis e_a: u = e_a x d
    B[:, 1, 3], B[:, 2, 3] = -d[:, 2], d[:, 1]
    B[:, 0, 4], B[:, 2, 4] = d[:, 2], -d[:, 0]
    B[:, 0, 5], B[:, 1, 5] = -d[:, 1], d[:, 0]
    B = B.reshape(3 * n, 6)
    if not normalize:
        return B
    norms = np.linalg.norm(B, axis=0)
    norms[norms == 0.0] = 1.0
    return B / norms


def _direction(v) -> str:
    """'the x axis' for a coordinate direction, else the unit vector."""
    u = np.asarray(v, dtype=np.float64) / np.linalg.norm(v)
    for a, name in enumerate("xyz"):
        if abs(abs(u[a]) - 1.0) < 1e-6:
            return f"the {name} axis"
    u = u * np.sign(u[np.argmax(np.abs(u))])
    return f"({u[0]:.3g}, {u[1]:.3g}, {u[2]:.3g})"


def static_supports_error(model, what: str) -> str:
    """'' when the fixed components of ``model`` remove every rigid motion, else the error message
    of a static solve (``what`` names how to fix components: "[[fixed]] or [[handle]]", ...)."""
    free = model.free_rigid_motions()
    if not free:
        return ""
    axes = [a for a, f in zip("xyz", model.fixed.any(axis=0)) if not f]
    return ("a static solve needs fixed components that remove every rigid motion (without mass nothing "
            f"holds them: the Newton systems are singular); still free: {'; '.join(free)}"
            + (f" (free axes: {axes})" if axes else "")
            + f". Fix more components ({what}) or use a time integrator")


def _free_motions(X, fixed) -> list[str]:
    """The rigid motions of one body (rest positions ``X`` (n, 3)) that its fixed components
    (``fixed`` (n, 3) bool) leave free, in words (``Model.free_rigid_motions``)."""
    c = X.mean(axis=0)
    L = float(np.linalg.norm(np.ptp(X, axis=0))) or 1.0
    n = len(X)
    B = rigid_body_modes(X, normalize=False)  # columns: translations, e_a x (X - c)
    norms = np.linalg.norm(B, axis=0)
    norms[norms == 0.0] = 1.0
    rows = (B / norms).reshape(n, 3, 6)[fixed]  # unit columns: a rank test free of units
    if rows.shape[0]:
        _, sv, Vt = np.linalg.svd(rows, full_matrices=True)
        rank = int(np.sum(sv > 1e-9 * sv[0])) if sv.size else 0
        N = Vt[rank:].T  # (6, k) coefficients of the free motions (unit columns)
    else:
        N = np.eye(6)
    if N.shape[1] == 0:
        return []
    out = []
    # pure translations: the combinations of N with no rotation part
    _, sr, Vr = np.linalg.svd(N[3:], full_matrices=True)
    rr = int(np.sum(sr > 1e-9)) if sr.size else 0
    T = np.linalg.qr((N @ Vr[rr:].T)[:3])[0][:, : N.shape[1] - rr]  # (3, kt) free translations
    out += [f"translation along {_direction(b)}" for b in T.T]
    Q = (N @ Vr[:rr].T) / norms[:, None]  # (6, kr) motions that rotate: (t, w) in m and 1/m
    if rr:
        # rotation axes: the coordinate axes in the span of the free rotation parts first
        Wb = np.linalg.qr(Q[3:])[0][:, :rr]
        axes = [e for e in np.eye(3) if np.linalg.norm(e - Wb @ (Wb.T @ e)) < 1e-9]
        for e in list(Wb.T):  # then the rest of the span, orthogonal to those
            r = e - sum(((a @ e) * a for a in axes), np.zeros(3))
            if len(axes) < rr and np.linalg.norm(r) > 1e-6:
                axes.append(r / np.linalg.norm(r))
        for w in axes[:rr]:  # a unit rotation about w: v = t + w x (X - c)
            coef = np.linalg.lstsq(Q[3:], w, rcond=None)[0]
            t = Q[:3] @ coef
            t = t - T @ (T.T @ t)  # the part no free translation explains
            p = c + np.cross(w, t)  # the axis point nearest the centroid
            p[np.abs(p) < 1e-9 * L] = 0.0
            text = f"rotation about {_direction(w)} through ({p[0]:.4g}, {p[1]:.4g}, {p[2]:.4g})"
            if abs(float(t @ w)) > 1e-9 * L:
                text += " (with a slide along it)"
            out.append(text)
    return out


class Model:
    """Bodies ready to simulate: their meshes and materials, fixed DOFs and loads.

    A model is a list of bodies (``bodies``, :class:`BaseBody`) in one vertex space; ``Model(mesh,
    material)`` is the one-body case (a :class:`Body` of ``mesh`` named after it, or "body") and
    :meth:`from_bodies` the general one; both build the model the same way.

    Args:
        mesh: a volume mesh (``warpfem.mesh.VolumeMesh`` of any element type, or any object with
            ``vertices``, ``elements`` and ``element_type``), positions in m.
        material: a material from ``warpfem.materials`` (carries the density, kg/m^3).
        gravity: acceleration (m/s^2), applied as lumped-mass body force (the total equals
            rho g V exactly for either mass matrix).
        mass_matrix: "lumped" (diagonal: the element type's lumping) or "consistent" (rho int N_a N_b dV;
            Tet4: rho V / 20 (1 + delta_ij) per tet; Zienkiewicz & Taylor, "The Finite Element
            Method"); ``warpfem.mesh.mass``.
        volumetric_integration: "full" or "reduced" (Hex8 meshes only, any material with
            ``volumetric_split()``, 0 <= nu < 0.5): selective reduced integration, the energy split
            exactly into a lambda-scaled volumetric part on 1 point per element and the rest on
            2x2x2, so nearly incompressible Hex8 does not lock. Linear: lam/2 tr(eps)^2 | mu eps:eps;
            StVK: lam/2 tr(E)^2 | mu E:E; corotated: lam/2 (J - 1)^2 | mu ||F - R||^2; stable
            neo-Hookean: lambda_L/2 (J - 1)^2 | the rest (see ``Material.volumetric_split``).
    """

    #: the rigid bodies' layout (``warpfem.rigid.model.RigidLayout``) of a model with some, else None
    rigid = None
    #: (n, 3) rest positions of every body's vertices in body order (``body_offsets``): the same as
    #: ``rest_positions`` without rigid bodies; with them, a rigid body's vertices where its mesh puts
    #: them (``rest_positions`` then holds its four nodes: docs/rigid.md)
    vertex_rest_positions = None

    def __init__(self, mesh, material, *, gravity=(0.0, 0.0, 0.0), mass_matrix: str = "lumped",
                 volumetric_integration: str = "full"):
        # a model of one mesh is the one-body case of Model.from_bodies: the same construction
        body = Body(mesh, material, volumetric_integration=volumetric_integration, mass_matrix=mass_matrix)
        body.name = getattr(mesh, "name", None) or "body"
        _construct(self, [body], gravity=gravity, mass_matrix=mass_matrix)

    # -- rest state -----------------------------------------------------------------------------
    @property
    def total_mass(self) -> float:
        """kg."""
        return float(self.lumped_mass.sum())

    def external_forces(self) -> np.ndarray:
        """Constant external force per vertex (N): gravity M (1 x g) on the model's mass matrix (the
        lumped mass, or rho int N_a dV with the consistent one) plus applied forces."""
        return self.gravity_mass[:, None] * self.gravity[None, :] + self.forces

    # -- boundary conditions and loads -----------------------------------------------------------
    def indices(self, indices) -> np.ndarray:
        """Vertex indices as a flat int64 array, checked (TypeError for non-integers, IndexError
        naming the first index out of range)."""
        idx = np.atleast_1d(np.asarray(indices))
        if idx.size and (idx.dtype.kind not in "iu"):
            raise TypeError(f"vertex indices must be integers, got dtype {idx.dtype}")
        idx = idx.astype(np.int64).ravel()
        if getattr(self, "rigid", None) is not None:  # soft vertices only (warpfem.rigid)
            self.rigid.check_vertices(idx)
        bad = idx[(idx < 0) | (idx >= self.num_vertices)]
        if bad.size:
            raise IndexError(f"vertex index {int(bad[0])} out of range [0, {self.num_vertices}) ({bad.size} bad)")
        return idx

    def fix(self, indices, components: str = "xyz") -> None:
        """Fix the given displacement components of vertices (Dirichlet)."""
        self.fixed[np.ix_(self.indices(indices), parse_components(components))] = True

    def release(self, indices, components: str = "xyz") -> None:
        """Free previously fixed components."""
        self.fixed[np.ix_(self.indices(indices), parse_components(components))] = False

    def free_rigid_motions(self) -> list[str]:
        """The rigid motions the fixed components leave free, described in words ([] when none).

        A rigid motion v(X) = t + w x (X - c) (c the centroid) is free when it moves no fixed
        component: the null space of the 6 rigid modes restricted to the fixed rows. Pure
        translations are named by their direction; every other free motion as a rotation about
        an axis through a point (p = c + w x t / |w|^2), plus its slide along the axis if any.
        A static solve of such a model is singular (no mass term holds the motion). Several
        bodies: each body's free motions, prefixed by its name.
        """
        out = []
        for name, lo, hi in zip(self.body_names, self.body_offsets[:-1], self.body_offsets[1:]):
            motions = _free_motions(self.rest_positions[lo:hi], self.fixed[lo:hi])
            out += motions if len(self.bodies) == 1 else [f"{name}: {m}" for m in motions]
        return out

    def add_force(self, indices, force) -> None:
        """Add a constant force (N) to each given vertex (with rigid bodies: vertex indices of every
        body, ``body_offsets``; on a rigid body's vertex the force and its torque act on the body)."""
        f = np.asarray(force, dtype=np.float64)
        if f.shape != (3,) or not np.all(np.isfinite(f)):
            raise ValueError(f"force must be 3 finite numbers, got {force!r}")
        if self.rigid is not None:  # vertices of every body; a rigid body's force acts through E^T
            self.rigid.add_force(self.forces, indices, f)
            return
        np.add.at(self.forces, self.indices(indices), f)


    # -- several bodies (Model.from_bodies) -------------------------------------------------------
    @classmethod
    def from_bodies(cls, bodies, *, gravity=(0.0, 0.0, 0.0), mass_matrix: str = "lumped",
                    check_overlap: bool = True) -> "Model":
        """A model of several bodies (:class:`Body`: mesh, material, name, offset, initial velocity),
        simulated together by one simulator.

        One vertex space: the bodies' vertices concatenated in body order (``body_offsets``: the
        first vertex of each body, then the total); ``rest_positions``, ``fixed``, ``forces``,
        ``lumped_mass`` and the (block-diagonal) ``mass`` are global, ``quadratures`` holds one
        quadrature set per body (its element type, connectivity in global indices) and
        ``materials`` one material per body, so each body keeps its own element type and material.
        ``mesh`` is a :class:`BodiesMesh` (the bodies' boundary triangles in global indices, the
        body of each vertex); :meth:`body_vertices` maps a body's own vertex indices to global
        ones. ``gravity`` and ``mass_matrix`` apply to every body (a body may set its own mass
        matrix). Bodies interact only through contact forms; without them each moves exactly as
        it would alone. One body gives the model ``Model(mesh, material)`` builds (the same
        construction): ``mesh``, ``quadrature`` and ``volumetric_integration`` are that body's.

        Bodies that overlap at the start (boundary surfaces crossing, or one inside another) are
        refused with :class:`warpfem.mesh.intersect.BodyOverlapError` naming the two bodies and the
        first crossing (an edge of one through a triangle of the other, with positions);
        ``check_overlap=False`` skips the test (``warpfem.mesh.intersect.first_body_overlap``).

        Rigid bodies (:class:`warpfem.RigidBody`, after the soft bodies in the list): the model's
        unknown then holds four nodes per rigid body in place of its vertices (``num_vertices``,
        ``rest_positions``, ``mass``, ``fixed`` are of the unknown; ``body_offsets`` and ``mesh``
        stay of the vertices; ``rigid`` maps one to the other: docs/rigid.md).
        """
        bodies = list(bodies)
        if not bodies:
            raise ValueError("Model.from_bodies needs at least one body")
        from warpfem.rigid.body import RigidBody

        names = [b.name or f"body{i + 1}" for i, b in enumerate(bodies)]
        rigid = [isinstance(b, RigidBody) for b in bodies]
        for i, b in enumerate(bodies):
            if not rigid[i] and not isinstance(b, BaseBody):
                raise TypeError(f"body #{i + 1} must be a warpfem.Body or warpfem.RigidBody, got {type(b).__name__}")
        if any(rigid):  # the unknown holds the soft vertices first, then four nodes per rigid body
            first = rigid.index(True)
            late = [names[i] for i in range(first, len(bodies)) if not rigid[i]]
            if late:
                raise ValueError(f"Model.from_bodies: soft body {late[0]!r} comes after rigid body {names[first]!r}; "
                                 "list the soft bodies first, then the rigid ones")
        dup = sorted({n for n in names if names.count(n) > 1})
        if dup:
            raise ValueError(f"body names must be unique, {dup[0]!r} is given {names.count(dup[0])} times")
        for b, n in zip(bodies, names):
            b.name = n
        if check_overlap and len(bodies) > 1:  # a crossing needs two bodies
            from warpfem.mesh.intersect import BodyOverlapError, first_body_overlap

            problem = first_body_overlap([b.mesh for b in bodies], names)
            if problem:
                raise BodyOverlapError(problem)
        model = cls.__new__(cls)
        _construct(model, bodies, gravity=gravity, mass_matrix=mass_matrix, name_errors=True)
        return model

    @property
    def num_bodies(self) -> int:
        """How many bodies the model holds (1 for a single-mesh model)."""
        return len(self.bodies)

    def body_index(self, body) -> int:
        """The index of ``body`` (its name, index or :class:`Body`); KeyError naming the bodies."""
        names = self.body_names
        if isinstance(body, BaseBody):
            body = body.name
        if isinstance(body, (int, np.integer)) and not isinstance(body, bool):
            if 0 <= int(body) < len(names):
                return int(body)
            raise KeyError(f"body index {body} out of range [0, {len(names)})")
        if body in names:
            return names.index(body)
        raise KeyError(f"no body {body!r}; bodies: {', '.join(names)}")

    def body_vertices(self, body, indices=None) -> np.ndarray:
        """Global vertex indices of ``body``'s own vertex ``indices`` (default: all its vertices)."""
        b = self.body_index(body)
        lo, hi = int(self.body_offsets[b]), int(self.body_offsets[b + 1])
        if indices is None:
            return np.arange(lo, hi, dtype=np.int64)
        idx = np.atleast_1d(np.asarray(indices))
        if idx.size and idx.dtype.kind not in "iu":
            raise TypeError(f"vertex indices must be integers, got dtype {idx.dtype}")
        idx = idx.astype(np.int64).ravel()
        bad = idx[(idx < 0) | (idx >= hi - lo)]
        if bad.size:
            raise IndexError(f"body {self.body_names[b]!r}: vertex index {int(bad[0])} out of range [0, {hi - lo})")
        return idx + lo

    def vertex_bodies(self) -> np.ndarray:
        """(n,) the body index of each vertex (all 0 for a single-mesh model)."""
        return np.repeat(np.arange(len(self.body_offsets) - 1), np.diff(self.body_offsets))

    def boundary_edges(self) -> np.ndarray:
        """(e, 2) unique edges (i < j) of the boundary triangles ``mesh.boundary_faces()`` (every
        body's, global vertex indices); with :meth:`vertex_bodies` what a body-body contact needs."""
        f = np.asarray(self.mesh.boundary_faces(), dtype=np.int64)
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        return np.unique(e, axis=0)

    def initial_velocities(self):
        """(n, 3) velocities at t = 0 (the bodies' ``initial_velocity``), or None when all are zero.
        With rigid bodies: of the unknown's nodes (``warpfem.rigid.model``)."""
        if self.rigid is not None:
            soft = [np.repeat(b.initial_velocity[None], n, axis=0) for b, n in
                    zip(self.bodies, np.diff(self.body_offsets)[:len(self.bodies) - len(self.rigid.bodies)])]
            return self.rigid.initial_velocities(np.concatenate(soft) if soft else np.zeros((0, 3)))
        if not any(np.any(b.initial_velocity != 0.0) for b in self.bodies):
            return None
        return np.repeat(np.stack([b.initial_velocity for b in self.bodies]), np.diff(self.body_offsets), axis=0)

# ----------------------------------------------------------------------------- several bodies
class BodyParts(NamedTuple):
    """One body discretised for a :class:`Model` (``BaseBody.discretize``), in the body's own vertex
    numbering: ``rest_positions`` (n, 3) m, ``quadrature`` (``warpfem.elements.QuadratureData``: the
    elastic energy's points, connectivity in the body's own indices), ``lumped_mass`` (n,) kg,
    ``mass`` (n, n) scipy sparse (per vertex; the same for each axis), ``gravity_mass`` (n,) (M 1:
    gravity is gravity_mass x g per vertex) and ``volumetric_parameters`` (None, or the two (mu, lam)
    pairs of selective reduced integration)."""

    rest_positions: np.ndarray
    quadrature: object
    lumped_mass: np.ndarray
    mass: object
    gravity_mass: np.ndarray
    volumetric_parameters: object = None


class BaseBody:
    """What a :class:`Model` needs of a body: the base class of :class:`Body` (a deformable body
    of finite elements) and of any other kind of body a model may hold.

    A subclass sets ``name`` (None: ``body<i>``, given by ``Model.from_bodies``), ``mesh`` (what
    the outputs and contact see of it: ``vertices`` (n, 3) and ``boundary_faces()``, plus
    ``elements`` and ``element_type`` for the per-element outputs), ``material`` (with
    ``density``; the model's contact defaults read ``youngs_modulus``), ``initial_velocity`` (3,)
    and ``volumetric_integration``, and implements :meth:`discretize`. ``Model`` concatenates the
    bodies' vertices in body order (``body_offsets``) and their quadratures and mass matrices
    block by block; nothing in it depends on how many bodies there are.
    """

    name = None
    mesh = None
    material = None
    initial_velocity = np.zeros(3)
    volumetric_integration = "full"

    def discretize(self, mass_matrix: str) -> BodyParts:
        """The body's :class:`BodyParts` with the model's mass matrix kind ``mass_matrix`` ("lumped"
        or "consistent"; a body may keep its own). ValueError / TypeError for bad input (the model
        names the body)."""
        raise NotImplementedError


class Body(BaseBody):
    def __init__(self, mesh, material, *, name=None, offset=(0.0, 0.0, 0.0), initial_velocity=(0.0, 0.0, 0.0),
                 volumetric_integration: str = "full", mass_matrix: str | None = None):
        off = np.asarray(offset, dtype=np.float64)
        v0 = np.asarray(initial_velocity, dtype=np.float64)
        for what, v, raw in (("offset", off, offset), ("initial_velocity", v0, initial_velocity)):
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise ValueError(f"body {name or ''}: {what} must be 3 finite numbers, got {raw!r}".replace("body : ", "body: "))
        if name is not None and (not isinstance(name, str) or not name):
            raise ValueError(f"body name must be a non-empty string, got {name!r}")
        if np.any(off != 0.0):
            from warpfem.mesh import VolumeMesh

            mesh = VolumeMesh(np.asarray(mesh.vertices, dtype=np.float64) + off, np.asarray(mesh.elements),
                              mesh.element_type, reorient=False, remove_unreferenced=False,
                              name=getattr(mesh, "name", None))
        self.mesh, self.material, self.name = mesh, material, name
        self.offset, self.initial_velocity = off, v0
        self.volumetric_integration = volumetric_integration
        self.mass_matrix = mass_matrix

    def discretize(self, mass_matrix: str) -> BodyParts:
        """Quadrature (``warpfem.elements.precompute_quadrature``) and mass matrices
        (``warpfem.mesh.mass``) of the mesh, with the body's ``mass_matrix`` or else the model's."""
        mesh, material = self.mesh, self.material
        mass_matrix = self.mass_matrix or mass_matrix
        if mass_matrix not in MASS_MATRIX_KINDS:
            raise ValueError(f"mass_matrix must be 'lumped' or 'consistent', got {mass_matrix!r}")
        for attr in ("kind", "kernel_mu", "kernel_lam", "density"):
            if not hasattr(material, attr):
                raise TypeError(f"material must be a warpfem material (missing {attr!r}), got {type(material).__name__}")
        vi = self.volumetric_integration
        volumetric_parameters = None
        if vi == "reduced":
            split = getattr(material, "volumetric_split", None)
            if split is None:
                raise ValueError("volumetric_integration='reduced' needs a material whose energy splits into a "
                                 f"volumetric and a remaining part (a volumetric_split() method); {type(material).__name__} "
                                 "has none")
            (mu_f, lam_f), (mu_v, lam_v) = split()
            if lam_v < 0.0:
                raise ValueError("volumetric_integration='reduced' is for nearly incompressible materials: it needs "
                                 f"poisson_ratio >= 0 (a non-negative volumetric part), got poisson_ratio="
                                 f"{getattr(material, 'poisson_ratio', '?')!r} for {type(material).__name__}")
            volumetric_parameters = ((float(mu_f), float(lam_f)), (float(mu_v), float(lam_v)))
        rest = np.asarray(mesh.vertices, dtype=np.float64)
        quadrature = precompute_quadrature(rest, mesh.elements, mesh.element_type, volumetric_integration=vi)
        lumped, mass = mass_matrices(mesh, material.density, mass_matrix)
        # M (1 x g): the lumped mass except for Tet10/Hex27 with the consistent mass (rho g int N_a dV there)
        gravity_mass = np.asarray(mass.sum(axis=1), dtype=np.float64).ravel()
        return BodyParts(rest, quadrature, lumped, mass, gravity_mass, volumetric_parameters)

    def __repr__(self):
        return (f"Body({self.name!r}, {getattr(self.mesh, 'element_type', '?')}, {self.mesh.num_vertices} vertices, "
                f"{type(self.material).__name__})")


def _construct(model, bodies, *, gravity, mass_matrix, name_errors=False):
    """The construction of every model (``model``: the Model being built, by ``Model.__init__`` and
    ``Model.from_bodies``): the bodies (:class:`BaseBody`, named) discretised one by
    one (``BaseBody.discretize``), their vertices concatenated in body order. ``name_errors``: a
    body's ValueError / TypeError is raised again prefixed by its name (its ``body`` attribute:
    the body's index, ``__cause__`` the body's own error).

    A model of one body (either construction) shows that body directly: ``mesh`` is its mesh,
    ``quadrature`` its quadrature, ``volumetric_integration`` / ``volumetric_parameters`` its
    own; with several they are a :class:`BodiesMesh`, None, the list per body and None."""
    import dataclasses

    if mass_matrix not in MASS_MATRIX_KINDS:
        raise ValueError(f"mass_matrix must be 'lumped' or 'consistent', got {mass_matrix!r}")
    g = np.asarray(gravity, dtype=np.float64)
    if g.shape != (3,) or not np.all(np.isfinite(g)):
        raise ValueError(f"gravity must be 3 finite numbers, got {gravity!r}")
    from warpfem.rigid.body import RigidBody

    soft = [b for b in bodies if not isinstance(b, RigidBody)]  # first (Model.from_bodies checks the order)
    rigid = bodies[len(soft):]
    parts = []
    for i, b in enumerate(soft):
        try:
            parts.append(b.discretize(mass_matrix))
        except (ValueError, TypeError) as e:
            if not name_errors:
                raise
            err = type(e)(f"body {b.name!r}: {e}")
            err.body = i
            raise err from e
    # vertex offsets: each body's vertices (a rigid body's too: its mesh's, moved by p + A X)
    sizes = [len(p.rest_positions) for p in parts] + [len(b.local_positions) for b in rigid]
    offsets = np.concatenate([[0], np.cumsum(sizes)]).astype(np.int64)
    model.bodies, model.body_names, model.body_offsets = list(bodies), [b.name for b in bodies], offsets
    one = len(bodies) == 1  # the one body's own mesh, quadrature and volumetric integration (above)
    model.mesh = bodies_mesh([b.mesh for b in bodies], offsets, model.body_names)
    # the material contact defaults scale with (the stiffest soft body's); per soft body: materials[i]
    mats = [b.material for b in soft]
    model.material = max(mats, key=lambda m: float(getattr(m, "youngs_modulus", 0.0) or 0.0)) if mats else None
    model.materials = mats
    model.gravity = g
    model.mass_matrix_kind = mass_matrix
    model.volumetric_integration = soft[0].volumetric_integration if one and soft else \
        [b.volumetric_integration for b in soft]
    # ((mu, lam) full-rule part, (mu, lam) 1-point part) with "reduced"; per body: body_volumetric_parameters
    model.body_volumetric_parameters = [p.volumetric_parameters for p in parts]
    model.volumetric_parameters = parts[0].volumetric_parameters if one and parts else None

    def shifted(qd, o):  # a body's quadrature with its connectivity in global vertex indices
        if qd is None or o == 0:
            return qd
        return dataclasses.replace(qd, elements=(np.asarray(qd.elements, dtype=np.int64) + o).astype(qd.elements.dtype),
                                   volumetric=shifted(qd.volumetric, o))

    model.quadratures = [shifted(p.quadrature, int(o)) for p, o in zip(parts, offsets)]
    model.quadrature = model.quadratures[0] if len(parts) == 1 else None
    soft_mass = [p.mass for p in parts]
    model.rest_positions = np.concatenate([p.rest_positions for p in parts] or [np.zeros((0, 3))])
    model.lumped_mass = np.concatenate([p.lumped_mass for p in parts] or [np.zeros(0)])
    # gravity is M (1 x g) with each body's mass matrix, so free fall is exact with either
    model.gravity_mass = np.concatenate([p.gravity_mass for p in parts] or [np.zeros(0)])
    if rigid:  # the unknown: the soft vertices, then each rigid body's four nodes (warpfem.rigid.model)
        from warpfem.rigid.model import attach_rigid

        soft_mass, model.vertex_rest_positions = attach_rigid(model, rigid, offsets, soft_mass)
    else:
        model.vertex_rest_positions = model.rest_positions
    model.num_vertices = len(model.rest_positions)
    model.mass = scipy.sparse.block_diag(soft_mass, format="csr")
    model.fixed = np.zeros((model.num_vertices, 3), dtype=bool)
    model.forces = np.zeros((model.num_vertices, 3))


def bodies_mesh(meshes, offsets, names):
    """The mesh of a model (or scene) of the bodies' ``meshes``: the one body's own mesh, or a
    :class:`BodiesMesh` of several (``offsets``: the first vertex of each, then the total)."""
    return meshes[0] if len(meshes) == 1 else BodiesMesh(meshes, offsets, names)


class BodiesMesh:
    """The bodies of a multi-body :class:`Model` seen as one point set (``Model.mesh``): vertices
    concatenated in body order, boundary triangles with global vertex indices (each body's own
    ``boundary_faces()``, shifted by its first vertex), and which body each vertex and triangle
    belongs to. No element connectivity: the bodies' element types may differ (``meshes``)."""

    def __init__(self, meshes, offsets, names):
        self.meshes, self.body_offsets, self.names = list(meshes), np.asarray(offsets, dtype=np.int64), list(names)
        self.vertices = np.concatenate([np.asarray(m.vertices, dtype=np.float64) for m in self.meshes])
        self.name = "+".join(self.names)
        self._faces = None

    @property
    def num_vertices(self) -> int:
        return int(self.body_offsets[-1])

    @property
    def num_elements(self) -> int:
        return int(sum(m.num_elements for m in self.meshes))

    @property
    def element_types(self) -> list:
        return [m.element_type for m in self.meshes]

    def bounds(self):
        return self.vertices.min(axis=0), self.vertices.max(axis=0)

    def total_volume(self) -> float:
        return float(sum(m.total_volume() for m in self.meshes))

    def boundary_faces(self) -> np.ndarray:
        """(f, 3) outward boundary triangles of every body, global vertex indices, in body order."""
        if self._faces is None:
            self._faces = np.concatenate([np.asarray(m.boundary_faces(), dtype=np.int64) + o
                                          for m, o in zip(self.meshes, self.body_offsets[:-1])])
        return self._faces

    def face_bodies(self) -> np.ndarray:
        """(f,) body index of each triangle of :meth:`boundary_faces`."""
        return self.vertex_bodies()[self.boundary_faces()[:, 0]]

    def vertex_bodies(self) -> np.ndarray:
        """(n,) body index of each vertex."""
        return np.repeat(np.arange(len(self.meshes)), np.diff(self.body_offsets))

    def boundary_edges(self) -> np.ndarray:
        """(e, 2) unique edges (i < j) of the boundary triangles, global indices."""
        f = self.boundary_faces()
        e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
        return np.unique(e, axis=0)
