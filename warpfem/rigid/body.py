"""A rigid body of a multi-body model: its mesh, density and mass properties (docs/rigid.md)."""

from __future__ import annotations

import numpy as np

__all__ = ["RigidBody", "mass_properties", "SurfaceBodyMesh"]


def _closed_surface_error(faces) -> str:
    """'' when the triangles ``faces`` form a closed surface (every edge in exactly two
    triangles, once in each direction), else what is wrong."""
    f = np.asarray(faces, dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3 or not len(f):
        return "it has no boundary triangles"
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    n = int(f.max()) + 1
    directed = e[:, 0] * n + e[:, 1]
    reverse = e[:, 1] * n + e[:, 0]
    d_keys, d_count = np.unique(directed, return_counts=True)
    if np.any(d_count > 1):
        k = int(d_keys[np.argmax(d_count > 1)])
        return (f"its surface is not a closed oriented 2-manifold (edge ({k // n}, {k % n}) is in "
                f"{int(d_count.max())} triangles with the same orientation)")
    missing = ~np.isin(reverse, d_keys)
    if np.any(missing):
        i = int(np.argmax(missing))
        return f"its surface is open (edge ({int(e[i, 0])}, {int(e[i, 1])}) has no neighbouring triangle)"
    return ""


def mass_properties(vertices, faces, density):
    """(mass, centre of mass, second moment S, volume) of the solid bounded by the closed,
    outward-oriented triangles ``faces``: S = int rho (x - c)(x - c)^T dV (3x3, kg m^2), by the
    divergence theorem over the tetrahedra of each triangle and a reference point (exact for the
    polyhedron)."""
    X = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    o = X.mean(axis=0)
    a, b, c = X[f[:, 0]] - o, X[f[:, 1]] - o, X[f[:, 2]] - o
    vol6 = np.einsum("ij,ij->i", a, np.cross(b, c))  # 6 x signed volume of (o, a, b, c)
    V = float(vol6.sum()) / 6.0
    # first moment: sum V_t (a + b + c) / 4; second: V_t / 20 (sum v v^T + (sum v)(sum v)^T)
    s = a + b + c
    first = (vol6[:, None] * s).sum(axis=0) / 24.0
    outer = (np.einsum("t,ti,tj->ij", vol6, a, a) + np.einsum("t,ti,tj->ij", vol6, b, b)
             + np.einsum("t,ti,tj->ij", vol6, c, c) + np.einsum("t,ti,tj->ij", vol6, s, s)) / 120.0
    if not V > 0.0:
        return 0.0, o, np.zeros((3, 3)), V
    rel = first / V
    S0 = outer - V * np.outer(rel, rel)  # about the centroid (volume weighted)
    return float(density * V), o + rel, density * 0.5 * (S0 + S0.T), V


class SurfaceBodyMesh:
    """A rigid body given by its closed surface only (vertices and outward triangles): what
    ``Model.from_bodies`` needs of a body's mesh (no elements)."""

    element_type = "tri3"

    def __init__(self, vertices, faces, name=None):
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = np.asarray(faces, dtype=np.int64)
        self.elements = np.zeros((0, 3), dtype=np.int64)
        self.name = name

    @property
    def num_vertices(self) -> int:
        return len(self.vertices)

    @property
    def num_elements(self) -> int:
        return 0

    def boundary_faces(self):
        return self.faces

    def total_volume(self) -> float:
        return mass_properties(self.vertices, self.faces, 1.0)[3]

    def bounds(self):
        return self.vertices.min(axis=0), self.vertices.max(axis=0)


class RigidBody:
    """A rigid body of a multi-body model (``Model.from_bodies``), simulated as an affine body.

    Its vertices move as x = p + A X (X: the rest position relative to the centre of mass, p the
    centre of mass, A a 3x3 matrix kept a rotation by a stiff orthogonality energy); the 12
    unknowns p, a_1, a_2, a_3 (the columns of A) are four nodes of the simulator's unknown. It is
    pushed by and pushes the other bodies and colliders through the contact forms (docs/rigid.md).

    Args:
        mesh: its shape: a volume mesh (``warpfem.mesh.VolumeMesh``, any element type: its
            boundary surface is used) or a closed surface as ``(vertices, triangles)`` (outward
            triangles), positions in m.
        density: kg/m^3 (> 0).
        name: a name (default ``body<i>``, as for :class:`warpfem.Body`).
        offset: (3,) translation (m) applied to the mesh's vertices.
        initial_velocity: (3,) velocity (m/s) of the centre of mass at t = 0.
        initial_angular_velocity: (3,) angular velocity (rad/s) about the centre of mass at
            t = 0 (the initial A-dot is [w]x A, A = I).
        stiffness: kappa (Pa) of the orthogonality energy kappa V ||A^T A - I||_F^2 (default 1e8:
            a rotation's strain stays below 1e-8 for the motions measured in docs/rigid.md).
    """

    def __init__(self, mesh, *, density, name=None, offset=(0.0, 0.0, 0.0), initial_velocity=(0.0, 0.0, 0.0),
                 initial_angular_velocity=(0.0, 0.0, 0.0), stiffness=1e8):
        if name is not None and (not isinstance(name, str) or not name):
            raise ValueError(f"rigid body name must be a non-empty string, got {name!r}")
        who = f"rigid body {name!r}" if name else "rigid body"
        try:
            rho = float(density)
        except (TypeError, ValueError):
            raise ValueError(f"{who}: density must be a number > 0 (kg/m^3), got {density!r}") from None
        if not (np.isfinite(rho) and rho > 0.0):
            raise ValueError(f"{who}: density must be > 0 (kg/m^3), got {density!r}")
        kappa = float(stiffness)
        if not (np.isfinite(kappa) and kappa > 0.0):
            raise ValueError(f"{who}: stiffness must be > 0 (Pa), got {stiffness!r}")
        vecs = {}
        for what, raw in (("offset", offset), ("initial_velocity", initial_velocity),
                          ("initial_angular_velocity", initial_angular_velocity)):
            v = np.asarray(raw, dtype=np.float64)
            if v.shape != (3,) or not np.all(np.isfinite(v)):
                raise ValueError(f"{who}: {what} must be 3 finite numbers, got {raw!r}")
            vecs[what] = v
        if isinstance(mesh, (tuple, list)) and len(mesh) == 2:
            mesh = SurfaceBodyMesh(*mesh, name=name)
        if not hasattr(mesh, "vertices") or not hasattr(mesh, "boundary_faces"):
            raise TypeError(f"{who}: mesh must be a volume mesh or (vertices, triangles), got {type(mesh).__name__}")
        X = np.asarray(mesh.vertices, dtype=np.float64) + vecs["offset"]
        faces = np.asarray(mesh.boundary_faces(), dtype=np.int64)
        problem = _closed_surface_error(faces)
        if problem:
            raise ValueError(f"{who}: the mesh must bound a solid, but {problem}")
        mass, com, S, V = mass_properties(X, faces, rho)
        if not V > 0.0:
            raise ValueError(f"{who}: its surface encloses no positive volume ({V:.3g} m^3): are its triangles "
                             "oriented inwards?")
        if isinstance(mesh, SurfaceBodyMesh):
            mesh = SurfaceBodyMesh(X, faces, name=name)
        else:
            from warpfem.mesh import VolumeMesh

            if np.any(vecs["offset"] != 0.0):
                mesh = VolumeMesh(X, np.asarray(mesh.elements), mesh.element_type, reorient=False,
                                  remove_unreferenced=False, name=getattr(mesh, "name", None))
        self.mesh, self.name, self.density, self.stiffness = mesh, name, rho, kappa
        self.offset = vecs["offset"]
        self.initial_velocity = vecs["initial_velocity"]
        self.initial_angular_velocity = vecs["initial_angular_velocity"]
        #: kg, m (3,), kg m^2 (3x3, about the centre of mass), m^3
        self.mass, self.center_of_mass, self.second_moment, self.volume = mass, com, S, V
        #: (n, 3) rest positions relative to the centre of mass (the X of x = p + A X)
        self.local_positions = X - com
        self.material = None

    @property
    def inertia_tensor(self):
        """The inertia tensor about the centre of mass (kg m^2): tr(S) I - S."""
        S = self.second_moment
        return np.trace(S) * np.eye(3) - S

    def dof_mass_matrix(self):
        """The 4x4 scalar matrix M of the kinetic energy 1/2 qdot^T (M (x) I3) qdot over the nodes
        (p, a_1, a_2, a_3): M = int rho (1, X)(1, X)^T dV = diag(m, S) (X centred)."""
        M = np.zeros((4, 4))
        M[0, 0] = self.mass
        M[1:, 1:] = self.second_moment
        return M

    def initial_node_velocities(self):
        """(4, 3): p-dot = initial_velocity, a_k-dot = w x e_k (A-dot = [w]x A at A = I)."""
        w = self.initial_angular_velocity
        return np.stack([self.initial_velocity] + [np.cross(w, e) for e in np.eye(3)])

    def __repr__(self):
        return f"RigidBody({self.name!r}, {len(self.local_positions)} vertices, {self.mass:.4g} kg)"
