"""The physical model: a mesh, a material, boundary conditions and loads (device independent)."""

from __future__ import annotations

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


class Model:
    """A deformable body ready to simulate: mesh + material + fixed DOFs + loads.

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

    def __init__(self, mesh, material, *, gravity=(0.0, 0.0, 0.0), mass_matrix: str = "lumped",
                 volumetric_integration: str = "full"):
        if mass_matrix not in MASS_MATRIX_KINDS:
            raise ValueError(f"mass_matrix must be 'lumped' or 'consistent', got {mass_matrix!r}")
        for attr in ("kind", "kernel_mu", "kernel_lam", "density"):
            if not hasattr(material, attr):
                raise TypeError(f"material must be a warpfem material (missing {attr!r}), got {type(material).__name__}")
        g = np.asarray(gravity, dtype=np.float64)
        if g.shape != (3,) or not np.all(np.isfinite(g)):
            raise ValueError(f"gravity must be 3 finite numbers, got {gravity!r}")
        self.mesh = mesh
        self.material = material
        self.gravity = g
        self.mass_matrix_kind = mass_matrix
        self.rest_positions = np.asarray(mesh.vertices, dtype=np.float64)
        self.num_vertices = len(self.rest_positions)
        self.volumetric_parameters = None  # ((mu, lam) full-rule part, (mu, lam) 1-point part) with "reduced"
        if volumetric_integration == "reduced":
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
            self.volumetric_parameters = ((float(mu_f), float(lam_f)), (float(mu_v), float(lam_v)))
        self.volumetric_integration = volumetric_integration
        self.quadrature = precompute_quadrature(self.rest_positions, mesh.elements, mesh.element_type,
                                                volumetric_integration=volumetric_integration)
        self.lumped_mass, self.mass = mass_matrices(mesh, material.density, mass_matrix)
        # gravity is M (1 x g) with the chosen mass matrix, so free fall is exact with either; this is
        # lumped_mass except for Tet10/Hex27 with the consistent mass (rho g int N_a dV there).
        self.gravity_mass = np.asarray(self.mass.sum(axis=1), dtype=np.float64).ravel()
        self.fixed = np.zeros((self.num_vertices, 3), dtype=bool)
        self.forces = np.zeros((self.num_vertices, 3))

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
        A static solve of such a model is singular (no mass term holds the motion).
        """
        X = self.rest_positions
        c = X.mean(axis=0)
        L = float(np.linalg.norm(np.ptp(X, axis=0))) or 1.0
        n = len(X)
        B = rigid_body_modes(X, normalize=False)  # columns: translations, e_a x (X - c)
        norms = np.linalg.norm(B, axis=0)
        norms[norms == 0.0] = 1.0
        rows = (B / norms).reshape(n, 3, 6)[self.fixed]  # unit columns: a rank test free of units
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

    def add_force(self, indices, force) -> None:
        """Add a constant force (N) to each given vertex."""
        f = np.asarray(force, dtype=np.float64)
        if f.shape != (3,) or not np.all(np.isfinite(f)):
            raise ValueError(f"force must be 3 finite numbers, got {force!r}")
        np.add.at(self.forces, self.indices(indices), f)
