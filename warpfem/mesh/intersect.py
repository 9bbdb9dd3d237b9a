"""Do closed surfaces cross or contain each other? (numpy + scipy; used to refuse overlapping bodies at t = 0).

:func:`first_body_overlap` checks every pair of bodies of a multi-body model: a pair whose bounding
boxes are apart costs nothing more; otherwise every boundary edge of each body near the other is
tested against the other's triangles near it (a k-d tree of triangle centres finds the candidates,
then an exact segment-triangle test, Moeller & Trumbore's "Fast, minimum storage ray-triangle
intersection", vectorised), and one vertex of each is tested for lying inside the other (the
generalised winding number, Jacobson, Kavan & Sorkine-Hornung, "Robust inside-outside
segmentation using generalized winding numbers"). Surfaces that only touch (coplanar faces, a
vertex on a face) are not reported: the tests are strict.
"""

from __future__ import annotations

import numpy as np

__all__ = ["BodyOverlapError", "SurfaceCrossing", "surface_crossing", "self_crossing", "winding_number",
           "first_body_overlap", "first_self_crossing"]


class BodyOverlapError(ValueError):
    """Two bodies intersect (or one is inside the other) at the start; the message names both and
    the first crossing."""


class SurfaceCrossing:
    """An edge of surface A through a triangle of surface B: ``edge`` (2 vertex indices of A),
    ``triangle`` (3 vertex indices of B), ``point`` (3,) where the edge crosses it, and the edge's
    end points ``edge_points`` (2, 3)."""

    def __init__(self, edge, triangle, point, edge_points, a_is_first=True):
        self.edge, self.triangle = tuple(int(i) for i in edge), tuple(int(i) for i in triangle)
        self.point, self.edge_points = np.asarray(point, dtype=np.float64), np.asarray(edge_points, dtype=np.float64)
        self.a_is_first = a_is_first  # the edge belongs to the first surface given

    def __repr__(self):
        return f"SurfaceCrossing(edge={self.edge}, triangle={self.triangle}, point={self.point.tolist()})"


def _edges(faces):
    f = np.asarray(faces, dtype=np.int64)
    e = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    return np.unique(e, axis=0)


def _fmt(p):
    return "(" + ", ".join(f"{c:.6g}" for c in np.asarray(p, dtype=np.float64)) + ")"


def _segment_hits(P0, P1, A, B, C, eps=1e-12):
    """Strict segment-triangle intersections of paired rows: (hit mask, parameter t along P0->P1)."""
    d = P1 - P0
    e1, e2 = B - A, C - A
    h = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, h)
    scale = np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1) * np.linalg.norm(d, axis=1)
    ok = np.abs(det) > eps * np.maximum(scale, np.finfo(np.float64).tiny)
    inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
    s = P0 - A
    u = inv * np.einsum("ij,ij->i", s, h)
    q = np.cross(s, e1)
    v = inv * np.einsum("ij,ij->i", d, q)
    t = inv * np.einsum("ij,ij->i", e2, q)
    tol = 1e-9
    # strictly inside the triangle and strictly between the segment's ends: touching (an edge on a face
    # or through a triangle's edge, a vertex on a face) is not a crossing; a crossing through exactly such
    # a point is found by the inside test of first_body_overlap
    hit = ok & (u > tol) & (v > tol) & (u + v < 1.0 - tol) & (t > tol) & (t < 1.0 - tol)
    return hit, t


