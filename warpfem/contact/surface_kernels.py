"""Warp kernels of surface contact: point-triangle and edge-edge pairs of the body surfaces.

Used by :mod:`warpfem.contact.surface` (body-body and self-contact; docs/contact.md). One module,
four kernels, float32 and float64 overloads:

* ``boxes_kernel``: the axis-aligned box of each primitive (vertex, edge, triangle) over the
  segment x -> x + scale dx, padded, in float32 (what ``wp.Bvh`` takes);
* ``broad_phase_kernel``: per surface vertex a ``wp.bvh_query_aabb`` of the triangles' BVH, per
  surface edge one of the edges' BVH; candidate (vertex, triangle) and (edge, edge) pairs that are
  not neighbours (a vertex of the triangle, edges sharing a vertex) and that the body filter keeps
  (same group: ``self``; different groups: ``bodies``) are appended to the pair list;
* ``pair_kernel``: per candidate pair, by ``mode``: barrier energy, gradient, SPD-projected
  Hessian (12 x 12 per pair, cyclic Jacobi eigen-projection, added into the 16 vertex blocks),
  the additive continuous-collision step bound, the distance, and the friction lagging;
* ``friction_kernel``: lagged smoothed friction of the pairs that were in contact at the start
  of the step (energy, gradient, Hessian blocks).

Distances are the unsigned Euclidean distances between the closest features (point-point,
point-edge, point-plane; edge-edge with its point-edge and point-point sub-cases). Every case is
written as one vector r = sum_i w_i(beta) x_i over the pair's four vertices, with w affine in the
k free parameters beta of the feature (k = 0, 1, 2) at the closest point; the squared distance
s = |r|^2 then has gradient 2 w_i r and the exact Hessian (implicit function theorem at the
optimal beta)

    d2s/dx_i dx_j = 2 w_i w_j I - sum_kl B_ik (G^-1)_kl B_jl^T,
    B_ik = 2 (dw_i/dbeta_k r + w_i J_k),  J_k = dr/dbeta_k,  G = 2 J^T J.

Barrier (Li et al. 2020, "Incremental Potential Contact"), on squared distances:
kappa b(s, dhat^2), b(s, t) = -(s - t)^2 ln(s / t) for s < t (0 beyond). Edge-edge pairs are
multiplied by the mollifier m(c) = (2 - c / eps_x) c / eps_x for c < eps_x (1 beyond),
c = |(a1 - a0) x (b1 - b0)|^2, eps_x = 1e-3 |A1 - A0|^2 |B1 - B0|^2 at rest (same paper), which
makes the energy smooth where edges become parallel.

Step bound: additive CCD (Li, Kaufman & Jiang 2021, "Codimensional Incremental Potential
Contact"): per pair, with the common translation of its four displacements removed and l the sum
of the two primitives' largest displacements, advance by t_l = (1 - eta) d / l, then by
0.9 d(t) / l, until the gap falls under eta d(0); each advance is below the distance over the
relative speed bound, so the pair never touches on [0, t].
"""

from __future__ import annotations

from typing import Any

import warp as wp

from warpfem.contact.kernels import barrier, friction_f0
from warpfem.kernels.generic import both_precisions, splittable

wp.set_module_options({"enable_backward": False, "max_unroll": 1})

MODE_ENERGY, MODE_GRADIENT, MODE_HESSIAN, MODE_MAX_STEP, MODE_DISTANCE, MODE_LAG = 0, 1, 2, 3, 4, 5
MODE_HESSIAN_UNPROJECTED = 6  # tests: the exact Hessian
PT, EE = 0, 1
ACCD_MAX_ITERS = 100

mat12f = wp.types.matrix(shape=(12, 12), dtype=wp.float32)
mat12d = wp.types.matrix(shape=(12, 12), dtype=wp.float64)
mat9f = wp.types.matrix(shape=(9, 9), dtype=wp.float32)
mat9d = wp.types.matrix(shape=(9, 9), dtype=wp.float64)


@wp.func
def _pe_param(p: Any, a: Any, b: Any):
    """Parameter t in [0, 1] of the closest point a + t (b - a) of segment ab to p, and |r|^2."""
    e = b - a
    zero = e[0] - e[0]
    one = zero + type(zero)(1.0)
    ee = wp.dot(e, e)
    t = zero
    if ee > zero:
        t = wp.clamp(wp.dot(p - a, e) / ee, zero, one)
    r = p - a - t * e
    return t, wp.dot(r, r)


