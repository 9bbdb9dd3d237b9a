"""Meshes of any element type (Tet4, Tet10, Hex8, Hex27): type, generators, file I/O, embedding.

Node order of every element follows :mod:`warpfem.elements.library` (= meshio / VTK order).
"""

from __future__ import annotations

import numbers
import os

import numpy as np

from warpfem.mesh import MeshError, TetMesh

from .library import (ELEMENT_TYPES, MESHIO_CELL_TYPE, NODES_PER_ELEMENT, REFERENCE_NODES, TET10_EDGES,
                      check_element_type, shape_functions, shape_gradients)
from warpfem.mesh.element_types import get_element

__all__ = ["ElementMesh", "box_hex_mesh", "tet10_from_tet4", "load_element_mesh", "save_element_mesh",
           "embed_points_in_elements"]

from warpfem.mesh.element_types.base import HEX_FACES as _HEX_FACES, TET_FACES as _TET_FACES  # noqa: E402


def _hex_face_tables(element_type):
    """Per face: corner node ids (4,) and outward triangles (t, 3) over the face's nodes."""
    nodes = REFERENCE_NODES[element_type]
    lookup = {tuple(np.rint(p).astype(int)): i for i, p in enumerate(nodes)}
    levels = [-1, 1] if element_type == "hex8" else [-1, 0, 1]
    out = []
    for axis, sign, u, v in _HEX_FACES:
        def node(a, b):
            c = [0, 0, 0]
            c[axis], c[u], c[v] = sign, a, b
            return lookup[tuple(c)]

        corners = [node(-1, -1), node(1, -1), node(1, 1), node(-1, 1)]
        tris = []
        for i in range(len(levels) - 1):
            for j in range(len(levels) - 1):
                a, b = node(levels[i], levels[j]), node(levels[i + 1], levels[j])
                c, d = node(levels[i + 1], levels[j + 1]), node(levels[i], levels[j + 1])
                tris += [(a, b, c), (a, c, d)]
        out.append((np.array(corners), np.array(tris)))
    return out


def _tet10_face_tables():
    edge = {}
    for i, (a, b) in enumerate(TET10_EDGES):
        edge[(a, b)] = edge[(b, a)] = 4 + i
    out = []
    for a, b, c in _TET_FACES:
        ab, bc, ca = edge[(a, b)], edge[(b, c)], edge[(c, a)]
        out.append((np.array([a, b, c]), np.array([(a, ab, ca), (ab, b, bc), (ca, bc, c), (ab, bc, ca)])))
    return out