def surface_crossing(points_a, faces_a, points_b, faces_b, *, chunk: int = 200_000, skip_shared: bool = False):
    """The first edge of surface A (in sorted edge order) that crosses a triangle of surface B, as
    a :class:`SurfaceCrossing` (vertex indices of each surface's own points), or None.
    ``skip_shared``: A and B index the same points (one surface against itself) and an edge is not
    tested against a triangle it shares a vertex with."""
    from scipy.spatial import cKDTree

    Pa, Pb = np.asarray(points_a, dtype=np.float64), np.asarray(points_b, dtype=np.float64)
    Fb = np.asarray(faces_b, dtype=np.int64)
    Ea = _edges(faces_a)
    if not len(Ea) or not len(Fb):
        return None
    lo = np.maximum(Pa.min(axis=0), Pb.min(axis=0))
    hi = np.minimum(Pa.max(axis=0), Pb.max(axis=0))
    if np.any(lo > hi):
        return None
    # only primitives whose boxes meet the boxes' overlap can cross
    ea0, ea1 = Pa[Ea[:, 0]], Pa[Ea[:, 1]]
    keep_e = np.all(np.minimum(ea0, ea1) <= hi, axis=1) & np.all(np.maximum(ea0, ea1) >= lo, axis=1)
    T = Pb[Fb]
    keep_f = np.all(T.min(axis=1) <= hi, axis=1) & np.all(T.max(axis=1) >= lo, axis=1)
    Ea, Fb, T = Ea[keep_e], Fb[keep_f], T[keep_f]
    if not len(Ea) or not len(Fb):
        return None
    centres = T.mean(axis=1)
    reach = float(np.linalg.norm(T - centres[:, None, :], axis=2).max())
    tree = cKDTree(centres)
    mids = 0.5 * (Pa[Ea[:, 0]] + Pa[Ea[:, 1]])
    half = 0.5 * np.linalg.norm(Pa[Ea[:, 1]] - Pa[Ea[:, 0]], axis=1)
    lists = tree.query_ball_point(mids, r=half + reach * (1.0 + 1e-9) + 1e-15)
    counts = np.fromiter((len(c) for c in lists), dtype=np.int64, count=len(lists))
    if not counts.sum():
        return None
    ei = np.repeat(np.arange(len(Ea)), counts)
    fi = np.fromiter((j for c in lists for j in c), dtype=np.int64, count=int(counts.sum()))
    if skip_shared:
        shared = np.zeros(len(ei), dtype=bool)
        for a_end in (0, 1):
            shared |= np.any(Fb[fi] == Ea[ei, a_end][:, None], axis=1)
        ei, fi = ei[~shared], fi[~shared]
    for a in range(0, len(ei), chunk):  # edges in order: the first hit is the first crossing edge
        e, f = ei[a:a + chunk], fi[a:a + chunk]
        p0, p1 = Pa[Ea[e, 0]], Pa[Ea[e, 1]]
        hit, t = _segment_hits(p0, p1, T[f, 0], T[f, 1], T[f, 2])
        if hit.any():
            k = int(np.nonzero(hit)[0][0])
            point = p0[k] + t[k] * (p1[k] - p0[k])
            return SurfaceCrossing(Ea[e[k]], Fb[f[k]], point, np.stack([p0[k], p1[k]]))
    return None


def self_crossing(points, faces, **kw):
    """The first edge of the surface (``points``, ``faces``) through one of its own triangles that
    does not share a vertex with it (:class:`SurfaceCrossing`; its ``triangle`` holds the three
    vertex indices and ``triangle_index`` the row of ``faces``), or None."""
    F = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    c = surface_crossing(points, F, points, F, skip_shared=True, **kw)
    if c is not None:
        hit = np.all(np.sort(F, axis=1) == np.sort(np.asarray(c.triangle))[None, :], axis=1)
        c.triangle_index = int(np.nonzero(hit)[0][0])
    return c


def winding_number(points, vertices, faces) -> np.ndarray:
    """Generalised winding number of the closed, outward-oriented triangle surface (``vertices``,
    ``faces``) at each of ``points`` (p, 3): about 1 inside, 0 outside."""
    V = np.asarray(vertices, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64)
    out = []
    for p in np.atleast_2d(np.asarray(points, dtype=np.float64)):
        a, b, c = V[F[:, 0]] - p, V[F[:, 1]] - p, V[F[:, 2]] - p
        la, lb, lc = (np.linalg.norm(x, axis=1) for x in (a, b, c))
        num = np.einsum("ij,ij->i", a, np.cross(b, c))
        den = la * lb * lc + np.einsum("ij,ij->i", a, b) * lc + np.einsum("ij,ij->i", b, c) * la \
            + np.einsum("ij,ij->i", c, a) * lb
        # a triangle whose plane holds the point (the point on it: touching) adds nothing, so a point on
        # the surface gets about 0.5 rather than the sign of round-off
        omega = np.where(np.abs(num) <= 1e-12 * la * lb * lc, 0.0, np.arctan2(num, den))
        out.append(omega.sum() / (2.0 * np.pi))
    return np.asarray(out)


