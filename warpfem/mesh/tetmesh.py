"""Linear tetrahedral mesh (Tet4) with constructor-time validation.

Conventions
-----------
* ``vertices``: (n, 3) float64 rest positions, ``tets``: (m, 4) int64 connectivity.
* A tet (a, b, c, d) is positively oriented when
  ``det[x_b - x_a, x_c - x_a, x_d - x_a] > 0``; ``rest_volumes()`` is that determinant / 6.
* The four faces of a positive tet, oriented outwards (right-hand rule normal points out of the
  tet), are ``(b, c, d), (a, d, c), (a, b, d), (a, c, b)`` (see ``TET_FACES``).
"""

from __future__ import annotations

import warnings

import numpy as np

__all__ = ["MeshError", "TetMesh", "TET_FACES", "tet_volumes", "boundary_faces"]

# Local vertex indices of the outward-oriented faces of a positively oriented tet.
TET_FACES = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], dtype=np.int64)

#: Relative threshold for degenerate tets: |vol| <= DEGENERATE_RTOL * characteristic_length**3.
DEGENERATE_RTOL = 1e-12

_MAX_LISTED = 10


class MeshError(ValueError):
    """Invalid mesh data. The message names the offending element / vertex (and file, if any)."""


def _fmt_list(idx, limit=_MAX_LISTED):
    idx = [int(i) for i in idx]
    s = ", ".join(str(i) for i in idx[:limit])
    if len(idx) > limit:
        s += f", ... ({len(idx) - limit} more)"
    return s


def tet_volumes(vertices, tets):
    """Signed volumes 1/6 det[x1 - x0, x2 - x0, x3 - x0] of each tet, shape (m,)."""
    x = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(tets, dtype=np.int64)
    x0 = x[t[:, 0]]
    d1 = x[t[:, 1]] - x0
    d2 = x[t[:, 2]] - x0
    d3 = x[t[:, 3]] - x0
    return np.einsum("ij,ij->i", d1, np.cross(d2, d3)) / 6.0


def boundary_faces(mesh_or_tets):
    """Faces used by exactly one tet, (k, 3) int64, oriented outwards.

    Accepts a ``TetMesh`` or a positively oriented (m, 4) connectivity array.
    """
    tets = getattr(mesh_or_tets, "tets", mesh_or_tets)
    tets = np.asarray(tets, dtype=np.int64)
    faces = tets[:, TET_FACES].reshape(-1, 3)  # (4m, 3), outward for positive tets
    key = np.sort(faces, axis=1)
    _, first, counts = np.unique(key, axis=0, return_index=True, return_counts=True)
    once = np.sort(first[counts == 1])  # keep element order, deterministic
    return np.ascontiguousarray(faces[once])