@wp.func
def pt_features(p: Any, a: Any, b: Any, c: Any):
    """Closest feature of point p to triangle abc: weights w (r = w . x), dw/dbeta (two columns)
    and the number k of free parameters."""
    zero = p[0] - p[0]
    one = zero + type(zero)(1.0)
    w = wp.vector(one, zero, zero, zero)
    c0 = wp.vector(zero, zero, zero, zero)
    c1 = wp.vector(zero, zero, zero, zero)
    ab = b - a
    ac = c - a
    ap = p - a
    d00 = wp.dot(ab, ab)
    d01 = wp.dot(ab, ac)
    d11 = wp.dot(ac, ac)
    e0 = wp.dot(ab, ap)
    e1 = wp.dot(ac, ap)
    den = d00 * d11 - d01 * d01
    if den > type(zero)(1e-12) * d00 * d11:
        u = (d11 * e0 - d01 * e1) / den
        v = (d00 * e1 - d01 * e0) / den
        if u >= zero and v >= zero and u + v <= one:
            w[1] = -(one - u - v)
            w[2] = -u
            w[3] = -v
            c0[1] = one
            c0[2] = -one
            c1[1] = one
            c1[3] = -one
            return w, c0, c1, 2
    # outside (or degenerate): the closest point is on an edge (ab: 1-2, bc: 2-3, ca: 3-1)
    t, best = _pe_param(p, a, b)
    i0 = int(1)
    i1 = int(2)
    t2, s2 = _pe_param(p, b, c)
    if s2 < best:
        best = s2
        t = t2
        i0 = 2
        i1 = 3
    t3, s3 = _pe_param(p, c, a)
    if s3 < best:
        best = s3
        t = t3
        i0 = 3
        i1 = 1
    if t <= zero:
        w[i0] = -one
        return w, c0, c1, 0
    if t >= one:
        w[i1] = -one
        return w, c0, c1, 0
    w[i0] = -(one - t)
    w[i1] = -t
    c0[i0] = one
    c0[i1] = -one
    return w, c0, c1, 1


@wp.func
def ee_features(a0: Any, a1: Any, b0: Any, b1: Any):
    """Closest features of segments a0a1 and b0b1 (r = (a0 + s da) - (b0 + t db))."""
    zero = a0[0] - a0[0]
    one = zero + type(zero)(1.0)
    d1 = a1 - a0
    d2 = b1 - b0
    r0 = a0 - b0
    A = wp.dot(d1, d1)
    E = wp.dot(d2, d2)
    F = wp.dot(d2, r0)
    C = wp.dot(d1, r0)
    B = wp.dot(d1, d2)
    den = A * E - B * B
    s = zero
    if den > type(zero)(1e-10) * A * E:
        s = wp.clamp((B * F - C * E) / den, zero, one)
    t = (B * s + F) / E
    if t < zero:
        t = zero
        s = wp.clamp(-C / A, zero, one)
    elif t > one:
        t = one
        s = wp.clamp((B - C) / A, zero, one)
    w = wp.vector(one - s, s, -(one - t), -t)
    c0 = wp.vector(zero, zero, zero, zero)
    c1 = wp.vector(zero, zero, zero, zero)
    sfree = s > zero and s < one
    tfree = t > zero and t < one
    k = int(0)
    if sfree and tfree:
        c0 = wp.vector(-one, one, zero, zero)
        c1 = wp.vector(zero, zero, one, -one)
        k = 2
    elif sfree:
        c0 = wp.vector(-one, one, zero, zero)
        k = 1
    elif tfree:
        c0 = wp.vector(zero, zero, one, -one)
        k = 1
    return w, c0, c1, k


@wp.func
def pair_features(kind: int, x0: Any, x1: Any, x2: Any, x3: Any):
    if kind == 0:
        return pt_features(x0, x1, x2, x3)
    return ee_features(x0, x1, x2, x3)


@wp.func
def pair_r(w: Any, x0: Any, x1: Any, x2: Any, x3: Any):
    return w[0] * x0 + w[1] * x1 + w[2] * x2 + w[3] * x3


@wp.func
def pair_distance(kind: int, x0: Any, x1: Any, x2: Any, x3: Any):
    w, c0, c1, k = pair_features(kind, x0, x1, x2, x3)
    return wp.length(pair_r(w, x0, x1, x2, x3))


@wp.func
def mollifier(c: Any, eps: Any):
    """(m, m', m'') of m(c) = (2 - c / eps) c / eps for c < eps, 1 beyond."""
    one = eps / eps
    zero = one - one
    if c >= eps:
        return one, zero, zero
    q = c / eps
    two = one + one
    return (two - q) * q, (two - two * q) / eps, -two / (eps * eps)


@wp.func
def _empty12(z: wp.float32):
    return mat12f()


@wp.func
def _empty12(z: wp.float64):
    return mat12d()


@wp.func
def _empty9(z: wp.float32):
    return mat9f()


@wp.func
def _empty9(z: wp.float64):
    return mat9d()


@wp.func
def _pick(i: int, a: Any, b: Any, c: Any, d: Any):
    if i == 0:
        return a
    if i == 1:
        return b
    if i == 2:
        return c
    return d


