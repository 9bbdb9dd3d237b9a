"""Scene loads as nodal data (numpy, no kernels): handle targets, tractions on boundary faces
(Tet4 triangles or the element type's faces), the default render surface."""

from __future__ import annotations

import math

import numpy as np

__all__ = ["handle_targets", "traction_forces", "element_traction_forces", "boundary_surface"]


def _rotation(axis, angle_rad):
    a = np.asarray(axis, dtype=np.float64)
    a = a / np.linalg.norm(a)
    K = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle_rad) * K + (1 - math.cos(angle_rad)) * (K @ K)


def handle_targets(rest, handle: dict, fraction: float, center=None) -> np.ndarray:
    """Positions (m) of handle vertices (rest (h, 3)) at ramp ``fraction`` in [0, 1].

    x = c + R(fraction * angle) (X - c) + fraction * translation, c the rotation centre
    (``handle["rotation_center"]`` or the centroid of ``rest``).
    """
    rest = np.asarray(rest, dtype=np.float64)
    s = float(min(max(fraction, 0.0), 1.0))
    x = rest.copy()
    if handle.get("rotation_axis") is not None and handle.get("rotation_angle", 0.0) != 0.0:
        c = np.asarray(handle.get("rotation_center") if handle.get("rotation_center") is not None
                       else (rest.mean(axis=0) if center is None else center), dtype=np.float64)
        R = _rotation(handle["rotation_axis"], math.radians(handle["rotation_angle"]) * s)
        x = c + (rest - c) @ R.T
    return x + s * np.asarray(handle.get("translation", (0.0, 0.0, 0.0)), dtype=np.float64)


def traction_forces(vertices, faces, box_min, box_max, force_per_area):
    """Consistent nodal forces (N) of a uniform traction (Pa) on the faces inside a box.

    A face is loaded when its three vertices lie in the box. For a linear triangle of reference
    area A the consistent load of a uniform traction t is t A / 3 on each of its vertices.
    Returns ``(forces (n, 3), loaded face indices, total loaded area (m^2))``.
    """
    from warpfem.mesh import select_vertices_in_box

    X = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    inside = np.zeros(len(X), dtype=bool)
    inside[select_vertices_in_box(X, box_min, box_max)] = True
    sel = np.flatnonzero(inside[faces].all(axis=1))
    f = faces[sel]
    area = 0.5 * np.linalg.norm(np.cross(X[f[:, 1]] - X[f[:, 0]], X[f[:, 2]] - X[f[:, 0]]), axis=1)
    t = np.asarray(force_per_area, dtype=np.float64)
    forces = np.zeros_like(X)
    per_vertex = (area / 3.0)[:, None] * t[None, :]
    for a in range(3):
        np.add.at(forces, f[:, a], per_vertex)
    return forces, sel, float(area.sum())


# Strang & Fix 6-point rule on the reference triangle (s, t >= 0, s + t <= 1), degree 4; weights sum to 1/2.
def _element_faces(element_type):
    """Per local face of an element: the element type's ``faces()`` (warpfem.mesh.element_types)."""
    from warpfem.mesh.element_types import get_element

    return get_element(element_type).faces()


def element_traction_forces(mesh, box_min, box_max, force_per_area):
    """Consistent nodal forces (N) of a uniform traction t (Pa) on the boundary faces of an element
    mesh (any element type) whose nodes all lie in the box: f_a = t int_face N_a dA, by Gauss
    quadrature on each face (3x3 points on hex faces, 6 points on tet faces), dA from the
    isoparametric map (exact on flat faces). For Tet10 faces the corner nodes get 0 and the
    mid-edge nodes A/3 each; for flat Hex8 faces every corner gets A/4.
    Returns ``(forces (n, 3), loaded boundary faces (element * faces_per_element + local face), area (m^2))``.
    """
    from warpfem.mesh.element_types import shape_functions, shape_gradients
    from warpfem.mesh import select_vertices_in_box

    etype = mesh.element_type
    X = np.asarray(mesh.vertices, dtype=np.float64)
    E = np.asarray(mesh.elements, dtype=np.int64)
    faces = _element_faces(etype)
    nf = len(faces)
    keys = np.stack([np.sort(E[:, c], axis=1) for _, c, *_ in faces], axis=1)  # (m, nf, corners)
    keys = keys.reshape(len(E) * nf, -1)
    _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    boundary = counts[inv.ravel()] == 1
    inside = np.zeros(len(X), dtype=bool)
    inside[select_vertices_in_box(X, box_min, box_max)] = True
    t = np.asarray(force_per_area, dtype=np.float64)
    forces = np.zeros_like(X)
    loaded, area = [], 0.0
    for f, (on, _, origin, T, pts, wts) in enumerate(faces):
        el = np.flatnonzero(boundary.reshape(len(E), nf)[:, f])
        el = el[inside[E[el][:, on]].all(axis=1)]
        if el.size == 0:
            continue
        xi = origin[None, :] + pts @ T  # (g, 3)
        N = shape_functions(etype, xi)  # (g, k)
        dN = shape_gradients(etype, xi)  # (g, k, 3)
        J = np.einsum("eai,gaj->egij", X[E[el]], dN)  # (e, g, 3, 3) dX/dxi
        Ts, Tt = J @ T[0], J @ T[1]  # (e, g, 3)
        dA = np.linalg.norm(np.cross(Ts, Tt), axis=2) * wts[None, :]  # (e, g)
        nodal = dA @ N  # (e, k): int N_a dA
        np.add.at(forces, E[el].ravel(), (nodal.ravel()[:, None] * t[None, :]))
        loaded.append(el * nf + f)
        area += float(dA.sum())
    sel = np.sort(np.concatenate(loaded)) if loaded else np.zeros(0, np.int64)
    return forces, sel, area


def boundary_surface(mesh):
    """Default render surface: ``(vertex ids (s,), triangles (f, 3) into them)`` of the mesh boundary
    (tet faces; Tet10/Hex faces triangulated through their nodes, see ``VolumeMesh.boundary_faces``)."""
    if mesh.element.is_linear_tet:
        from warpfem.skinning import mesh_boundary_surface

        return mesh_boundary_surface(mesh.vertices, mesh.tets)
    ids, tri = np.unique(np.asarray(mesh.boundary_faces(), dtype=np.int64).reshape(-1), return_inverse=True)
    return ids.astype(np.int64), tri.reshape(-1, 3).astype(np.int64)
