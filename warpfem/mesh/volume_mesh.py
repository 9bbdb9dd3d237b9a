"""The volume mesh: nodes + elements of one element type, validated when constructed.

Conventions
-----------
* ``vertices``: (n, 3) float64 rest positions (m), ``elements``: (m, k) int64 connectivity in the node
  order of the element type (meshio / VTK order; ``warpfem.mesh.element_types``).
* An element is positively oriented when det J > 0 at its quadrature points (for a tet (a, b, c, d):
  ``det[x_b - x_a, x_c - x_a, x_d - x_a] > 0``; ``rest_volumes()`` is that determinant / 6).
* The four faces of a positive tet, oriented outwards (right-hand rule normal points out of the
  tet), are ``(b, c, d), (a, d, c), (a, b, d), (a, c, b)`` (see ``TET_FACES``).

Everything that depends on the element type is asked of the element object (``mesh.element``): the
geometry (det J, volumes), the mirror image used to reorient inverted elements, the face triangles.
"""

from __future__ import annotations

import warnings

import numpy as np

from .element_types import ElementType, get_element
from .element_types.base import TET_FACES
from .element_types.tet4 import tet_volumes

__all__ = ["MeshError", "VolumeMesh", "TetMesh", "ElementMesh", "TET_FACES", "tet_volumes", "boundary_faces"]

#: Relative threshold for degenerate elements: |vol| <= DEGENERATE_RTOL * characteristic_length**3
#: (the mesh's bounding-box diagonal) ...
DEGENERATE_RTOL = 1e-12
#: ... and flat for its own size: |vol| <= DEGENERATE_SHAPE_RTOL * h**3, h the diagonal of the element's
#: own bounding box (a regular tet has 0.06 h^3). Both must hold: a tiny but well-shaped element is
#: not degenerate (TetGen refines a fine scanned surface's near-touching features into tets of
#: 2e-4 of the bounding box, a few 1e-14 of its cube, with 0.01-0.1 h^3).
DEGENERATE_SHAPE_RTOL = 1e-6

_MAX_LISTED = 10


class MeshError(ValueError):
    """Invalid mesh data. The message names the offending element / vertex (and file, if any)."""


def _fmt_list(idx, limit=_MAX_LISTED):
    idx = [int(i) for i in idx]
    s = ", ".join(str(i) for i in idx[:limit])
    if len(idx) > limit:
        s += f", ... ({len(idx) - limit} more)"
    return s


def boundary_faces(mesh_or_tets):
    """Boundary surface as outward triangles (k, 3) int64.

    Accepts a mesh (its :meth:`VolumeMesh.boundary_faces`) or a positively oriented (m, 4) tet
    connectivity array (faces used by exactly one tet).
    """
    if hasattr(mesh_or_tets, "boundary_faces"):
        return np.asarray(mesh_or_tets.boundary_faces())
    tets = np.asarray(mesh_or_tets, dtype=np.int64)
    faces = tets[:, TET_FACES].reshape(-1, 3)  # (4m, 3), outward for positive tets
    key = np.sort(faces, axis=1)
    _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    once = np.sort(first[counts == 1])  # keep element order, deterministic
    return np.ascontiguousarray(faces[once])