@wp.func
def _hc_block(i: int, j: int, u: Any, v: Any, one: Any):
    """Block (i, j) of the Hessian of c = |u|^2 |v|^2 - (u.v)^2 over the edge-edge pair's
    vertices (u = x1 - x0, v = x3 - x2)."""
    two = one + one
    I3 = wp.identity(3, type(one))
    si = -one
    if i == 1 or i == 3:
        si = one
    sj = -one
    if j == 1 or j == 3:
        sj = one
    uv = wp.dot(u, v)
    M = I3
    if i < 2 and j < 2:
        M = two * wp.dot(v, v) * I3 - two * wp.outer(v, v)
    elif i >= 2 and j >= 2:
        M = two * wp.dot(u, u) * I3 - two * wp.outer(u, u)
    elif i < 2:
        M = two * two * wp.outer(u, v) - two * wp.outer(v, u) - two * uv * I3
    else:
        M = two * two * wp.outer(v, u) - two * wp.outer(u, v) - two * uv * I3
    return (si * sj) * M


@wp.func
def add_block(H: Any, i: int, j: int, M: Any):
    for a in range(3):
        for b in range(3):
            H[3 * i + a, 3 * j + b] = H[3 * i + a, 3 * j + b] + M[a, b]
    return H


@wp.func
def psd_project(A: Any, n: int, tol: Any):
    """The projection of the symmetric n x n matrix A onto the PSD cone (cyclic Jacobi
    eigen-decomposition until the off-diagonal part's squared norm is below tol x |A|^2,
    negative eigenvalues set to 0)."""
    zero = A[0, 0] - A[0, 0]
    one = zero + type(zero)(1.0)
    two = one + one
    V = A - A
    scale = zero
    for i in range(n):
        V[i, i] = one
        for j in range(n):
            scale = scale + A[i, j] * A[i, j]
    for sweep in range(16):
        off = zero
        for p in range(n):
            for q in range(p + 1, n):
                off = off + A[p, q] * A[p, q]
        if off <= tol * scale:
            break
        for p in range(n):
            for q in range(p + 1, n):
                apq = A[p, q]
                if wp.abs(apq) > zero:
                    theta = (A[q, q] - A[p, p]) / (two * apq)
                    t = one / (wp.abs(theta) + wp.sqrt(theta * theta + one))
                    if theta < zero:
                        t = -t
                    c = one / wp.sqrt(t * t + one)
                    s = t * c
                    for k in range(n):
                        akp = A[k, p]
                        akq = A[k, q]
                        A[k, p] = c * akp - s * akq
                        A[k, q] = s * akp + c * akq
                    for k in range(n):
                        apk = A[p, k]
                        aqk = A[q, k]
                        A[p, k] = c * apk - s * aqk
                        A[q, k] = s * apk + c * aqk
                    for k in range(n):
                        vkp = V[k, p]
                        vkq = V[k, q]
                        V[k, p] = c * vkp - s * vkq
                        V[k, q] = s * vkp + c * vkq
    R = A - A
    for k in range(n):
        lam = A[k, k]
        if lam > zero:
            for i in range(n):
                for j in range(n):
                    R[i, j] = R[i, j] + lam * V[i, k] * V[j, k]
    return R


@wp.func
def _gram_schmidt(a: Any, b: Any, c: Any):
    """Orthonormal rows spanning the (independent) 4-vectors a, b, c."""
    q0 = wp.normalize(a)
    b1 = b - wp.dot(b, q0) * q0
    q1 = wp.normalize(b1)
    c1 = c - wp.dot(c, q0) * q0
    c1 = c1 - wp.dot(c1, q1) * q1
    q2 = wp.normalize(c1)
    return q0, q1, q2


@wp.func
def _qrow(q0: Any, q1: Any, q2: Any, al: int):
    if al == 0:
        return q0
    if al == 1:
        return q1
    return q2


@wp.func
def psd_project_pair(H: Any, kind: int, w: Any, tol: Any):
    """PSD projection of a pair's 12 x 12 Hessian, whose rows and columns lie in span{w, e, f} x
    R^3 (w the closest-point weights; e, f the two edge patterns of the triangle or of the two
    edges, which span the dw/dbeta of every feature and the mollifier's vertex patterns): the
    9 x 9 matrix in an orthonormal basis of that span is projected (same eigenvalues, about 2.4x
    fewer operations than the 12 x 12 one)."""
    zero = w[0] - w[0]
    one = zero + type(zero)(1.0)
    e = wp.vector(zero, one, -one, zero)
    f = wp.vector(zero, one, zero, -one)
    if kind == 1:
        e = wp.vector(-one, one, zero, zero)
        f = wp.vector(zero, zero, -one, one)
    q0, q1, q2 = _gram_schmidt(w, e, f)
    M = _empty9(zero)
    for al in range(3):
        qa = _qrow(q0, q1, q2, al)
        for be in range(3):
            qb = _qrow(q0, q1, q2, be)
            for a in range(3):
                for b in range(3):
                    acc = zero
                    for i in range(4):
                        for j in range(4):
                            acc = acc + qa[i] * qb[j] * H[3 * i + a, 3 * j + b]
                    M[3 * al + a, 3 * be + b] = acc
    M = psd_project(M, 9, tol)
    R = H - H
    for i in range(4):
        for j in range(4):
            for a in range(3):
                for b in range(3):
                    acc = zero
                    for al in range(3):
                        qa = _qrow(q0, q1, q2, al)
                        for be in range(3):
                            qb = _qrow(q0, q1, q2, be)
                            acc = acc + qa[i] * qb[j] * M[3 * al + a, 3 * be + b]
                    R[3 * i + a, 3 * j + b] = acc
    return R


