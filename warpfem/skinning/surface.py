"""Render surfaces: the boundary of a tet mesh, or a triangle surface read from a file."""

from __future__ import annotations

import os

import numpy as np

__all__ = ["boundary_faces", "mesh_boundary_surface", "load_surface", "SurfaceError"]


class SurfaceError(ValueError):
    """A surface file that cannot be used as a render surface."""


# Faces of a positively oriented tet (a, b, c, d) (det[b-a, c-a, d-a] > 0), outward normals.
_OUTWARD_FACES = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])


def _arrays(vertices, tets):
    if tets is None:
        if not (hasattr(vertices, "vertices") and hasattr(vertices, "tets")):
            raise TypeError("pass (vertices, tets) arrays or a mesh object with .vertices and .tets")
        vertices, tets = vertices.vertices, vertices.tets
    return vertices, tets


def boundary_faces(vertices, tets=None) -> np.ndarray:
    """Triangles (f, 3) used by exactly one tet, oriented outwards, in mesh vertex indices.

    Works for tets of either orientation (each tet's own orientation is used).
    ``boundary_faces(mesh)`` takes a mesh object with ``.vertices`` and ``.tets``.
    """
    vertices, tets = _arrays(vertices, tets)
    vertices = np.asarray(vertices, dtype=np.float64)
    tets = np.asarray(tets, dtype=np.int64)
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise ValueError(f"tets must have shape (m, 4), got {tets.shape}")
    if tets.size and (tets.min() < 0 or tets.max() >= vertices.shape[0]):
        raise ValueError("tets reference vertices out of range")
    X = vertices[tets]
    det = np.einsum(
        "ij,ij->i", np.cross(X[:, 1] - X[:, 0], X[:, 2] - X[:, 0]), X[:, 3] - X[:, 0]
    )
    t = tets.copy()
    neg = det < 0
    t[neg, 0], t[neg, 1] = tets[neg, 1], tets[neg, 0]  # swap two corners: positive orientation
    faces = t[:, _OUTWARD_FACES].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inv.reshape(-1)] == 1]


def mesh_boundary_surface(vertices, tets=None):
    """Default render surface of a tet mesh: its boundary triangles.

    Returns ``(surface_vertex_ids (s,), triangles (f, 3))`` where the triangles index into
    ``surface_vertex_ids`` (so ``vertices[surface_vertex_ids]`` are the surface points; they are
    a subset of the simulation vertices).
    """
    vertices, tets = _arrays(vertices, tets)
    faces = boundary_faces(vertices, tets)
    ids, tri = np.unique(faces.reshape(-1), return_inverse=True)
    return ids.astype(np.int64), tri.reshape(-1, 3).astype(np.int64)


_SURFACE_EXTENSIONS = (".obj", ".off", ".ply", ".stl")


def load_surface(path):
    """Read a triangle surface (.obj, .off, .ply, .stl) with meshio.

    Returns ``(vertices (k, 3) float64, triangles (f, 3) int64)``. Quads are split into two
    triangles; other cell types are ignored. Raises FileNotFoundError for a missing file and
    SurfaceError (a ValueError) for an unsupported extension, an unreadable file or a file with
    no triangles.
    """
    import meshio

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"surface file not found: {path}")
    ext = os.path.splitext(path)[1].lower()
    if ext not in _SURFACE_EXTENSIONS:
        raise SurfaceError(f"{path}: unsupported surface format {ext!r} (expected one of {', '.join(_SURFACE_EXTENSIONS)})")
    try:
        m = meshio.read(path)
    except Exception as e:  # meshio raises many types
        raise SurfaceError(f"{path}: cannot read surface: {e}") from e
    tris = []
    for block in m.cells:
        data = np.asarray(block.data, dtype=np.int64)
        if block.type == "triangle":
            tris.append(data.reshape(-1, 3))
        elif block.type == "quad":
            data = data.reshape(-1, 4)
            tris.append(data[:, [0, 1, 2]])
            tris.append(data[:, [0, 2, 3]])
    tris = np.concatenate(tris, axis=0) if tris else np.zeros((0, 3), np.int64)
    if tris.shape[0] == 0:
        kinds = ", ".join(sorted({b.type for b in m.cells if len(b.data)})) or "none"
        raise SurfaceError(f"{path}: no triangles in surface file (cell types: {kinds})")
    vertices = np.asarray(m.points, dtype=np.float64)
    if vertices.ndim != 2 or vertices.shape[1] not in (2, 3):
        raise SurfaceError(f"{path}: points have shape {vertices.shape}, expected (k, 3)")
    if vertices.shape[1] == 2:
        vertices = np.concatenate([vertices, np.zeros((vertices.shape[0], 1))], axis=1)
    if tris.min() < 0 or tris.max() >= vertices.shape[0]:
        raise SurfaceError(f"{path}: triangle references a vertex out of range [0, {vertices.shape[0]})")
    if not np.all(np.isfinite(vertices)):
        raise SurfaceError(f"{path}: non-finite vertex coordinates")
    return vertices, tris