class ElementMesh:
    """A volume mesh of one element type.

    Args:
        vertices: (n, 3) node positions (m).
        elements: (m, k) node indices per element in the order of :mod:`warpfem.elements.library`
            (k = 4, 10, 8, 27 for "tet4", "tet10", "hex8", "hex27").
        element_type: one of ``ELEMENT_TYPES``.
        name: optional, prefixes error messages.

    Validates shapes, finiteness and index ranges (:class:`~warpfem.mesh.MeshError` naming the
    element / vertex). Orientation (det J > 0 at every quadrature point) is checked when a
    :class:`warpfem.Model` is built (``ElementError`` naming the elements), or by :meth:`check`.
    """

    def __init__(self, vertices, elements, element_type: str, *, name=None):
        self.name = None if name is None else str(name)
        if element_type not in ELEMENT_TYPES:
            raise MeshError(self._msg(f"unknown element type {element_type!r}; supported: {', '.join(ELEMENT_TYPES)}"))
        k = NODES_PER_ELEMENT[element_type]
        x = np.array(vertices, dtype=np.float64, copy=True)
        if x.ndim != 2 or x.shape[1] != 3 or len(x) == 0:
            raise MeshError(self._msg(f"vertices must have shape (n, 3) with n > 0, got {x.shape}"))
        bad = np.flatnonzero(~np.isfinite(x).all(axis=1))
        if bad.size:
            raise MeshError(self._msg(f"vertex {bad[0]} has non-finite coordinates {x[bad[0]].tolist()} ({bad.size} such)"))
        e = np.asarray(elements)
        if e.ndim != 2 or e.shape[1] != k or len(e) == 0:
            raise MeshError(self._msg(f"{element_type} elements must have shape (m, {k}) with m > 0, got {e.shape}"))
        if e.dtype.kind not in "iu":
            raise MeshError(self._msg(f"elements must be integers, got dtype {e.dtype}"))
        e = np.array(e, dtype=np.int64, copy=True)
        oob = np.flatnonzero(((e < 0) | (e >= len(x))).any(axis=1))
        if oob.size:
            raise MeshError(self._msg(f"element {oob[0]} references a vertex out of range [0, {len(x)}): "
                                      f"{e[oob[0]].tolist()} ({oob.size} such)"))
        s = np.sort(e, axis=1)
        rep = np.flatnonzero((s[:, 1:] == s[:, :-1]).any(axis=1))
        if rep.size:
            raise MeshError(self._msg(f"element {rep[0]} repeats a vertex: {e[rep[0]].tolist()} ({rep.size} such)"))
        x.setflags(write=False)
        e.setflags(write=False)
        self._vertices, self._elements, self.element_type = x, e, element_type
        self.nodes_per_element = k
        self._boundary = None

    def _msg(self, text):
        return f"{self.name}: {text}" if self.name else text

    @property
    def element(self):
        """The element type object (:class:`warpfem.mesh.element_types.ElementType`)."""
        return get_element(self.element_type)

    @property
    def vertices(self):
        """(n, 3) float64 node positions, m (read-only)."""
        return self._vertices

    @property
    def elements(self):
        """(m, k) int64 connectivity (read-only)."""
        return self._elements

    @property
    def num_vertices(self):
        return int(len(self._vertices))

    @property
    def num_elements(self):
        return int(len(self._elements))

    @property
    def tets(self):
        """Tet4 meshes only: the (m, 4) connectivity (``TetMesh`` compatibility)."""
        if self.element_type != "tet4":
            raise AttributeError(f"a {self.element_type} mesh has no 'tets'; use elements or corner_tets()")
        return self._elements

    @property
    def num_tets(self):
        return len(self.tets)

    def bounds(self):
        return self._vertices.min(axis=0), self._vertices.max(axis=0)

    def check(self):
        """Raise ``ElementError`` naming elements with det J <= 0 at a quadrature point."""
        from .quadrature import precompute_quadrature

        precompute_quadrature(self._vertices, self._elements, self.element_type)

    def rest_volumes(self):
        """(m,) element volumes (m^3) from the stiffness rule (exact for affine elements)."""
        from .quadrature import precompute_quadrature

        qd = precompute_quadrature(self._vertices, self._elements, self.element_type)
        return np.bincount(qd.qp_element, weights=qd.qp_weight, minlength=self.num_elements)

    def total_volume(self):
        return float(self.rest_volumes().sum())

    def corner_tets(self):
        """(m * s, 4) straight-sided tets over the element corners (s = 1 for tets, 6 for hexes,
        split around the diagonal 0-6: ``element.corner_tets``); tet i belongs to element i // s."""
        return np.ascontiguousarray(self._elements[:, self.element.corner_tets].reshape(-1, 4))

    def boundary_faces(self):
        """Boundary surface as outward triangles (t, 3) over the mesh nodes. Faces used by one
        element only; curved faces are triangulated through their mid-nodes (Tet10: 4 triangles
        per face, Hex8: 2, Hex27: 8), so the surface follows every node."""
        if self._boundary is None:
            if self.element_type == "tet4":
                tables = [(f, f[None, :]) for f in _TET_FACES]
            elif self.element_type == "tet10":
                tables = _tet10_face_tables()
            else:
                tables = _hex_face_tables(self.element_type)
            e = self._elements
            nf = len(tables)
            keys = np.stack([np.sort(e[:, c], axis=1) for c, _ in tables], axis=1).reshape(len(e) * nf, -1)
            _, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
            once = np.flatnonzero(counts[inv.ravel()] == 1)  # (element * nf + face)
            tris = []
            for idx in once:
                el, f = divmod(int(idx), nf)
                tris.append(e[el][tables[f][1]])
            out = np.concatenate(tris, axis=0) if tris else np.zeros((0, 3), np.int64)
            out.setflags(write=False)
            self._boundary = out
        return self._boundary

    def boundary_vertices(self):
        return np.unique(self.boundary_faces())

    def __repr__(self):
        return f"ElementMesh({self.element_type}, num_vertices={self.num_vertices}, num_elements={self.num_elements})"