def _shared_faces(element, t):
    """The corner faces shared between elements: (e1, e2, same_order, nodes, crowded) with e1, e2 (p,)
    the two elements of each face shared by exactly two, ``nodes`` (p, c) its sorted corners (-1
    padded), ``same_order`` (p,) True where both list the
    face's corners in the same cyclic order (each element lists its faces outward for det J > 0),
    and ``crowded`` a list of the element ids of each face shared by more than two. None when the
    element type has no face table."""
    try:
        tables = [np.asarray(c, dtype=np.int64) for c, _ in element.face_triangles()]
    except NotImplementedError:
        return None
    m = t.shape[0]
    width = max(len(c) for c in tables)
    keys, succ, elem = [], [], []
    rows = np.arange(m)[:, None]
    for c in tables:
        F = t[:, c]  # (m, k) corners in the element's cyclic order
        k = len(c)
        r = F.argmin(axis=1)
        rolled = F[rows, (r[:, None] + np.arange(k)[None, :]) % k]  # smallest corner first
        keys.append(np.pad(np.sort(F, axis=1), ((0, 0), (0, width - k)), constant_values=-1))
        succ.append(rolled[:, 1])  # the corner after the smallest: tells the two cyclic orders apart
        elem.append(np.arange(m))
    keys = np.concatenate(keys)
    succ = np.concatenate(succ)
    elem = np.concatenate(elem)
    order = np.lexsort(keys.T[::-1])  # rows sorted, equal faces adjacent
    ks = keys[order]
    starts = np.flatnonzero(np.concatenate([[True], (ks[1:] != ks[:-1]).any(axis=1)]))
    counts = np.diff(np.append(starts, len(ks)))
    uniq = ks[starts]
    two = np.flatnonzero(counts == 2)
    a, b = order[starts[two]], order[starts[two] + 1]
    crowded = [sorted(set(elem[order[starts[g]:starts[g] + counts[g]]].tolist()))
               for g in np.flatnonzero(counts > 2)]
    return elem[a], elem[b], succ[a] == succ[b], uniq[two], crowded