@wp.func
def _swept_box(x: wp.array(dtype=Any), dx: wp.array(dtype=Any), scale: Any, prims: wp.array(dtype=wp.int32), k: int,
               i: int):
    """(lower, upper, largest |coordinate|) of primitive i's vertices over x -> x + scale dx."""
    v = prims[k * i]
    lo = x[v]
    hi = x[v]
    for j in range(k):
        u = prims[k * i + j]
        p = x[u]
        q = p + scale * dx[u]
        lo = wp.min(lo, wp.min(p, q))
        hi = wp.max(hi, wp.max(p, q))
    m = wp.max(wp.max(wp.abs(lo[0]), wp.abs(lo[1])), wp.max(wp.abs(lo[2]), wp.max(wp.abs(hi[0]), wp.max(wp.abs(hi[1]), wp.abs(hi[2])))))
    return lo, hi, m


@both_precisions(x="v[]", dx="v[]", scale="s", pad="s")
@wp.kernel
def boxes_kernel(x: wp.array(dtype=Any), dx: wp.array(dtype=Any), scale: Any, prims: wp.array(dtype=wp.int32),
                 k: int, pad: Any, lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3)):
    """Box of primitive i (vertices prims[k i : k i + k]) over x -> x + scale dx, padded by pad
    (and by a float32 rounding margin)."""
    i = wp.tid()
    lo, hi, m = _swept_box(x, dx, scale, prims, k, i)
    r = wp.float32(pad) + wp.float32(1e-6) * wp.float32(m)
    lowers[i] = wp.vec3(wp.float32(lo[0]) - r, wp.float32(lo[1]) - r, wp.float32(lo[2]) - r)
    uppers[i] = wp.vec3(wp.float32(hi[0]) + r, wp.float32(hi[1]) + r, wp.float32(hi[2]) + r)


@both_precisions(x="v[]", dx="v[]", scale="s", pad="s")
@wp.kernel
def boxes_fit_kernel(x: wp.array(dtype=Any), dx: wp.array(dtype=Any), scale: Any, prims: wp.array(dtype=wp.int32),
                     k: int, pad: Any, lowers: wp.array(dtype=wp.vec3), uppers: wp.array(dtype=wp.vec3),
                     misses: wp.array(dtype=wp.int32)):
    """misses[0] += 1 for each primitive whose box over x -> x + scale dx, padded by pad, is not
    inside its box of the last query (then the candidate pairs of that query may miss a pair)."""
    i = wp.tid()
    lo, hi, m = _swept_box(x, dx, scale, prims, k, i)
    r = wp.float32(pad) + wp.float32(2e-6) * wp.float32(m)
    L = lowers[i]
    U = uppers[i]
    out = int(0)
    for a in range(3):
        if wp.float32(lo[a]) - r < L[a] or wp.float32(hi[a]) + r > U[a]:
            out = out + 1
    if out > 0:
        wp.atomic_add(misses, 0, 1)


@wp.func
def _keep(group: wp.array(dtype=wp.int32), a: int, b: int, self_on: int, bodies_on: int):
    if group[a] == group[b]:
        return self_on != 0
    return bodies_on != 0


@wp.func
def _append(pairs: wp.array(dtype=wp.vec4i), kinds: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
            capacity: int, q: wp.vec4i, kind: int):
    slot = wp.atomic_add(count, 0, 1)
    if slot < capacity:
        pairs[slot] = q
        kinds[slot] = kind


@wp.func
def _sort_pair(kind: int, q: wp.vec4i, group: wp.array(dtype=wp.int32), rest: wp.array(dtype=wp.vec3), rest_gap: float,
               pairs: wp.array(dtype=wp.vec4i), kinds: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
               capacity: int, ccd_pairs: wp.array(dtype=wp.vec4i), ccd_kinds: wp.array(dtype=wp.int32),
               ccd_count: wp.array(dtype=wp.int32), ccd_capacity: int):
    """A candidate ``q`` of ``kind`` (0 point-triangle: q[0] the point; 1 edge-edge: q[0], q[2] the
    edges' first ends) into the barrier list, or, for a self pair closer than ``rest_gap`` in the
    rest shape, the CCD-only list; a self pair touching at rest into neither."""
    dr = rest_gap
    if rest_gap > 0.0 and group[q[0]] == group[q[2 - kind]]:
        dr = pair_distance(kind, rest[q[0]], rest[q[1]], rest[q[2]], rest[q[3]])
    if dr >= rest_gap:
        _append(pairs, kinds, count, capacity, q, kind)
    elif dr > 0.0:
        _append(ccd_pairs, ccd_kinds, ccd_count, ccd_capacity, q, kind)


