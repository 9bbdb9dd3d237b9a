"""Splitting a tet mesh by an embedded triangle surface (e.g. a convex-hull tetrahedralisation
whose file also carries the object's surface triangles, like libigl's bunny.mesh)."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from scipy.sparse.csgraph import connected_components

from .volume_mesh import TET_FACES

__all__ = ["winding_number", "tet_components", "tets_inside_surface"]


def winding_number(points, vertices, triangles):
    """Generalised winding number of each point w.r.t. a triangle surface (Jacobson et al. 2013).

    ~1 inside a closed outward-oriented surface, ~0 outside (sign flips with orientation).
    """
    p = np.atleast_2d(np.asarray(points, dtype=np.float64))
    x = np.asarray(vertices, dtype=np.float64)
    t = np.asarray(triangles, dtype=np.int64)
    out = np.empty(len(p))
    for s in range(0, len(p), 256):
        q = p[s:s + 256, None, :]
        a, b, c = x[t[:, 0]] - q, x[t[:, 1]] - q, x[t[:, 2]] - q
        la, lb, lc = (np.linalg.norm(v, axis=-1) for v in (a, b, c))
        num = np.einsum("pti,pti->pt", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("pti,pti->pt", a, b) * lc
               + np.einsum("pti,pti->pt", b, c) * la + np.einsum("pti,pti->pt", c, a) * lb)
        out[s:s + 256] = (2.0 * np.arctan2(num, den)).sum(axis=1) / (4.0 * np.pi)
    return out


def tet_components(mesh, separating_triangles=None):
    """Label tets by face-connected component, not crossing ``separating_triangles``.

    Returns (num_components, labels (m,) int).
    """
    tets = mesh.tets
    m = len(tets)
    faces = np.sort(tets[:, TET_FACES].reshape(-1, 3), axis=1)
    owner = np.repeat(np.arange(m), 4)
    sep = np.zeros((0, 3), dtype=np.int64)
    if separating_triangles is not None and len(separating_triangles):
        sep = np.sort(np.asarray(separating_triangles, dtype=np.int64), axis=1)
    _, inv = np.unique(np.concatenate([faces, sep]), axis=0, return_inverse=True)
    inv = inv.ravel()
    fid = inv[: 4 * m]
    blocked = np.zeros(inv.max() + 1, dtype=bool)
    blocked[inv[4 * m:]] = True
    order = np.argsort(fid, kind="stable")
    fs, os_ = fid[order], owner[order]
    link = (fs[1:] == fs[:-1]) & ~blocked[fs[1:]]
    A = sp.coo_matrix((np.ones(int(link.sum())), (os_[:-1][link], os_[1:][link])), shape=(m, m))
    return connected_components(A, directed=False)


def tets_inside_surface(mesh, triangles):
    """Boolean mask of tets inside the closed surface ``triangles`` (indices into mesh vertices).

    Tets are grouped into components that do not cross the surface; each component is classified
    by the winding number at the centroid of its largest tet (orientation-independent: |w| > 1/2).
    """
    n, labels = tet_components(mesh, triangles)
    vol = mesh.rest_volumes()
    reps = np.empty(n, dtype=np.int64)
    order = np.lexsort((-vol, labels))  # by label, then largest volume first
    first = np.ones(len(order), dtype=bool)
    first[1:] = labels[order][1:] != labels[order][:-1]
    reps[labels[order][first]] = order[first]
    cent = mesh.vertices[mesh.tets[reps]].mean(axis=1)
    w = winding_number(cent, mesh.vertices, triangles)
    return (np.abs(w) > 0.5)[labels]