def _check_box_args(size, cells, origin):
    cells = tuple(cells)
    if len(cells) != 3 or not all(isinstance(c, numbers.Integral) and not isinstance(c, bool) and c >= 1 for c in cells):
        raise MeshError(f"cells must be three integers >= 1, got {cells!r}")
    size = np.asarray(size, dtype=np.float64)
    origin = np.asarray(origin, dtype=np.float64)
    if size.shape != (3,) or not np.all(np.isfinite(size)) or not np.all(size > 0):
        raise MeshError(f"size must be three finite values > 0 (m), got {np.ravel(size).tolist()}")
    if origin.shape != (3,) or not np.all(np.isfinite(origin)):
        raise MeshError(f"origin must be three finite values (m), got {np.ravel(origin).tolist()}")
    return size, tuple(int(c) for c in cells), origin


def box_hex_mesh(*, size=(1.0, 1.0, 1.0), cells=(1, 1, 1), origin=(0.0, 0.0, 0.0), order: int = 1, name=None):
    """Hex mesh of the box ``origin + [0, size]`` (m) with ``cells = (nx, ny, nz)`` cells.

    ``order=1``: Hex8; ``order=2``: Hex27 (nodes on the grid refined twice). Grid node (i, j, k)
    has index ``i + (o nx + 1) (j + (o ny + 1) k)`` with o = order.
    """
    if order not in (1, 2):
        raise MeshError(f"order must be 1 (hex8) or 2 (hex27), got {order!r}")
    size, (nx, ny, nz), origin = _check_box_args(size, cells, origin)
    o = order
    gx, gy, gz = o * nx + 1, o * ny + 1, o * nz + 1
    k, j, i = np.meshgrid(np.arange(gz), np.arange(gy), np.arange(gx), indexing="ij")
    ijk = np.stack([i.ravel(), j.ravel(), k.ravel()], axis=1)
    h = size / (o * np.array([nx, ny, nz], dtype=np.float64))
    vertices = origin + ijk * h
    for d, g in enumerate((gx, gy, gz)):
        vertices[ijk[:, d] == g - 1, d] = origin[d] + size[d]
    etype = "hex8" if order == 1 else "hex27"
    ref = np.rint((REFERENCE_NODES[etype] + 1) * o / 2).astype(np.int64)  # (k, 3) grid offsets
    ck, cj, ci = np.meshgrid(np.arange(nz), np.arange(ny), np.arange(nx), indexing="ij")
    base = o * np.stack([ci.ravel(), cj.ravel(), ck.ravel()], axis=1)
    node = base[:, None, :] + ref[None]
    elements = node[..., 0] + gx * (node[..., 1] + gy * node[..., 2])
    return ElementMesh(vertices, elements, etype, name=name)


def tet10_from_tet4(mesh, *, name=None):
    """Tet10 mesh from a Tet4 mesh (``TetMesh`` or ``ElementMesh``): one mid-node per unique edge
    (shared between neighbours), placed at the edge midpoint; corner indices are kept."""
    tets = np.asarray(getattr(mesh, "tets", getattr(mesh, "elements", None)), dtype=np.int64)
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise MeshError(f"tet10_from_tet4 needs a Tet4 mesh with (m, 4) elements, got {tets.shape}")
    X = np.asarray(mesh.vertices, dtype=np.float64)
    edges = tets[:, TET10_EDGES]  # (m, 6, 2)
    key = np.sort(edges.reshape(-1, 2), axis=1)
    uniq, inv = np.unique(key, axis=0, return_inverse=True)
    mids = 0.5 * (X[uniq[:, 0]] + X[uniq[:, 1]])
    elements = np.concatenate([tets, len(X) + inv.reshape(-1, 6)], axis=1)
    return ElementMesh(np.concatenate([X, mids]), elements, "tet10", name=name if name is not None else getattr(mesh, "name", None))