@wp.kernel
def broad_phase_kernel(tri_bvh: wp.uint64, edge_bvh: wp.uint64, vlo: wp.array(dtype=wp.vec3), vhi: wp.array(dtype=wp.vec3),
                       elo: wp.array(dtype=wp.vec3), ehi: wp.array(dtype=wp.vec3), verts: wp.array(dtype=wp.int32),
                       tris: wp.array(dtype=wp.int32), edges: wp.array(dtype=wp.int32), group: wp.array(dtype=wp.int32),
                       self_on: int, bodies_on: int, num_verts: int, pairs: wp.array(dtype=wp.vec4i),
                       kinds: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32), capacity: int,
                       rest: wp.array(dtype=wp.vec3), rest_gap: float, ccd_pairs: wp.array(dtype=wp.vec4i),
                       ccd_kinds: wp.array(dtype=wp.int32), ccd_count: wp.array(dtype=wp.int32), ccd_capacity: int):
    """Candidate pairs of the boxes' overlaps. A self pair (same group) whose distance in the rest
    shape (``rest``, float32) is below ``rest_gap`` goes to the CCD-only list (``ccd_*``: step
    bound, no barrier) instead, and one at distance 0 there (touching at rest) to neither."""
    i = wp.tid()
    t = int(0)
    if i < num_verts:
        v = verts[i]
        query = wp.bvh_query_aabb(tri_bvh, vlo[i], vhi[i])
        while wp.bvh_query_next(query, t):
            a = tris[3 * t]
            b = tris[3 * t + 1]
            c = tris[3 * t + 2]
            if v != a and v != b and v != c:
                if _keep(group, v, a, self_on, bodies_on):
                    _sort_pair(0, wp.vec4i(v, a, b, c), group, rest, rest_gap, pairs, kinds, count, capacity,
                               ccd_pairs, ccd_kinds, ccd_count, ccd_capacity)
    else:
        e = i - num_verts
        a0 = edges[2 * e]
        a1 = edges[2 * e + 1]
        query = wp.bvh_query_aabb(edge_bvh, elo[e], ehi[e])
        while wp.bvh_query_next(query, t):
            if t > e:
                b0 = edges[2 * t]
                b1 = edges[2 * t + 1]
                if a0 != b0 and a0 != b1 and a1 != b0 and a1 != b1:
                    if _keep(group, a0, b0, self_on, bodies_on):
                        _sort_pair(1, wp.vec4i(a0, a1, b0, b1), group, rest, rest_gap, pairs, kinds, count, capacity,
                                   ccd_pairs, ccd_kinds, ccd_count, ccd_capacity)


@wp.func
def pair_accd(kind: int, x0: Any, x1: Any, x2: Any, x3: Any, p0: Any, p1: Any, p2: Any, p3: Any, eta: Any):
    """Additive CCD: a step length t in [0, 1] along x + t p with the pair apart on [0, t] and its
    gap at t at least eta x the current one (1 when it does not come that close)."""
    zero = eta - eta
    one = zero + type(eta)(1.0)
    pm = (p0 + p1 + p2 + p3) * type(eta)(0.25)
    q0 = p0 - pm
    q1 = p1 - pm
    q2 = p2 - pm
    q3 = p3 - pm
    lp = zero
    if kind == 0:
        lp = wp.length(q0) + wp.max(wp.length(q1), wp.max(wp.length(q2), wp.length(q3)))
    else:
        lp = wp.max(wp.length(q0), wp.length(q1)) + wp.max(wp.length(q2), wp.length(q3))
    d0 = pair_distance(kind, x0, x1, x2, x3)
    if d0 <= zero:
        return zero
    if lp <= zero:
        return one
    gap = eta * d0
    t = zero
    tl = (one - eta) * d0 / lp
    y0 = x0
    y1 = x1
    y2 = x2
    y3 = x3
    for it in range(ACCD_MAX_ITERS):
        y0 = y0 + tl * q0
        y1 = y1 + tl * q1
        y2 = y2 + tl * q2
        y3 = y3 + tl * q3
        d = pair_distance(kind, y0, y1, y2, y3)
        if t > zero and d < gap:
            return t
        t = t + tl
        if t >= one:
            return one
        tl = type(eta)(0.9) * d / lp
    return t