def _tangled_elements(m, e1, e2, bad, sign):
    """The elements to name for overlapping faces: the shared faces that are fine join elements into
    consistent patches; in each connected part with an overlap, every patch but the largest (on a
    tie: the one with more positive elements) is named (a pushed vertex: its inverted tets)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    def comps(sel):
        g = coo_matrix((np.ones(int(sel.sum())), (e1[sel], e2[sel])), shape=(m, m))
        return connected_components(g, directed=False)[1]

    part = comps(np.ones_like(bad))
    patch = comps(~bad)
    named = []
    for p in np.unique(part[np.concatenate([e1[bad], e2[bad]])]):
        members = np.flatnonzero(part == p)
        ids, local, size = np.unique(patch[members], return_inverse=True, return_counts=True)
        pos = np.bincount(local.ravel(), weights=sign[members] > 0, minlength=len(ids))
        keep = ids[np.lexsort((-pos, -size))[0]]
        named.append(members[patch[members] != keep])
    return np.concatenate(named)


def _tangle_vertex(element, x, t, named, e1, e2, nodes, limit=10000):
    """The vertex to name for a tangle: a corner of an element at an overlapping face that lies
    inside the element across that face (a vertex pushed through a face lies in the element beyond
    it), the one found most often; else (and to break ties) the corner most common to the named
    elements."""
    count = np.bincount(t[named][:, element.corner_nodes].ravel(), minlength=len(x)).astype(np.float64)
    hits = np.zeros(len(x))
    sub = element.corner_tets
    for a, b in ((e1[:limit], e2[:limit]), (e2[:limit], e1[:limit])):
        corners = t[a][:, element.corner_nodes]  # (p, c): the corners of a off the face are its apexes
        apex = ~(corners[:, :, None] == nodes[:limit][:, None, :]).any(axis=2)
        rows, cols = np.nonzero(apex)
        p = corners[rows, cols]  # apex vertices, element b each
        T = x[t[b[rows]][:, sub]]  # (r, s, 4, 3) the sub-tets of b
        A = np.moveaxis(T[:, :, 1:] - T[:, :, :1], 2, 3)  # (r, s, 3, 3) columns = edges
        try:
            lam = np.linalg.solve(A, (x[p][:, None, :] - T[:, :, 0])[..., None])[..., 0]
        except np.linalg.LinAlgError:  # a flat corner sub-tet (a warped hex): count only
            continue
        inside = ((lam > 0).all(axis=2) & (lam.sum(axis=2) < 1)).any(axis=1)
        np.add.at(hits, p[inside], 1.0)
    score = hits * (count.max() + 1) + count
    return int(score.argmax())


class VolumeMesh:
    """A validated volume mesh of one element type.

    Parameters
    ----------
    vertices : (n, 3) array_like of float
    elements : (m, k) array_like of int, k = ``element.nodes_per_element``
    element_type : str or ElementType
        A registered element type (``warpfem.mesh.element_types.ELEMENTS``: "tet4" (default),
        "tet10", "hex8", "hex27") or its object.
    reorient : bool
        Replace elements that are inverted everywhere (det J < 0 at every quadrature point) by their
        mirror image (same nodes, ``element.mirror_permutation``; Tet4: swap local vertices 2 and 3),
        with a warning. If False, inverted elements raise ``MeshError``.
    remove_unreferenced : bool
        Drop vertices used by no element and compact the indices (with a warning).
        ``vertex_map[i]`` is the new index of input vertex ``i`` (-1 if removed).
    name : str, optional
        Used as a prefix in error and warning messages (the loaders pass the file name).

    Every type gets the same checks, each raising :class:`MeshError` naming the element / vertex:
    shapes, integer indices, finite coordinates, indices in range, no repeated node in an element,
    no degenerate (zero-volume) element and no element whose det J changes sign inside (tangled).
    """

    def __init__(self, vertices, elements, element_type="tet4", *, reorient=True, remove_unreferenced=True,
                 name=None):
        self.name = None if name is None else str(name)
        try:
            element = get_element(element_type)
        except ValueError as exc:
            raise MeshError(self._msg(str(exc))) from None
        self.element: ElementType = element
        self.element_type: str = element.name
        self.nodes_per_element: int = element.nodes_per_element
        noun = element.noun
        x = self._as_vertices(vertices)
        t = self._as_elements(elements)
        n = x.shape[0]

        # Non-finite coordinates.
        bad = np.flatnonzero(~np.isfinite(x).all(axis=1))
        if bad.size:
            kinds = "NaN" if np.isnan(x[bad[0]]).any() else "inf"
            raise MeshError(self._msg(
                f"vertex {bad[0]} has non-finite ({kinds}) coordinates {x[bad[0]].tolist()}; "
                f"{bad.size} vertices with NaN/inf: {_fmt_list(bad)}"))

        # Index range.
        oob = (t < 0) | (t >= n)
        if oob.any():
            rows = np.flatnonzero(oob.any(axis=1))
            e = rows[0]
            idx = int(t[e][oob[e]][0])
            raise MeshError(self._msg(
                f"{noun} {e} references vertex index {idx} out of range [0, {n}) ({noun} = {t[e].tolist()}); "
                f"{rows.size} {noun}s with bad indices: "
                f"{_fmt_list(rows)}"))

        # Repeated vertex within an element.
        s = np.sort(t, axis=1)
        rep = np.flatnonzero((s[:, 1:] == s[:, :-1]).any(axis=1))
        if rep.size:
            e = rep[0]
            raise MeshError(self._msg(
                f"{noun} {e} repeats a vertex ({noun} = {t[e].tolist()}); "
                f"{rep.size} {noun}s with repeated vertices: {_fmt_list(rep)}"))

        # Unreferenced vertices.
        used = np.zeros(n, dtype=bool)
        used[t.ravel()] = True
        unref = np.flatnonzero(~used)
        self.unreferenced_vertices = unref
        if unref.size and remove_unreferenced:
            vmap = np.full(n, -1, dtype=np.int64)
            vmap[used] = np.arange(int(used.sum()), dtype=np.int64)
            x = x[used]
            t = vmap[t]
            warnings.warn(self._msg(
                f"{unref.size} unreferenced vertices removed (indices compacted, see "
                f"vertex_map): {_fmt_list(unref)}"), stacklevel=2)
        else:
            vmap = np.arange(n, dtype=np.int64)
            if unref.size:
                warnings.warn(self._msg(
                    f"{unref.size} unreferenced vertices kept: {_fmt_list(unref)}"), stacklevel=2)

        # Degenerate (zero-volume) elements, scale-aware, then orientation (det J sign at every point).
        L = self._bbox_diagonal(x, t)
        vol = element.signed_point_volumes(x, t)  # (m, q)
        thresh = DEGENERATE_RTOL * L**3
        small = (np.abs(vol) <= thresh).any(axis=1)
        if small.any():
            idx = np.flatnonzero(small)
            X = x[t[idx]]
            h = np.linalg.norm(X.max(axis=1) - X.min(axis=1), axis=1)
            small[idx] = (np.abs(vol[idx]) <= DEGENERATE_SHAPE_RTOL * h[:, None] ** 3).any(axis=1)
        degen = np.flatnonzero(small)
        if degen.size:
            raise MeshError(self._msg(
                f"{degen.size} degenerate (zero-volume) {noun}s, |vol| <= {thresh:.3g} "
                f"(= {DEGENERATE_RTOL:g} * {L:.3g}^3) and <= {DEGENERATE_SHAPE_RTOL:g} * (own size)^3: "
                f"{noun}s {_fmt_list(degen)}"))
        tangled = np.flatnonzero((vol < 0).any(axis=1) & (vol > 0).any(axis=1))
        if tangled.size:
            raise MeshError(self._msg(
                f"{tangled.size} {noun}s with det J changing sign inside (tangled rest shape or wrong node "
                f"order): {noun}s {_fmt_list(tangled)}"))
        # Elements overlapping their neighbours (a tangle: a vertex pushed through a face of its star)
        # are refused; flipped elements that do not overlap anything are reoriented below.
        self._check_overlaps(x, t, np.where((vol > 0).all(axis=1), 1, -1), np.flatnonzero(vmap >= 0))
        neg = np.flatnonzero((vol < 0).all(axis=1))
        self.reoriented_tets = neg
        if neg.size:
            if not reorient:
                raise MeshError(self._msg(
                    f"{neg.size} negatively oriented {noun}s: {_fmt_list(neg)}"))
            perm = element.mirror_permutation
            t = t.copy()
            t[neg] = t[neg][:, perm]
            pairs = [(i, int(j)) for i, j in enumerate(perm) if i < j]
            how = (f"swapped local vertices {pairs[0][0]} and {pairs[0][1]}" if len(pairs) == 1
                   else "mirrored: swapped local nodes " + ", ".join(f"{i}-{j}" for i, j in pairs))
            warnings.warn(self._msg(
                f"reoriented {neg.size} of {t.shape[0]} negatively oriented {noun}s "
                f"({how}): {_fmt_list(neg)}"), stacklevel=2)

        x = np.array(x, dtype=np.float64, copy=True)
        t = np.array(t, dtype=np.int64, copy=True)
        vmap = np.array(vmap, copy=True)
        for a in (x, t, vmap):
            a.setflags(write=False)
        self._vertices = x
        self._elements = t
        self._volumes = None
        self.vertex_map = vmap
        self._boundary = None

    # ------------------------------------------------------------------ helpers
    def _check_overlaps(self, x, t, sign, input_ids):
        """Raise ``MeshError`` when elements sharing a face lie on the same side of it.

        ``sign`` (m,) is each element's orientation (+1: det J > 0 at every point, -1: < 0);
        ``input_ids`` the input index of each vertex (for the message). Across a
        face shared by two elements, the two lie on opposite sides of it exactly when they list the
        face's corners in opposite cyclic orders and have the same sign, or in the same order and
        opposite signs (for a Tet4 this is the sign test of the two opposite vertices against the
        face; curved and hex elements are judged by their det J sign and their corner faces). A
        mesh, or a connected part of it, written with the other winding passes (every sign and every
        order flipped), and so does any element stored with its own nodes mirrored. A face shared by
        more than two elements is an overlap as well.
        """
        faces = _shared_faces(self.element, t)
        if faces is None:
            return
        e1, e2, same_order, nodes, crowded = faces
        bad = (sign[e1] == sign[e2]) == same_order
        if not bad.any() and not crowded:
            return
        noun = self.element.noun
        m = t.shape[0]
        named = set()
        if bad.any():
            named.update(_tangled_elements(m, e1, e2, bad, sign).tolist())
        for ids in crowded:
            named.update(ids)
        named = np.array(sorted(named), dtype=np.int64)
        v = _tangle_vertex(self.element, x, t, named, e1[bad], e2[bad], nodes[bad])
        where = ", ".join(f"{c:.6g}" for c in x[v])
        v_in = int(input_ids[v])
        parts = []
        if bad.any():
            parts.append(f"{int(bad.sum())} shared face(s) with both {noun}s on the same side")
        if crowded:
            parts.append(f"{len(crowded)} face(s) shared by more than two {noun}s (first: {noun}s "
                         f"{_fmt_list(crowded[0])})")
        raise MeshError(self._msg(
            f"tangled mesh: {named.size} {noun}s overlap their neighbours ({'; '.join(parts)}): "
            f"{noun}s {_fmt_list(named)}, around vertex {v_in} at ({where}); "
            f"a vertex pushed through a face of its star, or elements that cross each other. "
            f"Only elements that overlap nothing (a mesh or a connected part of it written with the "
            f"other winding) are reoriented; fix the vertex positions"))

    def _msg(self, text):
        return f"{self.name}: {text}" if self.name else text

    def _as_vertices(self, vertices):
        try:
            x = np.array(vertices, dtype=np.float64, copy=True)
        except (TypeError, ValueError) as exc:
            raise MeshError(self._msg(f"vertices are not a numeric array: {exc}")) from None
        if x.ndim != 2 or x.shape[1] != 3:
            raise MeshError(self._msg(f"vertices must have shape (n, 3), got {x.shape}"))
        if x.shape[0] == 0:
            raise MeshError(self._msg("mesh has no vertices"))
        return x

    def _as_elements(self, elements):
        k, noun = self.nodes_per_element, self.element.noun
        t = np.asarray(elements)
        if t.size == 0 and (t.ndim != 2 or t.shape[1] == k or t.shape == (0,)):
            raise MeshError(self._msg(f"mesh has no {noun}s ({noun}s shape {t.shape})"))
        if t.ndim != 2 or t.shape[1] != k:
            raise MeshError(self._msg(f"{noun}s must have shape (m, {k}), got {t.shape}"))
        if t.dtype.kind in "iu":
            return t.astype(np.int64)
        if t.dtype.kind == "f":
            ti = np.rint(t)
            bad = np.flatnonzero((~np.isfinite(t) | (ti != t)).any(axis=1))
            if bad.size:
                raise MeshError(self._msg(
                    f"{noun} {bad[0]} has non-integer indices {t[bad[0]].tolist()}"))
            return ti.astype(np.int64)
        raise MeshError(self._msg(f"{noun}s must be integers, got dtype {t.dtype}"))

    @staticmethod
    def _bbox_diagonal(x, t=None):
        pts = x if t is None else x[np.unique(t)]
        return float(np.linalg.norm(pts.max(axis=0) - pts.min(axis=0)))

    # --------------------------------------------------------------- properties
    @property
    def vertices(self):
        """(n, 3) float64 rest positions (read-only)."""
        return self._vertices

    @property
    def elements(self):
        """(m, k) int64 connectivity, positively oriented (read-only)."""
        return self._elements

    @property
    def tets(self):
        """Linear-tet meshes only: the (m, 4) connectivity (the same array as ``elements``)."""
        if not self.element.is_linear_tet:
            raise AttributeError(f"a {self.element_type} mesh has no 'tets'; use elements or corner_tets()")
        return self._elements

    @property
    def num_vertices(self):
        return int(self._vertices.shape[0])

    @property
    def num_elements(self):
        return int(self._elements.shape[0])

    @property
    def num_tets(self):
        return len(self.tets)

    # ------------------------------------------------------------------ queries
    def rest_volumes(self):
        """Element volumes (m,) float64, all > 0 (Tet4: 1/6 det[x1-x0, x2-x0, x3-x0]; other types:
        sum_q w_q det J_q of the stiffness rule, exact for affine elements)."""
        if self._volumes is None:
            v = np.array(self.element.rest_volumes(self._vertices, self._elements), dtype=np.float64)
            v.setflags(write=False)
            self._volumes = v
        return self._volumes

    def total_volume(self):
        return float(self.rest_volumes().sum())

    def check(self):
        """Raise ``ElementError`` naming elements with det J <= 0 at a quadrature point."""
        self.element.point_data(self._vertices, self._elements, "stiffness")

    def bounds(self):
        """(min, max) corners of the axis-aligned bounding box, each (3,) float64."""
        return self._vertices.min(axis=0), self._vertices.max(axis=0)

    def characteristic_length(self):
        """Bounding-box diagonal length."""
        lo, hi = self.bounds()
        return float(np.linalg.norm(hi - lo))

    def corner_tets(self):
        """(m * s, 4) straight-sided tets over the element corners (s = 1 for tets, 6 for hexes,
        split around the diagonal 0-6: ``element.corner_tets``); tet i belongs to element i // s."""
        return np.ascontiguousarray(self._elements[:, self.element.corner_tets].reshape(-1, 4))

    def boundary_faces(self):
        """Boundary surface as outward triangles (t, 3) int64 over the mesh nodes: the faces used by
        one element only (Tet4: the faces themselves), curved faces triangulated through their nodes
        (``element.face_triangles()``: Tet10 4 triangles per face, Hex8 2, Hex27 8), in element order."""
        if self._boundary is None:
            tables = self.element.face_triangles()
            e = self._elements
            nf = len(tables)
            width = max(len(c) for c, _ in tables)  # faces may differ in corner count (a prism: 3 and 4)
            keys = np.stack([np.pad(np.sort(e[:, c], axis=1), ((0, 0), (0, width - len(c))), constant_values=-1)
                             for c, _ in tables], axis=1).reshape(len(e) * nf, -1)
            uniq, inv, counts = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
            once = np.flatnonzero(counts[inv.ravel()] == 1)  # (element * nf + face), ascending
            tris, order = [], []
            per_face = max(len(tri) for _, tri in tables)
            for f, (_, tri) in enumerate(tables):
                sel = once[once % nf == f]
                tris.append(e[sel // nf][:, tri].reshape(-1, 3))
                order.append(sel.repeat(len(tri)) * per_face + np.tile(np.arange(len(tri)), len(sel)))
            out = np.concatenate(tris, axis=0)[np.argsort(np.concatenate(order), kind="stable")]
            out = np.ascontiguousarray(out, dtype=np.int64)
            out.setflags(write=False)
            self._boundary = out
        return self._boundary

    def boundary_vertices(self):
        """Sorted indices of vertices on the boundary surface."""
        return np.unique(self.boundary_faces())

    def quality(self):
        """Mean-ratio quality per element: 12 (3|V|)^(2/3) / sum of squared edge lengths of its corner
        tets (the worst one for elements split into several). 1 for a regular tet, -> 0 for slivers."""
        ct = self.corner_tets()
        x = self._vertices[ct]
        pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
        l2 = sum(np.sum((x[:, i] - x[:, j]) ** 2, axis=1) for i, j in pairs)
        q = 12.0 * (3.0 * np.abs(tet_volumes(self._vertices, ct))) ** (2.0 / 3.0) / l2
        return q.reshape(self.num_elements, -1).min(axis=1)

    def submesh(self, elements, *, name=None):
        """A new mesh of the same type from a subset of the elements (bool mask or indices), unused
        vertices removed; its ``vertex_map`` maps *this* mesh's vertex indices to the new ones (-1
        dropped) and ``tet_map`` (= ``element_map``) lists the parent element of each new element."""
        sel = np.asarray(elements)
        idx = np.flatnonzero(sel) if sel.dtype == bool else sel.astype(np.int64)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sub = VolumeMesh(self._vertices, self._elements[idx], self.element, reorient=False,
                             remove_unreferenced=True, name=name if name is not None else self.name)
        sub.tet_map = sub.element_map = idx
        return sub

    def __repr__(self):
        nm = f" {self.name!r}" if self.name else ""
        return (f"VolumeMesh{nm}({self.element_type}, num_vertices={self.num_vertices}, "
                f"num_elements={self.num_elements})")


#: The historical names of the one mesh class (``TetMesh(vertices, tets)`` is a Tet4 mesh,
#: ``ElementMesh(vertices, elements, "hex8")`` any type): the same class, kept for existing code.
TetMesh = ElementMesh = VolumeMesh