def first_body_overlap(meshes, names):
    """A message naming the first pair of bodies (volume meshes with ``vertices`` and
    ``boundary_faces()``, in scene coordinates) whose surfaces cross, or one inside the other,
    with the first crossing: an edge of one through a triangle of the other (vertex indices of each
    body's own mesh, positions in m); '' when no two bodies overlap."""
    surf = []
    for m in meshes:
        V = np.asarray(m.vertices, dtype=np.float64)
        F = np.asarray(m.boundary_faces(), dtype=np.int64)
        surf.append((V, F, V.min(axis=0), V.max(axis=0)))
    for i in range(len(meshes)):
        for j in range(i + 1, len(meshes)):
            (Va, Fa, loa, hia), (Vb, Fb, lob, hib) = surf[i], surf[j]
            if np.any(np.maximum(loa, lob) > np.minimum(hia, hib)):
                continue  # boxes apart
            A, B = repr(names[i]), repr(names[j])
            for (Vp, Fp, P), (Vq, Fq, Q) in (((Va, Fa, A), (Vb, Fb, B)), ((Vb, Fb, B), (Va, Fa, A))):
                c = surface_crossing(Vp, Fp, Vq, Fq)
                if c is not None:
                    return (f"bodies {A} and {B} overlap at t = 0: edge {list(c.edge)} of {P} "
                            f"{_fmt(c.edge_points[0])} - {_fmt(c.edge_points[1])} crosses triangle {list(c.triangle)} "
                            f"of {Q} at {_fmt(c.point)} (vertex indices of each body's own mesh; move a body "
                            "with its offset)")
            for (Vp, Fp, P), (Vq, Fq, Q) in (((Va, Fa, A), (Vb, Fb, B)), ((Vb, Fb, B), (Va, Fa, A))):
                # no surface crossing: one body may still hold the other. Surface vertices of P in Q's box
                # (at most 64, spread over them) tested for lying inside Q (0.5 is on Q's surface: touching)
                ids = np.unique(Fp)
                lo, hi = Vq.min(axis=0), Vq.max(axis=0)
                surface_count = len(ids)
                ids = ids[np.all((Vp[ids] >= lo) & (Vp[ids] <= hi), axis=1)]
                some_outside = len(ids) < surface_count  # outside Q's box: outside Q
                ids = ids[np.linspace(0, len(ids) - 1, min(64, len(ids))).astype(np.int64)] if len(ids) else ids
                w = winding_number(Vp[ids], Vq, Fq) if len(ids) else np.zeros(0)
                inside = np.nonzero(np.abs(w) > 0.75)[0]
                if inside.size:
                    k = int(ids[inside[0]])
                    some_outside = some_outside or bool(np.any(np.abs(w) < 0.25))
                    how = (f"the surfaces cross (through edges or vertices of each other's triangles): vertex {k} of {P}"
                           if some_outside else f"{P} is inside {Q}: its vertex {k}")
                    return (f"bodies {A} and {B} overlap at t = 0: {how} at {_fmt(Vp[k])} is inside {Q} (winding number "
                            f"{float(w[inside[0]]):.3g} with respect to {Q}'s surface; vertex indices of each body's own "
                            "mesh; move a body with its offset)")
    return ""


def first_self_crossing(points, faces, body_offsets=None, names=None):
    """A message naming the first body whose surface passes through itself, with the first crossing:
    an edge of the body through one of its own triangles that shares no vertex with it (vertex
    indices of the body's own mesh, the triangle's row among the body's boundary triangles, the
    point in m); '' when none does. ``points`` (n, 3) and ``faces`` (m, 3) are global; a triangle
    belongs to the body of its first vertex (``body_offsets``: the first vertex of each body, then
    the total; default one body)."""
    P = np.asarray(points, dtype=np.float64)
    F = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    offsets = np.asarray([0, len(P)] if body_offsets is None or len(body_offsets) < 2 else body_offsets, dtype=np.int64)
    body_of = np.searchsorted(offsets, F[:, 0], side="right") - 1
    for b in range(len(offsets) - 1):
        Fb = F[body_of == b]
        if not len(Fb):
            continue
        c = self_crossing(P, Fb)
        if c is None:
            continue
        o = int(offsets[b])
        name = repr(names[b]) if names is not None and b < len(names) else f"#{b + 1}"
        return (f"body {name} passes through itself: its edge {[i - o for i in c.edge]} "
                f"{_fmt(c.edge_points[0])} - {_fmt(c.edge_points[1])} crosses its triangle {c.triangle_index} "
                f"{[i - o for i in c.triangle]} at {_fmt(c.point)} (vertex indices of the body's own mesh, the "
                "triangle's row among its boundary triangles)")
    return ""