@wp.func
def _add_pair_hessian(values: wp.array(dtype=Any), blocks: wp.array(dtype=wp.int32), p: int, scale: Any, mode: int,
                      kind: int, x0: Any, x1: Any, x2: Any, x3: Any, w: Any, c0: Any, c1: Any, k: int, r: Any, u: Any,
                      v: Any, m: Any, m1: Any, m2: Any, b0: Any, b1: Any, b2: Any, gc0: Any, gc1: Any, gc2: Any,
                      gc3: Any, kappa: Any, jtol: Any, hslots: wp.array(dtype=Any), h: int):
    """Hessian of kappa m b(s): m b'' gs gs^T + m b' Hs + b' (gm gs^T + gs gm^T) + b Hm (mode 2: its PSD
    projection), times scale: pair p's 16 vertex blocks into its slots ``hslots[16 h:16 h + 16]``
    (``h >= 0``, the gather path), or added with atomics into values (``h < 0``; none when the
    pattern has no blocks for the pair, -1: not reached, a pair within dhat has them)."""
    if h < 0 and blocks[16 * p] < 0:
        return
    zero = kappa - kappa
    one = zero + type(kappa)(1.0)
    two = one + one
    J0 = c0[0] * x0 + c0[1] * x1 + c0[2] * x2 + c0[3] * x3
    J1 = c1[0] * x0 + c1[1] * x1 + c1[2] * x2 + c1[3] * x3
    g00 = two * wp.dot(J0, J0)
    g01 = two * wp.dot(J0, J1)
    g11 = two * wp.dot(J1, J1)
    i00 = zero
    i01 = zero
    i11 = zero
    if k == 1 and g00 > zero:
        i00 = one / g00
    elif k == 2:
        det = g00 * g11 - g01 * g01
        if det > zero:
            i00 = g11 / det
            i01 = -g01 / det
            i11 = g00 / det
    H = _empty12(zero)
    I3 = wp.identity(3, type(kappa))
    rr = wp.outer(r, r)
    for i in range(4):
        Bi0 = two * (c0[i] * r + w[i] * J0)
        Bi1 = two * (c1[i] * r + w[i] * J1)
        gci = _pick(i, gc0, gc1, gc2, gc3)
        gsi = (two * w[i]) * r
        for j in range(4):
            Bj0 = two * (c0[j] * r + w[j] * J0)
            Bj1 = two * (c1[j] * r + w[j] * J1)
            hs = (two * w[i] * w[j]) * I3 - i00 * wp.outer(Bi0, Bj0) - i01 * (wp.outer(Bi0, Bj1) + wp.outer(Bi1, Bj0)) \
                - i11 * wp.outer(Bi1, Bj1)
            blk = (m * b2 * two * two * w[i] * w[j]) * rr + (m * b1) * hs
            if kind == 1:
                gcj = _pick(j, gc0, gc1, gc2, gc3)
                gsj = (two * w[j]) * r
                blk = blk + (b1 * m1) * (wp.outer(gci, gsj) + wp.outer(gsi, gcj)) + (b0 * m2) * wp.outer(gci, gcj) \
                    + (b0 * m1) * _hc_block(i, j, u, v, one)
            H = add_block(H, i, j, kappa * blk)
    if mode == 2:
        H = psd_project_pair(H, kind, w, jtol)
    for i in range(4):
        for j in range(4):
            M = rr - rr
            for a in range(3):
                for b in range(3):
                    M[a, b] = H[3 * i + a, 3 * j + b]
            if h >= 0:
                hslots[16 * h + 4 * i + j] = scale * M
            else:
                wp.atomic_add(values, blocks[16 * p + 4 * i + j], scale * M)


@wp.func
def _no_slots(mode: int, p: int, h: int, active: wp.array(dtype=wp.int32), hactive: wp.array(dtype=wp.int32),
              slots: int):
    """Pair p adds nothing (gradient, mode 1; Hessian, modes 2 and 6, h >= 0): its slots are
    marked inactive, and the gather skips them."""
    if slots == 0:
        return
    if mode == 1:
        active[p] = 0
    elif (mode == 2 or mode == 6) and h >= 0:
        hactive[h] = 0


# split across CPU threads (``kernels.generic.splittable``) when ``slots`` is set: every pair writes
# only its own outputs (distance, lagging data, gradient and Hessian slots, gathered afterwards by
# ``gather_vec_kernel`` / ``gather_mat_kernel``); energies, magnitudes (sums) and the step bound (a
# minimum) go through rows of partial results
@splittable("reduce", 512, acc=18, slot=19, n_add=3, n_min=1, when=26)
@both_precisions(x="v[]", rest="v[]", dx="v[]", dhat2="s", kappa="s", eta="s", scale="s", g="v[]", values="m[]",
                 out="s[]", f_w="v4[]", f_n="v[]", f_lam="s[]", jtol="s", gslots="v[]", hslots="m[]")
