"""Point location in a tetrahedral mesh: which tet holds a point, and its barycentric coordinates.

Used to embed render-surface points in the simulation mesh (:mod:`warpfem.skinning`) and, on the
corner sub-tets of higher-order elements, to find a point's element (:func:`embed_points_in_elements`:
then Newton on the isoparametric map for the reference coordinates).

Each point X is attached to one tet t = (v0, v1, v2, v3) with barycentric coordinates
(w0, w1, w2, w3), sum w = 1, X = sum_a w_a X_{v_a}. The deformed point is x = sum_a w_a x_{v_a},
i.e. x_surface = W x with a sparse W (p x n, 4 non-zeros per row).

Points outside the volume attach to the nearest tet (smallest Euclidean distance to the solid
tet) with extrapolated coordinates (some w_a < 0); they still sum to 1, so affine motions of
the mesh are reproduced exactly.

Search: a KD-tree on tet centroids. A tet contains X only if |X - c_t| <= r_t (r_t = largest
centroid-to-vertex distance of tet t), so a ball query of radius max r_t gives every candidate.
The k nearest centroids are tried first (most points are resolved there); the ball query only
runs for the rest.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# scipy.sparse / scipy.spatial are imported by the functions that use them (~0.2 s at start-up)

__all__ = ["Embedding", "embed_points", "embed_points_in_elements", "barycentric_coordinates", "point_tet_distance",
           "INSIDE_TOL"]

# A point is inside a tet when its smallest barycentric coordinate is >= -INSIDE_TOL
# (barycentric coordinates are scale free, so the tolerance is relative).
INSIDE_TOL = 1e-10


@dataclass
class Embedding:
    """Result of :func:`embed_points`.

    Attributes
    ----------
    tet_index : (p,) int64, the tet each point is attached to.
    vertex_ids : (p, 4) int64, ``tets[tet_index]`` (the 4 mesh vertices each point depends on).
    weights : (p, 4) float64, barycentric coordinates (rows sum to 1; negative when outside).
    distances : (p,) float64, distance from each point to its tet (0 inside).
    outside : (p,) bool, points not inside any tet (within ``INSIDE_TOL``).
    num_vertices : number of mesh vertices n (columns of W).
    element_type : "tet4" (barycentric), or "tet10" / "hex8" / "hex27" from
        :func:`embed_points_in_mesh`: then ``tet_index`` is the element index, ``vertex_ids`` /
        ``weights`` are (p, k) with k the element's nodes and the weights its shape functions at
        the point (rows still sum to 1).
    """

    tet_index: np.ndarray
    vertex_ids: np.ndarray
    weights: np.ndarray
    distances: np.ndarray
    outside: np.ndarray
    num_vertices: int
    element_type: str = "tet4"

    @property
    def element_index(self) -> np.ndarray:
        """(p,) the element each point is attached to (= ``tet_index``)."""
        return self.tet_index

    @property
    def weights_per_point(self) -> int:
        """k, the stored entries per row of W (4 for tets, 10, 8, 27 for tet10, hex8, hex27)."""
        return int(np.shape(self.weights)[1])

    @property
    def num_points(self) -> int:
        return int(self.tet_index.shape[0])

    @property
    def num_outside(self) -> int:
        """Number of points outside the tet mesh (attached to their nearest tet)."""
        return int(np.count_nonzero(self.outside))

    @property
    def max_outside_distance(self) -> float:
        """Largest distance from an outside point to its tet (0.0 when all points are inside)."""
        if not np.any(self.outside):
            return 0.0
        return float(self.distances[self.outside].max())

    def matrix(self) -> scipy.sparse.csr_matrix:
        """The skinning matrix W (p x n, csr, k stored entries per row, rows sum to 1)."""
        import scipy.sparse

        p, k = self.num_points, self.weights_per_point
        indptr = np.arange(0, k * p + 1, k, dtype=np.int64)
        return scipy.sparse.csr_matrix(
            (self.weights.reshape(-1).copy(), self.vertex_ids.reshape(-1).copy(), indptr),
            shape=(p, self.num_vertices),
        )

    def apply(self, x: np.ndarray) -> np.ndarray:
        """x_surface = W x for mesh positions x (n, 3), in numpy (float64)."""
        x = np.asarray(x, dtype=np.float64)
        if x.ndim != 2 or x.shape != (self.num_vertices, 3):
            raise ValueError(f"positions must have shape ({self.num_vertices}, 3), got {x.shape}")
        return np.einsum("pa,pak->pk", self.weights, x[self.vertex_ids])


def _check_mesh(vertices, tets):
    if tets is None:  # a mesh object (warpfem.mesh.TetMesh or anything with .vertices / .tets)
        if not (hasattr(vertices, "vertices") and hasattr(vertices, "tets")):
            raise TypeError("pass (vertices, tets) arrays or a mesh object with .vertices and .tets")
        vertices, tets = vertices.vertices, vertices.tets
    vertices = np.asarray(vertices, dtype=np.float64)
    tets = np.asarray(tets)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must have shape (n, 3), got {vertices.shape}")
    if tets.ndim != 2 or tets.shape[1] != 4:
        raise ValueError(f"tets must have shape (m, 4), got {tets.shape}")
    if tets.shape[0] == 0:
        raise ValueError("tet mesh has no tets")
    if not np.issubdtype(tets.dtype, np.integer):
        raise ValueError(f"tets must be integers, got dtype {tets.dtype}")
    tets = tets.astype(np.int64)
    bad = np.nonzero((tets < 0) | (tets >= vertices.shape[0]))[0]
    if bad.size:
        raise ValueError(
            f"tet {bad[0]} references vertex out of range [0, {vertices.shape[0]}): {tets[bad[0]].tolist()}"
        )
    if not np.all(np.isfinite(vertices)):
        i = np.nonzero(~np.all(np.isfinite(vertices), axis=1))[0][0]
        raise ValueError(f"vertex {i} has a non-finite coordinate: {vertices[i].tolist()}")
    return vertices, tets


def _tet_frames(vertices, tets):
    """Per tet: X0 (m,3), inverse edge matrix Dm^-1 (m,3,3), valid mask (non-degenerate)."""
    X = vertices[tets]  # (m,4,3)
    Dm = np.stack([X[:, 1] - X[:, 0], X[:, 2] - X[:, 0], X[:, 3] - X[:, 0]], axis=2)  # columns
    det = np.linalg.det(Dm)
    scale = np.max(np.linalg.norm(Dm, axis=1), axis=1)  # longest edge from X0
    valid = np.abs(det) > 1e-14 * np.maximum(scale, 1e-300) ** 3
    Dinv = np.zeros_like(Dm)
    if np.any(valid):
        Dinv[valid] = np.linalg.inv(Dm[valid])
    return X[:, 0].copy(), Dinv, valid


def barycentric_coordinates(points, vertices, tets, tet_index) -> np.ndarray:
    """Barycentric coordinates (p, 4) of points w.r.t. tets[tet_index] (extrapolated outside)."""
    vertices, tets = _check_mesh(vertices, tets)
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    tet_index = np.asarray(tet_index, dtype=np.int64)
    if tet_index.shape != (points.shape[0],):
        raise ValueError(f"tet_index must have shape ({points.shape[0]},), got {tet_index.shape}")
    X0, Dinv, valid = _tet_frames(vertices, tets)
    if not np.all(valid[tet_index]):
        raise ValueError("barycentric coordinates requested for a degenerate (zero volume) tet")
    return _bary(points, X0[tet_index], Dinv[tet_index])


def _bary(points, X0, Dinv):
    b = np.einsum("pij,pj->pi", Dinv, points - X0)
    return np.concatenate([1.0 - b.sum(axis=1, keepdims=True), b], axis=1)


def _closest_on_triangles(p, a, b, c):
    """Closest points on triangles (a, b, c) to points p, all (k,3). Ericson, RTCD 5.1.5."""
    ab = b - a
    ac = c - a
    ap = p - a
    d1 = np.einsum("ij,ij->i", ab, ap)
    d2 = np.einsum("ij,ij->i", ac, ap)
    bp = p - b
    d3 = np.einsum("ij,ij->i", ab, bp)
    d4 = np.einsum("ij,ij->i", ac, bp)
    cp = p - c
    d5 = np.einsum("ij,ij->i", ab, cp)
    d6 = np.einsum("ij,ij->i", ac, cp)

    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2

    out = np.empty_like(p)
    done = np.zeros(p.shape[0], dtype=bool)

    def assign(mask, value):
        nonlocal done
        m = mask & ~done
        out[m] = value[m] if value.ndim == 2 else value
        done |= m

    with np.errstate(divide="ignore", invalid="ignore"):
        # vertex regions
        assign((d1 <= 0) & (d2 <= 0), a)
        assign((d3 >= 0) & (d4 <= d3), b)
        assign((d6 >= 0) & (d5 <= d6), c)
        # edge regions
        v = d1 / (d1 - d3)
        assign((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + v[:, None] * ab)
        w = d2 / (d2 - d6)
        assign((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + w[:, None] * ac)
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        assign((va <= 0) & ((d4 - d3) >= 0) & ((d5 - d6) >= 0), b + w[:, None] * (c - b))
        # face region
        denom = 1.0 / (va + vb + vc)
        v = vb * denom
        w = vc * denom
        assign(np.ones_like(done), a + ab * v[:, None] + ac * w[:, None])
    # degenerate triangles can produce NaN in the face region: fall back to the nearest vertex
    bad = ~np.all(np.isfinite(out), axis=1)
    if np.any(bad):
        cand = np.stack([a[bad], b[bad], c[bad]], axis=1)
        k = np.argmin(np.linalg.norm(cand - p[bad, None, :], axis=2), axis=1)
        out[bad] = cand[np.arange(cand.shape[0]), k]
    return out


_TET_FACES = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])


def point_tet_distance(points, tet_vertices, weights=None) -> np.ndarray:
    """Distance from points (k,3) to solid tets given by their corners (k,4,3).

    ``weights`` (k,4), the barycentric coordinates, lets inside points skip the face search.
    """
    points = np.asarray(points, dtype=np.float64)
    k = points.shape[0]
    dist = np.full(k, np.inf)
    for f in _TET_FACES:
        q = _closest_on_triangles(points, tet_vertices[:, f[0]], tet_vertices[:, f[1]], tet_vertices[:, f[2]])
        dist = np.minimum(dist, np.linalg.norm(points - q, axis=1))
    if weights is not None:
        dist[np.min(weights, axis=1) >= 0.0] = 0.0
    return dist


def _pick_best(pi, score, num_points, maximize=True):
    """For pairs (point pi, score), index of the best pair per point (or -1 when a point has none)."""
    best = np.full(num_points, -1, dtype=np.int64)
    if pi.size == 0:
        return best
    key = -score if maximize else score
    order = np.lexsort((key, pi))
    first = np.ones(order.size, dtype=bool)
    first[1:] = pi[order[1:]] != pi[order[:-1]]
    best[pi[order[first]]] = order[first]
    return best


class _TetSearch:
    """Ball queries on tet bounding spheres (centroid c_t, radius r_t).

    Tets are bucketed by radius (factor 2 per bucket), one KD-tree per bucket, so a few huge
    sliver tets do not inflate the query radius for all others.
    """

    def __init__(self, centroids, radii):
        self.centroids = centroids
        self.radii = radii
        from scipy.spatial import cKDTree

        r_min = max(float(radii.min()), 1e-300)
        level = np.floor(np.log2(np.maximum(radii, r_min) / r_min)).astype(np.int64)
        self.buckets = []
        for lv in np.unique(level):
            ids = np.nonzero(level == lv)[0]
            self.buckets.append((ids, cKDTree(centroids[ids]), float(radii[ids].max())))

    def pairs(self, pts, extra, idx):
        """(point index, tet index) pairs with |p - c_t| <= extra + r_t (extra: scalar or per point)."""
        extra = np.broadcast_to(np.asarray(extra, dtype=np.float64), (pts.shape[0],))
        out_p, out_t = [], []
        for ids, tree, rmax in self.buckets:
            lists = tree.query_ball_point(pts, extra + rmax, return_sorted=False)
            counts = np.fromiter((len(l) for l in lists), dtype=np.int64, count=len(lists))
            total = int(counts.sum())
            if total == 0:
                continue
            pl = np.repeat(np.arange(pts.shape[0]), counts)
            tl = ids[np.concatenate([np.asarray(l, dtype=np.int64) for l in lists if len(l)])]
            keep = np.linalg.norm(pts[pl] - self.centroids[tl], axis=1) <= (extra[pl] + self.radii[tl]) * (1 + 1e-12)
            out_p.append(idx[pl[keep]])
            out_t.append(tl[keep])
        if not out_p:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        return np.concatenate(out_p), np.concatenate(out_t)


def embed_points(points, vertices, tets=None, *, k_nearest: int = 12) -> Embedding:
    """Embed points (p,3) into the tet mesh (vertices (n,3), tets (m,4)), or a Tet4 mesh as
    ``embed_points(points, mesh)``.

    Each point gets the tet containing it (if several contain it, the one where it is most
    interior) and its barycentric coordinates. A point in no tet attaches to the nearest tet
    (Euclidean distance to the solid tet) with extrapolated barycentric coordinates; its
    distance is stored in ``Embedding.distances`` and summarised by ``max_outside_distance``.
    Degenerate (zero-volume) tets are never chosen. Tet orientation does not matter.
    """
    vertices, tets = _check_mesh(vertices, tets)
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (p, 3), got {points.shape}")
    if not np.all(np.isfinite(points)):
        i = np.nonzero(~np.all(np.isfinite(points), axis=1))[0][0]
        raise ValueError(f"point {i} has a non-finite coordinate: {points[i].tolist()}")
    p = points.shape[0]
    n = vertices.shape[0]

    X0_all, Dinv_all, valid = _tet_frames(vertices, tets)
    if not np.any(valid):
        raise ValueError("every tet of the mesh is degenerate (zero volume)")
    tet_ids = np.nonzero(valid)[0]  # search only non-degenerate tets
    X = vertices[tets[tet_ids]]
    X0, Dinv = X0_all[tet_ids], Dinv_all[tet_ids]
    centroids = X.mean(axis=1)
    radii = np.linalg.norm(X - centroids[:, None, :], axis=2).max(axis=1)
    from scipy.spatial import cKDTree

    tree = cKDTree(centroids)
    search = _TetSearch(centroids, radii)

    chosen = np.full(p, -1, dtype=np.int64)  # index into tet_ids
    chosen_w = np.zeros((p, 4))
    if p == 0:
        return Embedding(np.zeros(0, np.int64), np.zeros((0, 4), np.int64), np.zeros((0, 4)),
                         np.zeros(0), np.zeros(0, bool), n)

    # 1) k nearest centroids
    k = min(k_nearest, tet_ids.size)
    _, knn = tree.query(points, k=k)
    knn = knn.reshape(p, k)
    pi = np.repeat(np.arange(p), k)
    ti = knn.reshape(-1)
    w = _bary(points[pi], X0[ti], Dinv[ti])
    score = w.min(axis=1)
    best = _pick_best(pi, score, p)
    inside = score[best] >= -INSIDE_TOL
    chosen[inside] = ti[best[inside]]
    chosen_w[inside] = w[best[inside]]

    # 2) bounding-sphere query: every tet that can contain the point
    rest = np.nonzero(~inside)[0]
    if rest.size:
        pi2, ti2 = search.pairs(points[rest], 0.0, rest)
        w2 = _bary(points[pi2], X0[ti2], Dinv[ti2])
        s2 = w2.min(axis=1)
        b2 = _pick_best(pi2, s2, p)
        b2r = b2[rest]
        ok = (b2r >= 0)
        ok[ok] = s2[b2r[ok]] >= -INSIDE_TOL
        got = rest[ok]
        chosen[got] = ti2[b2r[ok]]
        chosen_w[got] = w2[b2r[ok]]
        inside[got] = True

    distances = np.zeros(p)
    # 3) outside points: nearest tet by distance
    out_idx = np.nonzero(~inside)[0]
    if out_idx.size:
        # upper bound from the k-nearest candidates
        po = np.repeat(out_idx, k)
        to = knn[out_idx].reshape(-1)
        d_knn = point_tet_distance(points[po], X[to]).reshape(out_idx.size, k)
        ub = d_knn.min(axis=1)
        # every tet within distance ub has its centroid within ub + r_t <= ub + r_max
        pi3, ti3 = search.pairs(points[out_idx], ub * (1 + 1e-9), out_idx)
        d3 = point_tet_distance(points[pi3], X[ti3])
        w3 = _bary(points[pi3], X0[ti3], Dinv[ti3])
        b3 = _pick_best(pi3, d3, p, maximize=False)  # nearest tet
        sel = b3[out_idx]
        chosen[out_idx] = ti3[sel]
        chosen_w[out_idx] = w3[sel]
        distances[out_idx] = d3[sel]

    tet_index = tet_ids[chosen]
    return Embedding(
        tet_index=tet_index,
        vertex_ids=tets[tet_index],
        weights=chosen_w,
        distances=distances,
        outside=~inside,
        num_vertices=n,
    )


def embed_points_in_elements(points, mesh, *, max_newton_iters: int = 30, corner_embedding=None):
    """Embed points (p, 3) in a mesh of any element type: x(point) = sum_a w_a x_{ids_a}.

    Returns ``(ids (p, k) int64, weights (p, k) float64, element (p,) int64)``: the element's
    nodes and its shape functions at the point's reference coordinates (rows sum to 1). The
    element is found on the corner tets (:func:`embed_points`, nearest for outside points);
    reference coordinates: barycentric on the corner tet, then (unless the element is a linear tet,
    ``element.is_linear_tet``) refined by Newton on the isoparametric map X(xi) = sum_a N_a(xi) X_a
    (the inverse map of hexes and curved Tet10). A point outside the mesh keeps extrapolated
    coordinates (weights may be negative).
    ``corner_embedding``: the result of ``embed_points(points, mesh.vertices, mesh.corner_tets())``
    when the caller already has it (the search is then not repeated).
    """
    from .element_types import get_element

    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"points must have shape (p, 3), got {points.shape}")
    if not np.all(np.isfinite(points)):
        i = int(np.flatnonzero(~np.isfinite(points).all(axis=1))[0])
        raise ValueError(f"point {i} has a non-finite coordinate: {points[i].tolist()}")
    element = get_element(mesh.element_type)
    elements = np.asarray(mesh.elements, dtype=np.int64)
    X = np.asarray(mesh.vertices, dtype=np.float64)
    corner = elements[:, element.corner_tets].reshape(-1, 4)
    emb = corner_embedding if corner_embedding is not None else embed_points(points, X, corner)
    s = len(corner) // len(elements)
    elem = emb.tet_index // s
    # initial reference coordinates: barycentric interpolation of the corner tet's reference nodes
    ref_tet = element.reference_nodes[element.corner_tets[emb.tet_index % s]]  # (p, 4, 3)
    xi = np.einsum("pa,pai->pi", emb.weights, ref_tet)
    if not element.is_linear_tet:
        Xe = X[elements[elem]]  # (p, k, 3)
        scale = np.linalg.norm(Xe.max(axis=1) - Xe.min(axis=1), axis=1)
        for _ in range(int(max_newton_iters)):
            N, dN = element.shape(xi)
            r = points - np.einsum("pa,pai->pi", N, Xe)
            if np.all(np.linalg.norm(r, axis=1) <= 1e-13 * scale):
                break
            J = np.einsum("pai,paj->pij", Xe, dN)
            xi = xi + np.linalg.solve(J, r[:, :, None])[:, :, 0]
        else:
            r = points - np.einsum("pa,pai->pi", element.shape_functions(xi), Xe)
            bad = np.flatnonzero(np.linalg.norm(r, axis=1) > 1e-8 * scale)
            if bad.size:
                import warnings

                warnings.warn(f"inverse isoparametric map did not converge for {bad.size} point(s) (first: point "
                              f"{int(bad[0])} in element {int(elem[bad[0]])}); their weights are approximate",
                              RuntimeWarning, stacklevel=2)
    weights = element.shape_functions(xi)
    return elements[elem], weights, elem