def load_element_mesh(path, *, element_type=None):
    """Read a meshio file with ``tetra``, ``tetra10``, ``hexahedron`` or ``hexahedron27`` cells.

    With ``element_type=None`` the file must hold volume cells of exactly one of these types
    (other cells, e.g. surface triangles, are ignored). Unreferenced points are kept. Errors name
    the file and the cell types found.
    """
    import meshio

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"mesh file not found: {path}")
    try:
        m = meshio.read(path)
    except Exception as exc:
        raise MeshError(f"{path}: meshio could not read the file: {type(exc).__name__}: {exc}") from exc
    to_type = {v: k for k, v in MESHIO_CELL_TYPE.items()}
    found = {to_type[c.type] for c in m.cells if c.type in to_type and len(c.data)}
    if element_type is not None:
        check_element_type(element_type)
        found &= {element_type}
    if len(found) != 1:
        types = sorted({f"{c.type} ({len(c.data)})" for c in m.cells}) or ["none"]
        what = "no supported volume cells" if not found else f"several volume cell types {sorted(found)} (pass element_type=)"
        raise MeshError(f"{path}: {what}; cell types in file: {', '.join(types)}")
    etype = found.pop()
    data = np.concatenate([c.data for c in m.cells if c.type == MESHIO_CELL_TYPE[etype] and len(c.data)])
    points = np.asarray(m.points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise MeshError(f"{path}: points must be 3D, got shape {points.shape}")
    return ElementMesh(points, data.astype(np.int64), etype, name=path)


def save_element_mesh(mesh, path, **kw):
    """Write an element mesh (nodes + its cells) with meshio; the format comes from the extension
    (".msh" writes Gmsh 4.1 ASCII). ``kw`` goes to ``meshio.write``."""
    import meshio

    path = os.fspath(path)
    etype = mesh.element_type
    cells = [(MESHIO_CELL_TYPE[etype], np.asarray(mesh.elements, dtype=np.int64))]
    if path.endswith(".msh"):  # Gmsh (meshio would otherwise pick ANSYS, which has no quadratic cells)
        kw.setdefault("file_format", "gmsh")
        kw.setdefault("binary", False)
    meshio.write(path, meshio.Mesh(np.asarray(mesh.vertices, dtype=np.float64), cells), **kw)
    return path


def embed_points_in_elements(points, mesh, *, max_newton_iters: int = 30, corner_embedding=None):
    """Embed points (p, 3) in an element mesh: x(point) = sum_a w_a x_{ids_a}.

    Returns ``(ids (p, k) int64, weights (p, k) float64, element (p,) int64)``: the element's
    nodes and its shape functions at the point's reference coordinates (rows sum to 1). The
    element is found on the corner tets (:func:`warpfem.mesh.locate.embed_points`, nearest for
    outside points); reference coordinates: barycentric for tets, refined for every type by Newton
    on the isoparametric map X(xi) = sum_a N_a(xi) X_a (the inverse map of hexes and curved Tet10).
    A point outside the mesh keeps extrapolated coordinates (weights may be negative).
    ``corner_embedding``: the result of ``embed_points(points, mesh.vertices, mesh.corner_tets())``
    when the caller already has it (the search is then not repeated).
    """
    from warpfem.mesh.locate import embed_points

    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (p, 3), got {points.shape}")
    if not np.all(np.isfinite(points)):
        i = int(np.flatnonzero(~np.isfinite(points).all(axis=1))[0])
        raise ValueError(f"point {i} has a non-finite coordinate: {points[i].tolist()}")
    etype = mesh.element_type
    element = get_element(etype)
    elements = np.asarray(mesh.elements, dtype=np.int64)
    X = np.asarray(mesh.vertices, dtype=np.float64)
    corner = elements[:, element.corner_tets].reshape(-1, 4)
    emb = corner_embedding if corner_embedding is not None else embed_points(points, X, corner)
    s = len(corner) // len(elements)
    elem = emb.tet_index // s
    # initial reference coordinates: barycentric interpolation of the corner tet's reference nodes
    ref_tet = element.reference_nodes[element.corner_tets[emb.tet_index % s]]  # (p, 4, 3)
    xi = np.einsum("pa,pai->pi", emb.weights, ref_tet)
    if etype != "tet4":
        Xe = X[elements[elem]]  # (p, k, 3)
        scale = np.linalg.norm(Xe.max(axis=1) - Xe.min(axis=1), axis=1)
        for _ in range(int(max_newton_iters)):
            N = shape_functions(etype, xi)
            dN = shape_gradients(etype, xi)
            r = points - np.einsum("pa,pai->pi", N, Xe)
            if np.all(np.linalg.norm(r, axis=1) <= 1e-13 * scale):
                break
            J = np.einsum("pai,paj->pij", Xe, dN)
            xi = xi + np.linalg.solve(J, r[:, :, None])[:, :, 0]
        else:
            r = points - np.einsum("pa,pai->pi", shape_functions(etype, xi), Xe)
            bad = np.flatnonzero(np.linalg.norm(r, axis=1) > 1e-8 * scale)
            if bad.size:
                import warnings

                warnings.warn(f"inverse isoparametric map did not converge for {bad.size} point(s) (first: point "
                              f"{int(bad[0])} in element {int(elem[bad[0]])}); their weights are approximate",
                              RuntimeWarning, stacklevel=2)
    weights = shape_functions(etype, xi)
    return elements[elem], weights, elem
