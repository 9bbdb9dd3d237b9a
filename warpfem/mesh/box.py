"""Mesh generators: structured boxes (Tet4: each hex cell split into 6 tets around the cell diagonal
0-6; Hex8 / Hex27 grids) and the Tet10 mesh of a Tet4 mesh."""

from __future__ import annotations

import numbers

import numpy as np

from .element_types import get_element
from .element_types.base import HexElement
from .element_types.tet10 import TET10_EDGES
from .volume_mesh import MeshError, VolumeMesh

__all__ = ["box_tet_mesh", "box_hex_mesh", "tet10_from_tet4", "icosphere_surface", "HEX_CORNERS", "HEX_TO_TETS"]

#: Unit-cell corner offsets (i, j, k) in the reference order 0..7.
HEX_CORNERS = np.array(
    [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]],
    dtype=np.int64,
)
#: The 6 tets of a cell around the diagonal 0-6 (all positively oriented with HEX_CORNERS): the hex
#: element types' corner sub-tets.
HEX_TO_TETS = HexElement.corner_tets


def box_tet_mesh(*, size=(1.0, 1.0, 1.0), cells=(1, 1, 1), origin=(0.0, 0.0, 0.0), name=None):
    """Tet4 mesh of the box ``origin + [0, size]`` with ``cells = (nx, ny, nz)`` hex cells.

    Vertex (i, j, k) of the grid has index ``i + (nx+1) * (j + (ny+1) * k)`` and position
    ``origin + (i, j, k) * size / cells``. Cell (ci, cj, ck) gives tets
    ``6 * (ci + nx * (cj + ny * ck)) + s`` for the six split tets s of ``HEX_TO_TETS``.
    """
    cells = tuple(cells)
    if len(cells) != 3 or not all(
        isinstance(c, numbers.Integral) and not isinstance(c, bool) for c in cells
    ):
        raise MeshError(f"cells must be three integers, got {cells!r}")
    if min(cells) < 1:
        raise MeshError(f"cells must be >= 1, got {cells!r}")
    size = np.asarray(size, dtype=np.float64)
    origin = np.asarray(origin, dtype=np.float64)
    if size.shape != (3,) or not np.all(np.isfinite(size)) or not np.all(size > 0):
        raise MeshError(f"size must be three finite values > 0, got {size.tolist()}")
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise MeshError(f"origin must be three finite values, got {origin.tolist()}")

    nx, ny, nz = (int(c) for c in cells)
    k, j, i = np.meshgrid(np.arange(nz + 1), np.arange(ny + 1), np.arange(nx + 1), indexing="ij")
    ijk = np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1)  # index = i + (nx+1)(j + (ny+1)k)
    h = size / np.array([nx, ny, nz], dtype=np.float64)
    vertices = origin + ijk * h
    # Exact far faces (avoid i*h rounding away from origin + size).
    for d, n in enumerate((nx, ny, nz)):
        vertices[ijk[:, d] == n, d] = origin[d] + size[d]

    ck, cj, ci = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    base = np.stack([ci.ravel(), cj.ravel(), ck.ravel()], axis=1)  # (ncells, 3)
    corner = base[:, None, :] + HEX_CORNERS[None, :, :]  # (ncells, 8, 3)
    cid = corner[..., 0] + (nx + 1) * (corner[..., 1] + (ny + 1) * corner[..., 2])
    tets = cid[:, HEX_TO_TETS].reshape(-1, 4)
    return VolumeMesh(vertices, tets, reorient=True, name=name)