class TetMesh:
    """A validated Tet4 mesh.

    Parameters
    ----------
    vertices : (n, 3) array_like of float
    tets : (m, 4) array_like of int
    reorient : bool
        Swap two vertices of negatively oriented tets (with a warning). If False, negative tets
        raise ``MeshError``.
    remove_unreferenced : bool
        Drop vertices used by no tet and compact the indices (with a warning).
        ``vertex_map[i]`` is the new index of input vertex ``i`` (-1 if removed).
    name : str, optional
        Used as a prefix in error and warning messages (``load_mesh`` passes the file name).
    """

    element_type = "tet4"
    nodes_per_element = 4

    @property
    def element(self):
        """The element type object (:class:`warpfem.mesh.element_types.ElementType`): Tet4."""
        from .element_types import get_element

        return get_element(self.element_type)

    def __init__(self, vertices, tets, *, reorient=True, remove_unreferenced=True, name=None):
        self.name = None if name is None else str(name)
        x = self._as_vertices(vertices)
        t = self._as_tets(tets)
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
                f"tet {e} references vertex index {idx} out of range [0, {n}) "
                f"(tet = {t[e].tolist()}); {rows.size} tets with bad indices: {_fmt_list(rows)}"))

        # Repeated vertex within a tet.
        s = np.sort(t, axis=1)
        rep = np.flatnonzero((s[:, 1:] == s[:, :-1]).any(axis=1))
        if rep.size:
            e = rep[0]
            raise MeshError(self._msg(
                f"tet {e} repeats a vertex (tet = {t[e].tolist()}); "
                f"{rep.size} tets with repeated vertices: {_fmt_list(rep)}"))

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

        # Degenerate (zero-volume) tets, scale-aware.
        self._vertices = x
        L = self._bbox_diagonal(x, t)
        vol = tet_volumes(x, t)
        thresh = DEGENERATE_RTOL * L**3
        degen = np.flatnonzero(np.abs(vol) <= thresh)
        if degen.size:
            raise MeshError(self._msg(
                f"{degen.size} degenerate (zero-volume) tets, |vol| <= {thresh:.3g} "
                f"(= {DEGENERATE_RTOL:g} * {L:.3g}^3): tets {_fmt_list(degen)}"))

        # Orientation.
        neg = np.flatnonzero(vol < 0)
        self.reoriented_tets = neg
        if neg.size:
            if not reorient:
                raise MeshError(self._msg(
                    f"{neg.size} negatively oriented tets: {_fmt_list(neg)}"))
            t = t.copy()
            t[neg, 2], t[neg, 3] = t[neg, 3].copy(), t[neg, 2].copy()
            vol[neg] = -vol[neg]
            warnings.warn(self._msg(
                f"reoriented {neg.size} of {t.shape[0]} negatively oriented tets "
                f"(swapped local vertices 2 and 3): {_fmt_list(neg)}"), stacklevel=2)

        x = np.array(x, dtype=np.float64, copy=True)
        t = np.array(t, dtype=np.int64, copy=True)
        vol = np.array(vol, copy=True)
        vmap = np.array(vmap, copy=True)
        for a in (x, t, vol, vmap):
            a.setflags(write=False)
        self._vertices = x
        self._tets = t
        self._volumes = vol
        self.vertex_map = vmap
        self._boundary = None

    # ------------------------------------------------------------------ helpers
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

    def _as_tets(self, tets):
        t = np.asarray(tets)
        if t.size == 0 and (t.ndim != 2 or t.shape[1] == 4 or t.shape == (0,)):
            raise MeshError(self._msg(f"mesh has no tets (tets shape {t.shape})"))
        if t.ndim != 2 or t.shape[1] != 4:
            raise MeshError(self._msg(f"tets must have shape (m, 4), got {t.shape}"))
        if t.dtype.kind in "iu":
            return t.astype(np.int64)
        if t.dtype.kind == "f":
            ti = np.rint(t)
            bad = np.flatnonzero((~np.isfinite(t) | (ti != t)).any(axis=1))
            if bad.size:
                raise MeshError(self._msg(
                    f"tet {bad[0]} has non-integer indices {t[bad[0]].tolist()}"))
            return ti.astype(np.int64)
        raise MeshError(self._msg(f"tets must be integers, got dtype {t.dtype}"))

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
    def tets(self):
        """(m, 4) int64 connectivity, positively oriented (read-only)."""
        return self._tets

    @property
    def elements(self):
        """Alias of ``tets`` (the element connectivity, k = 4 nodes per element)."""
        return self._tets

    @property
    def num_vertices(self):
        return int(self._vertices.shape[0])

    @property
    def num_tets(self):
        return int(self._tets.shape[0])

    @property
    def num_elements(self):
        return self.num_tets

    # ------------------------------------------------------------------ queries
    def rest_volumes(self):
        """Signed rest volumes 1/6 det[x1-x0, x2-x0, x3-x0], (m,) float64 (all > 0)."""
        return self._volumes

    def total_volume(self):
        return float(self._volumes.sum())

    def bounds(self):
        """(min, max) corners of the axis-aligned bounding box, each (3,) float64."""
        return self._vertices.min(axis=0), self._vertices.max(axis=0)

    def characteristic_length(self):
        """Bounding-box diagonal length."""
        lo, hi = self.bounds()
        return float(np.linalg.norm(hi - lo))

    def boundary_faces(self):
        """Faces used by exactly one tet, (k, 3) int64, right-hand-rule normal pointing outwards."""
        if self._boundary is None:
            f = boundary_faces(self._tets)
            f.setflags(write=False)
            self._boundary = f
        return self._boundary

    def boundary_vertices(self):
        """Sorted indices of vertices on the boundary surface."""
        return np.unique(self.boundary_faces())

    def quality(self):
        """Mean-ratio quality per tet: 12 (3|V|)^(2/3) / sum of squared edge lengths.

        1 for a regular tet, -> 0 for slivers / needles.
        """
        x = self._vertices[self._tets]
        pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
        l2 = sum(np.sum((x[:, i] - x[:, j]) ** 2, axis=1) for i, j in pairs)
        return 12.0 * (3.0 * np.abs(self._volumes)) ** (2.0 / 3.0) / l2

    def submesh(self, tets, *, name=None):
        """A new ``TetMesh`` from a subset of the tets (bool mask or indices), unused vertices
        removed; its ``vertex_map`` maps *this* mesh's vertex indices to the new ones (-1 dropped)
        and ``tet_map`` lists the parent tet of each new tet."""
        sel = np.asarray(tets)
        idx = np.flatnonzero(sel) if sel.dtype == bool else sel.astype(np.int64)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            sub = TetMesh(self._vertices, self._tets[idx], reorient=False,
                          remove_unreferenced=True, name=name if name is not None else self.name)
        sub.tet_map = idx
        return sub

    def __repr__(self):
        nm = f" {self.name!r}" if self.name else ""
        return f"TetMesh{nm}(num_vertices={self.num_vertices}, num_tets={self.num_tets})"