@wp.kernel
def pair_kernel(x: wp.array(dtype=Any), rest: wp.array(dtype=Any), pairs: wp.array(dtype=wp.vec4i),
                kinds: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32), dhat2: Any, kappa: Any,
                mode: int, scale: Any, dx: wp.array(dtype=Any), eta: Any, g: wp.array(dtype=Any),
                blocks: wp.array(dtype=wp.int32), values: wp.array(dtype=Any), out: wp.array(dtype=Any),
                f_w: wp.array(dtype=Any), f_n: wp.array(dtype=Any), f_lam: wp.array(dtype=Any),
                acc: wp.array(dtype=wp.float64), slot: int, jtol: Any, gslots: wp.array(dtype=Any),
                hslots: wp.array(dtype=Any), hidx: wp.array(dtype=wp.int32), active: wp.array(dtype=wp.int32),
                hactive: wp.array(dtype=wp.int32), slots: int, start: int, row_block: int, row_stride: int):
    """Pair p's job of ``mode`` (module docstring). ``slots != 0``: the gradient (mode 1) into the
    pair's four slots ``gslots[4 p:4 p + 4]`` (``active[p]`` 1, or 0 when the pair adds nothing)
    and the Hessian (modes 2, 6) into its 16 slots ``hslots[16 h:16 h + 16]``, h = ``hidx[p]``
    (-1: the pair has no blocks; ``hactive[h]`` as ``active``), both for a gather in a fixed
    order; ``slots == 0``: added with atomics into g and values. Sums and the step bound go to
    ``acc[slot + (p / row_block) row_stride + j]`` (rows of partial results when split)."""
    p = wp.tid() + start
    if p >= count[0]:
        return
    ra = slot + (p / row_block) * row_stride
    h = int(-1)
    if slots != 0 and (mode == 2 or mode == 6):
        h = hidx[p]
        if h < 0:
            return
    ids = pairs[p]
    kind = kinds[p]
    x0 = x[ids[0]]
    x1 = x[ids[1]]
    x2 = x[ids[2]]
    x3 = x[ids[3]]
    zero = kappa - kappa
    one = zero + type(kappa)(1.0)
    two = one + one
    if mode == 3:
        t = pair_accd(kind, x0, x1, x2, x3, scale * dx[ids[0]], scale * dx[ids[1]], scale * dx[ids[2]],
                      scale * dx[ids[3]], eta)
        wp.atomic_min(acc, ra + 3, wp.float64(t))
        return
    w, c0, c1, k = pair_features(kind, x0, x1, x2, x3)
    r = pair_r(w, x0, x1, x2, x3)
    s = wp.dot(r, r)
    if mode == 4:
        out[p] = wp.sqrt(s)
        return
    if s <= zero:
        if mode == 0:
            wp.atomic_add(acc, ra + 1, wp.float64(1.0))
        _no_slots(mode, p, h, active, hactive, slots)
        return
    if s >= dhat2:
        if mode == 5:
            f_lam[p] = zero
        _no_slots(mode, p, h, active, hactive, slots)
        return
    b0, b1, b2 = barrier(s, dhat2)
    # edge-edge mollifier and its derivatives (1, 0, 0 for point-triangle pairs)
    m = one
    m1 = zero
    m2 = zero
    u = x1 - x0
    v = x3 - x2
    if kind == 1:
        cr = wp.cross(u, v)
        cc = wp.dot(cr, cr)
        ru = rest[ids[1]] - rest[ids[0]]
        rv = rest[ids[3]] - rest[ids[2]]
        epsx = type(kappa)(1e-3) * wp.dot(ru, ru) * wp.dot(rv, rv)
        m, m1, m2 = mollifier(cc, epsx)
    if mode == 5:  # friction lagging: normal force, closest-point weights, normal
        f_lam[p] = kappa * m * (-b1) * two * wp.sqrt(s)
        f_w[p] = w
        f_n[p] = r / wp.sqrt(s)
        return
    if mode == 0:
        wp.atomic_add(acc, ra, wp.float64(kappa * m * b0))
        return
    # dc/dx per vertex (edge-edge only): c = |u|^2 |v|^2 - (u.v)^2, u = x1 - x0, v = x3 - x2
    uv = wp.dot(u, v)
    gu = two * wp.dot(v, v) * u - two * uv * v
    gv = two * wp.dot(u, u) * v - two * uv * u
    gc0 = -gu
    gc1 = gu
    gc2 = -gv
    gc3 = gv
    if mode == 1:
        gsq = wp.float64(0.0)
        for i in range(4):
            gi = (kappa * m * b1 * two * w[i]) * r
            if kind == 1 and m1 != zero:
                gci = gc0
                if i == 1:
                    gci = gc1
                elif i == 2:
                    gci = gc2
                elif i == 3:
                    gci = gc3
                gi = gi + (kappa * b0 * m1) * gci
            if slots != 0:
                gslots[4 * p + i] = scale * gi
            else:
                wp.atomic_add(g, ids[i], scale * gi)
            gsq += wp.float64(wp.dot(gi, gi))
        if slots != 0:
            active[p] = 1
        wp.atomic_add(acc, ra + 2, gsq * wp.float64(scale * scale))
        return
    if h >= 0:
        hactive[h] = 1
    # modes 2, 6 (a function: its 12 x 12 locals are only set up for the pairs within dhat)
    _add_pair_hessian(values, blocks, p, scale, mode, kind, x0, x1, x2, x3, w, c0, c1, k, r, u, v, m, m1, m2, b0, b1, b2,
                      gc0, gc1, gc2, gc3, kappa, jtol, hslots, h)


@splittable("reduce", 1024, acc=15, slot=16, n_add=3, when=20)
@both_precisions(dbase="v[]", ydisp="v[]", sy="s", f_w="v4[]", f_n="v[]", f_lam="s[]", mu="s", eps="s", scale="s",
                 g="v[]", values="m[]", gslots="v[]", hslots="m[]")