def box_hex_mesh(*, size=(1.0, 1.0, 1.0), cells=(1, 1, 1), origin=(0.0, 0.0, 0.0), order: int = 1, name=None):
    """Hex mesh of the box ``origin + [0, size]`` (m) with ``cells = (nx, ny, nz)`` cells.

    ``order=1``: Hex8; ``order=2``: Hex27 (nodes on the grid refined twice). Grid node (i, j, k)
    has index ``i + (o nx + 1) (j + (o ny + 1) k)`` with o = order.
    """
    if order not in (1, 2):
        raise MeshError(f"order must be 1 (hex8) or 2 (hex27), got {order!r}")
    cells = tuple(cells)
    if len(cells) != 3 or not all(isinstance(c, numbers.Integral) and not isinstance(c, bool) and c >= 1 for c in cells):
        raise MeshError(f"cells must be three integers >= 1, got {cells!r}")
    size = np.asarray(size, dtype=np.float64)
    origin = np.asarray(origin, dtype=np.float64)
    if size.shape != (3,) or not np.all(np.isfinite(size)) or not np.all(size > 0):
        raise MeshError(f"size must be three finite values > 0 (m), got {np.ravel(size).tolist()}")
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise MeshError(f"origin must be three finite values (m), got {np.ravel(origin).tolist()}")
    nx, ny, nz = (int(c) for c in cells)
    o = order
    gx, gy, gz = o * nx + 1, o * ny + 1, o * nz + 1
    k, j, i = np.meshgrid(np.arange(gz), np.arange(gy), np.arange(gx), indexing="ij")
    ijk = np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1)
    h = size / (o * np.array([nx, ny, nz], dtype=np.float64))
    vertices = origin + ijk * h
    for d, g in enumerate((gx, gy, gz)):
        vertices[ijk[:, d] == g - 1, d] = origin[d] + size[d]
    element = get_element("hex8" if order == 1 else "hex27")
    ref = np.rint((element.reference_nodes + 1) * o / 2).astype(np.int64)  # (k, 3) grid offsets
    ck, cj, ci = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    base = o * np.stack([ci.ravel(), cj.ravel(), ck.ravel()], axis=1)
    node = base[:, None, :] + ref[None]
    elements = node[..., 0] + gx * (node[..., 1] + gy * node[..., 2])
    return VolumeMesh(vertices, elements, element, name=name)


def tet10_from_tet4(mesh, *, name=None):
    """Tet10 mesh from a Tet4 mesh: one mid-node per unique edge (shared between neighbours), placed
    at the edge midpoint; corner indices are kept."""
    tets = np.asarray(mesh.elements, dtype=np.int64)
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise MeshError(f"tet10_from_tet4 needs a Tet4 mesh with (m, 4) elements, got {tets.shape}")
    X = np.asarray(mesh.vertices, dtype=np.float64)
    edges = tets[:, TET10_EDGES]  # (m, 6, 2)
    key = np.sort(edges.reshape(-1, 2), axis=1)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    mids = 0.5 * (X[uniq[:, 0]] + X[uniq[:, 1]])
    elements = np.concatenate([tets, len(X) + inv.reshape(-1, 6)], axis=1)
    return VolumeMesh(np.concatenate([X, mids]), elements, "tet10",
                      name=name if name is not None else getattr(mesh, "name", None))


def icosphere_surface(radius: float = 1.0, subdivisions: int = 2):
    """A closed triangle surface of a sphere about the origin: the icosahedron with each triangle
    split in four ``subdivisions`` times, vertices pushed onto the sphere (10 4^k + 2 vertices,
    20 4^k triangles, outward). Returns (vertices (n, 3) float64, triangles (m, 3) int64)."""
    t = (1.0 + 5.0 ** 0.5) / 2.0
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
         (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2), (10, 7, 6),
         (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5), (2, 4, 11), (6, 2, 10),
         (8, 6, 7), (9, 8, 1)]
    verts = [np.array(p, dtype=np.float64) / np.linalg.norm(p) for p in v]
    for _ in range(int(subdivisions)):
        mid, faces = {}, []

        def midpoint(a, b):
            key = (min(a, b), max(a, b))
            if key not in mid:
                p = verts[a] + verts[b]
                verts.append(p / np.linalg.norm(p))
                mid[key] = len(verts) - 1
            return mid[key]

        for a, b, c in f:
            ab, bc, ca = midpoint(a, b), midpoint(b, c), midpoint(c, a)
            faces += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        f = faces
    return float(radius) * np.array(verts), np.array(f, dtype=np.int64)