@wp.kernel
def friction_kernel(dbase: wp.array(dtype=Any), ydisp: wp.array(dtype=Any), sy: Any, pairs: wp.array(dtype=wp.vec4i),
                    f_w: wp.array(dtype=Any), f_n: wp.array(dtype=Any), f_lam: wp.array(dtype=Any),
                    count: int, mu: Any, eps: Any, mode: int, scale: Any, g: wp.array(dtype=Any),
                    blocks: wp.array(dtype=wp.int32), values: wp.array(dtype=Any), acc: wp.array(dtype=wp.float64),
                    slot: int, gslots: wp.array(dtype=Any), hslots: wp.array(dtype=Any), active: wp.array(dtype=wp.int32),
                    slots: int, start: int, row_block: int, row_stride: int):
    """Lagged friction of pair p: mu lambda f0(|u|), u = P sum_i w_i (x_i - x_i^n), P = I - n n^T
    (lambda, w, n from the start of the step; x - x^n = dbase + sy ydisp). ``slots != 0``: the
    gradient into ``gslots[4 p:4 p + 4]``, the Hessian into ``hslots[16 p:16 p + 16]`` (``active[p]``
    0 for a pair without a normal force), gathered afterwards in a fixed order; ``slots == 0``:
    added with atomics. Sums into rows as ``pair_kernel``."""
    p = wp.tid() + start
    if p >= count:
        return
    ra = slot + (p / row_block) * row_stride
    lam = f_lam[p]
    zero = mu - mu
    if lam <= zero:
        if slots != 0:
            active[p] = 0
        return
    if slots != 0:
        active[p] = 1
    ids = pairs[p]
    w = f_w[p]
    nv = f_n[p]
    Pm = wp.identity(3, type(mu)) - wp.outer(nv, nv)
    rel = nv - nv
    for i in range(4):
        rel = rel + w[i] * (dbase[ids[i]] + sy * ydisp[ids[i]])
    u = Pm * rel
    y = wp.length(u)
    c = mu * lam
    if mode == 0:
        wp.atomic_add(acc, ra, wp.float64(c * friction_f0(y, eps)))
        return
    f1y = c / eps  # f1(y) / y times c: 1 / eps in the sticking zone (a linear spring), 1 / y beyond
    if y >= eps:
        f1y = c / y
    if mode == 1:
        gsq = wp.float64(0.0)
        for i in range(4):
            gi = (w[i] * f1y) * u
            if slots != 0:
                gslots[4 * p + i] = scale * gi
            else:
                wp.atomic_add(g, ids[i], scale * gi)
            gsq += wp.float64(wp.dot(gi, gi))
        wp.atomic_add(acc, ra + 2, gsq * wp.float64(scale * scale))
        return
    Hu = f1y * Pm
    if y >= eps:
        Hu = (c / y) * (Pm - wp.outer(u, u) / (y * y))
    for i in range(4):
        for j in range(4):
            if slots != 0:
                hslots[16 * p + 4 * i + j] = (scale * w[i] * w[j]) * Hu
            else:
                wp.atomic_add(values, blocks[16 * p + 4 * i + j], (scale * w[i] * w[j]) * Hu)


# the gather half of the deterministic assembly: per target (a vertex, a pattern block) the sum of its
# slots in the order of its map, added to what the target holds (split across CPU threads: each
# target is written by one index only)
@wp.func
def _gather_target(i: int, targets: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32),
                   entries: wp.array(dtype=wp.int32), active: wp.array(dtype=wp.int32), shift: int,
                   contrib: wp.array(dtype=Any), out: wp.array(dtype=Any)):
    """out[targets[i]] += contrib[s] for s = entries[k], k in offsets[i]:offsets[i + 1], in that
    order, skipping the slots of inactive owners (``active[s >> shift] == 0``)."""
    lo = offsets[i]
    hi = offsets[i + 1]
    k = lo
    while k < hi and active[entries[k] >> shift] == 0:  # the target is read only if a slot adds to it
        k += 1
    if k < hi:
        t = targets[i]
        a = out[t]
        while k < hi:
            e = entries[k]
            if active[e >> shift] != 0:
                a = a + contrib[e]
            k += 1
        out[t] = a


@splittable("start", 2048)
@both_precisions(contrib="v[]", out="v[]")
@wp.kernel
def gather_vec_kernel(targets: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32),
                      entries: wp.array(dtype=wp.int32), active: wp.array(dtype=wp.int32), shift: int,
                      contrib: wp.array(dtype=Any), out: wp.array(dtype=Any), start: int):
    """Vertex targets: :func:`_gather_target` for each target i."""
    _gather_target(wp.tid() + start, targets, offsets, entries, active, shift, contrib, out)


@splittable("start", 1024)
@both_precisions(contrib="m[]", out="m[]")
@wp.kernel
def gather_mat_kernel(targets: wp.array(dtype=wp.int32), offsets: wp.array(dtype=wp.int32),
                      entries: wp.array(dtype=wp.int32), active: wp.array(dtype=wp.int32), shift: int,
                      contrib: wp.array(dtype=Any), out: wp.array(dtype=Any), start: int):
    """Pattern-block targets: :func:`_gather_target` for each target i."""
    _gather_target(wp.tid() + start, targets, offsets, entries, active, shift, contrib, out)
