"""Shared Warp helpers for isotropic materials: signed SVD, cofactor, the analytic Hessian block.

The Hessian dP/dF of an isotropic energy psi(F) = Psi(s) (s = signed singular values) has a
closed-form eigensystem (Smith, de Goes, Kim 2019, "Analytic eigensystems for isotropic
distortion energies", ACM TOG 38(1), sec. 4-5; see also Xu, Sin, Zhu, Barbic 2015):

* scaling modes  U diag(Q[:, m]) V^T, eigenvalue d[m], where (Q, d) is the eigensystem of the
  3x3 matrix A = d2Psi/ds2;
* twist modes    U (e_i e_j^T - e_j e_i^T) V^T / sqrt2, eigenvalue twist[k] = (Psi_i + Psi_j)/(s_i + s_j);
* flip modes     U (e_i e_j^T + e_j e_i^T) V^T / sqrt2, eigenvalue flip[k]  = (Psi_i - Psi_j)/(s_i - s_j);

where pair k is the pair of axes other than k: k=0 -> (1,2), k=1 -> (0,2), k=2 -> (0,1).
Every material module supplies closed forms for A, twist and flip that have no division by
s_i - s_j. All functions are generic over float32/float64 (mat33/mat33d).
"""

from typing import Any

import warp as wp

__all__ = [
    "signed_svd",
    "jacobi_signed_svd",
    "cofactor",
    "scaling_eigensystem",
    "pair_axes",
    "hessian_block",
    "project_scaling_block",
    "hessian_point_prepare",
    "hessian_point_block",
    "hessian_point_matrix",
    "hessian_matrix_rows",
]


@wp.func
def signed_svd(F: Any):
    """Signed ("rotation-variant") SVD F = U diag(s) V^T with det U = det V = +1.

    ``wp.svd3`` (McAdams et al. 2011) returns s sorted by decreasing magnitude with
    s[0] >= s[1] >= |s[2]| and rotations U, V, i.e. for det F < 0 the reflection is already in
    s[2] < 0 (checked on warp-lang 1.19). This function re-checks and, should a reflection ever
    appear in U or V, moves it into s[2] by negating the last column, so that callers can rely
    on the convention. Returns (U, s, V).
    """
    U = type(F)()
    V = type(F)()
    s = wp.vector(length=3, dtype=F.dtype)
    wp.svd3(F, U, s, V)
    zero = F.dtype(0.0)
    if wp.determinant(U) < zero:
        U = U * wp.diag(wp.vector(F.dtype(1.0), F.dtype(1.0), F.dtype(-1.0)))
        s = wp.vector(s[0], s[1], -s[2])
    if wp.determinant(V) < zero:
        V = V * wp.diag(wp.vector(F.dtype(1.0), F.dtype(1.0), F.dtype(-1.0)))
        s = wp.vector(s[0], s[1], -s[2])
    return U, s, V


@wp.func
def _jacobi_rotation(app: Any, aqq: Any, apq: Any, apr: Any, aqr: Any, vp: Any, vq: Any, tol2: Any):
    """One exact Jacobi rotation of a symmetric 3x3 matrix that zeroes its entry (p, q)
    (Golub & Van Loan, "Matrix Computations", sec. 8.5, the symmetric Schur decomposition):
    returns the new a_pp, a_qq, a_pr, a_qr (a_pq is then 0, a_rr unchanged) and the columns p, q of
    the accumulated rotation V <- V J. An entry already at the working precision (a_pq^2 <=
    tol2 (a_pp^2 + a_qq^2)) is left as it is (it would move a_pp, a_qq by a_pq^2 / (a_qq - a_pp))."""
    zero = app - app
    if apq == zero or apq * apq <= tol2 * (app * app + aqq * aqq):
        return app, aqq, apr, aqr, vp, vq
    one = zero + type(app)(1.0)
    theta = (aqq - app) / (type(app)(2.0) * apq)
    t = one / (wp.abs(theta) + wp.sqrt(one + theta * theta))
    if theta < zero:
        t = -t
    c = one / wp.sqrt(one + t * t)
    s = t * c
    return app - t * apq, aqq + t * apq, c * apr - s * aqr, s * apr + c * aqr, c * vp - s * vq, s * vp + c * vq


@wp.func
def _unit_normal_to(u: Any):
    """A unit vector orthogonal to the unit vector u (crossed with the axis least aligned with it)."""
    zero = u[0] - u[0]
    one = zero + type(u[0])(1.0)
    e = type(u)(one, zero, zero)
    if wp.abs(u[1]) <= wp.abs(u[0]) and wp.abs(u[1]) <= wp.abs(u[2]):
        e = type(u)(zero, one, zero)
    elif wp.abs(u[2]) <= wp.abs(u[0]):
        e = type(u)(zero, zero, one)
    return wp.normalize(wp.cross(u, e))


@wp.func
def jacobi_signed_svd(F: Any):
    """Signed SVD F = U diag(s) V^T (det U = det V = +1, s[0] >= s[1] >= |s[2]|, a reflection in
    s[2] < 0), the same convention as :func:`signed_svd`, computed more cheaply: cyclic Jacobi on
    F^T F with exact rotations until its off-diagonal part is below the working precision (a
    near-rest F^T F = I + 2E converges in 2-4 sweeps, against the fixed 8 approximate sweeps of
    ``wp.svd3`` in float64), the columns sorted by decreasing eigenvalue with the determinant
    kept, then U from Gram-Schmidt on B = F V (u2 = u0 x u1, s[2] = u2 . b2 signed). Rank-deficient
    F: columns of U are completed orthonormally. Returns (U, s, V)."""
    zero = F.dtype(0.0)
    one = F.dtype(1.0)
    A = wp.transpose(F) * F
    d0 = A[0, 0]
    d1 = A[1, 1]
    d2 = A[2, 2]
    o01 = A[0, 1]
    o02 = A[0, 2]
    o12 = A[1, 2]
    v0 = wp.vector(one, zero, zero)
    v1 = wp.vector(zero, one, zero)
    v2 = wp.vector(zero, zero, one)
    # stop when sum(off^2) <= tol2 sum(diag^2): off-diagonals at the working precision; below
    # rel x s[0], s[1] is round-off and u1 any unit vector orthogonal to u0
    tol2 = F.dtype(1.0e-30)
    rel = F.dtype(1.0e-14)
    if one + F.dtype(1.0e-10) == one:  # float32
        tol2 = F.dtype(1.0e-13)
        rel = F.dtype(1.0e-6)
    for _sweep in range(12):
        if o01 * o01 + o02 * o02 + o12 * o12 <= tol2 * (d0 * d0 + d1 * d1 + d2 * d2):
            break
        d0, d1, o02, o12, v0, v1 = _jacobi_rotation(d0, d1, o01, o02, o12, v0, v1, tol2)  # (p, q, r) = (0, 1, 2)
        o01 = zero
        d0, d2, o01, o12, v0, v2 = _jacobi_rotation(d0, d2, o02, o01, o12, v0, v2, tol2)  # (0, 2, 1)
        o02 = zero
        d1, d2, o01, o02, v1, v2 = _jacobi_rotation(d1, d2, o12, o01, o02, v1, v2, tol2)  # (1, 2, 0)
        o12 = zero
    # sort by decreasing eigenvalue; a swap negates one column so that det V stays +1
    if d0 < d1:
        d0, d1 = d1, d0
        v0, v1 = v1, -v0
    if d0 < d2:
        d0, d2 = d2, d0
        v0, v2 = v2, -v0
    if d1 < d2:
        d1, d2 = d2, d1
        v1, v2 = v2, -v1
    b0 = F * v0
    b1 = F * v1
    b2 = F * v2
    n0 = wp.length(b0)
    u0 = wp.vector(one, zero, zero)
    if n0 > zero:
        u0 = b0 / n0
    c1 = b1 - wp.dot(u0, b1) * u0
    n1 = wp.length(c1)
    u1 = _unit_normal_to(u0)
    if n1 > rel * n0 and n1 > zero:
        u1 = c1 / n1
        u1 = wp.normalize(u1 - wp.dot(u0, u1) * u0)  # Gram-Schmidt twice: orthogonal to round-off
    u2 = wp.cross(u0, u1)
    U = wp.matrix_from_cols(u0, u1, u2)
    V = wp.matrix_from_cols(v0, v1, v2)
    return U, wp.vector(n0, wp.dot(u1, b1), wp.dot(u2, b2)), V


@wp.func
def cofactor(F: Any):
    """Cofactor matrix cof(F) = dJ/dF = J F^{-T}, computed without inversion.

    Column c of cof(F) is the cross product of the other two columns of F:
    cof = [f1 x f2 | f2 x f0 | f0 x f1] with f_c = F[:, c].
    """
    f0 = wp.vector(F[0, 0], F[1, 0], F[2, 0])
    f1 = wp.vector(F[0, 1], F[1, 1], F[2, 1])
    f2 = wp.vector(F[0, 2], F[1, 2], F[2, 2])
    c0 = wp.cross(f1, f2)
    c1 = wp.cross(f2, f0)
    c2 = wp.cross(f0, f1)
    return wp.matrix_from_cols(c0, c1, c2)


@wp.func
def scaling_eigensystem(A: Any):
    """Eigensystem of the symmetric 3x3 scaling block A = d2Psi/ds2 with ``wp.eig3``.

    Returns (Q, d) with A = Q diag(d) Q^T: the columns Q[:, m] are the eigenvectors
    (``wp.eig3`` convention, eigenvalues unsorted; checked on warp-lang 1.19). ``wp.eig3`` is
    applied twice (the second time to Q^T A Q) for float32 accuracy.
    """
    Q = type(A)()
    d = wp.vector(length=3, dtype=A.dtype)
    wp.eig3(A, Q, d)
    # Second Jacobi pass on the nearly diagonal Q^T A Q: in float32 a single wp.eig3 call can stop
    # with a reconstruction error ~1e-4 relative (measured); the refinement brings it to ~1e-7.
    Q2 = type(A)()
    wp.eig3(wp.transpose(Q) * A * Q, Q2, d)
    return Q * Q2, d


@wp.func
def pair_axes(k: int):
    """Axes (i, j), i < j, of pair k: k=0 -> (1,2), k=1 -> (0,2), k=2 -> (0,1)."""
    i = 0
    j = 2
    if k == 0:
        i = 1
    if k == 2:
        j = 1
    return i, j


@wp.func
def project_scaling_block(A: Any, project: int):
    """The scaling block for assembly: A itself when ``project == 0`` or when A is positive definite
    (Sylvester: A00 > 0, A00 A11 - A01^2 > 0, det A > 0; then clamping changes nothing), otherwise
    Q diag(max(d, 0)) Q^T from :func:`scaling_eigensystem`. The eigen-solve (two ``wp.eig3`` calls,
    the most expensive step of a Hessian point: ~6.5 us of ~13 us on one CPU core, measured) is
    only paid where A is indefinite."""
    if project == 0:
        return A
    zero = A.dtype(0.0)
    if A[0, 0] > zero:
        if A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0] > zero:
            if wp.determinant(A) > zero:
                return A
    Q, d = scaling_eigensystem(A)
    return Q * wp.diag(wp.vector(wp.max(d[0], zero), wp.max(d[1], zero), wp.max(d[2], zero))) * wp.transpose(Q)


@wp.func
def _clamp_if(v: Any, project: int):
    if project != 0:
        zero = v[0] - v[0]
        return type(v)(wp.max(v[0], zero), wp.max(v[1], zero), wp.max(v[2], zero))
    return v


@wp.func
def hessian_point_prepare(U: Any, V: Any, A: Any, twist: Any, flip: Any, project: int):
    """Per-quadrature-point half of the Hessian contraction: dP/dF (9x9) in compressed form.

    Input: the eigen form of ``material_hessian_parts`` (F = U diag(s) V^T, scaling block
    A = d2Psi/ds2, twist / flip eigenvalues). Returns (U, Vt, A', cp, cm): A' the scaling block
    (SPD-projected with :func:`project_scaling_block` when ``project != 0``), cp[k] = (t'_k + f'_k)/2,
    cm[k] = (f'_k - t'_k)/2 with t', f' clamped at 0 when projecting. This is everything of dP/dF
    that does not depend on the shape-function gradients; do it once per point, then call
    :func:`hessian_point_block` per node pair.
    """
    half = U.dtype(0.5)
    tw = _clamp_if(twist, project)
    fl = _clamp_if(flip, project)
    return U, wp.transpose(V), project_scaling_block(A, project), half * (tw + fl), half * (fl - tw)


@wp.func
def hessian_point_block(U: Any, A: Any, cp: Any, cm: Any, a: Any, b: Any):
    """Block sum_m lambda_m (Q_m ga)(Q_m gb)^T from :func:`hessian_point_prepare`'s output, with the
    gradients already in the rotated frame: ``a = Vt ga``, ``b = Vt gb`` (so a caller rotates each
    node's gradient once, not once per block). In the rotated frame
    M_pq = a_p A_pq b_q, and for pair k = (i, j): M_ii += cp_k a_j b_j, M_jj += cp_k a_i b_i,
    M_ij += cm_k a_j b_i, M_ji += cm_k a_i b_j; the block is U M U^T.
    """
    # M_pq = a_p A_pq b_q entry by entry (diag(a) A diag(b) as two matrix products costs 3x the
    # multiplies), pair 0 = (1, 2), pair 1 = (0, 2), pair 2 = (0, 1) unrolled, one constructor
    a0b0 = a[0] * b[0]
    a1b1 = a[1] * b[1]
    a2b2 = a[2] * b[2]
    M = type(A)(a0b0 * A[0, 0] + cp[1] * a2b2 + cp[2] * a1b1,
                a[0] * A[0, 1] * b[1] + cm[2] * a[1] * b[0],
                a[0] * A[0, 2] * b[2] + cm[1] * a[2] * b[0],
                a[1] * A[1, 0] * b[0] + cm[2] * a[0] * b[1],
                a1b1 * A[1, 1] + cp[0] * a2b2 + cp[2] * a0b0,
                a[1] * A[1, 2] * b[2] + cm[0] * a[2] * b[1],
                a[2] * A[2, 0] * b[0] + cm[1] * a[0] * b[2],
                a[2] * A[2, 1] * b[1] + cm[0] * a[1] * b[2],
                a2b2 * A[2, 2] + cp[0] * a1b1 + cp[1] * a0b0)
    return U * M * wp.transpose(U)


@wp.func
def _vec9(M: Any):
    """Row-major vec of a 3x3 matrix: index 3 i + j holds M[i, j]."""
    return wp.vector(M[0, 0], M[0, 1], M[0, 2], M[1, 0], M[1, 1], M[1, 2], M[2, 0], M[2, 1], M[2, 2])


@wp.func
def hessian_point_matrix(U: Any, V: Any, A: Any, twist: Any, flip: Any, project: int):
    """dP/dF as an explicit 9x9 matrix H[3i+j, 3k+l] = d2psi/dF_ij dF_kl (row-major F) from the
    eigen form of ``material_hessian_parts``, SPD-projected when ``project != 0``:
    H = sum_pq A'_pq w_p w_q^T + sum_k (t'_k t_k t_k^T + f'_k f_k f_k^T), w_p = vec(u_p v_p^T),
    t_k / f_k = vec(U (e_i e_j^T -/+ e_j e_i^T) V^T) / sqrt2 (u_p, v_p columns of U, V; A' as in
    :func:`hessian_point_prepare`). ~550 multiply-adds per point; pays off when an element has many
    node pairs (see :func:`hessian_matrix_rows`).
    """
    r2 = wp.sqrt(U.dtype(0.5))
    Ap = project_scaling_block(A, project)
    tw = _clamp_if(twist, project)
    fl = _clamp_if(flip, project)
    w0 = _vec9(wp.outer(wp.vector(U[0, 0], U[1, 0], U[2, 0]), wp.vector(V[0, 0], V[1, 0], V[2, 0])))
    w1 = _vec9(wp.outer(wp.vector(U[0, 1], U[1, 1], U[2, 1]), wp.vector(V[0, 1], V[1, 1], V[2, 1])))
    w2 = _vec9(wp.outer(wp.vector(U[0, 2], U[1, 2], U[2, 2]), wp.vector(V[0, 2], V[1, 2], V[2, 2])))
    z0 = Ap[0, 0] * w0 + Ap[1, 0] * w1 + Ap[2, 0] * w2
    z1 = Ap[0, 1] * w0 + Ap[1, 1] * w1 + Ap[2, 1] * w2
    z2 = Ap[0, 2] * w0 + Ap[1, 2] * w1 + Ap[2, 2] * w2
    H = wp.outer(z0, w0) + wp.outer(z1, w1) + wp.outer(z2, w2)
    for k in range(3):
        i, j = pair_axes(k)
        E1 = wp.outer(wp.vector(U[0, i], U[1, i], U[2, i]), wp.vector(V[0, j], V[1, j], V[2, j]))
        E2 = wp.outer(wp.vector(U[0, j], U[1, j], U[2, j]), wp.vector(V[0, i], V[1, i], V[2, i]))
        t = _vec9(r2 * (E1 - E2))
        f = _vec9(r2 * (E1 + E2))
        H += tw[k] * wp.outer(t, t) + fl[k] * wp.outer(f, f)
    return H


@wp.func
def _matrix_row_contract(H: Any, i: int, g: Any):
    T = wp.matrix(shape=(3, 3), dtype=g.dtype)
    for k in range(3):
        for l in range(3):
            T[k, l] = H[3 * i, 3 * k + l] * g[0] + H[3 * i + 1, 3 * k + l] * g[1] + H[3 * i + 2, 3 * k + l] * g[2]
    return T


@wp.func
def hessian_matrix_rows(H: Any, ga: Any):
    """Contract the 9x9 ``H`` with one node's gradient: T_i[k, l] = sum_j H[3i+j, 3k+l] ga_j, i = 0..2.

    Then block (a, b) of the element Hessian (before the weight) has rows T_i gb:
    ``wp.matrix_from_rows(T0 * gb, T1 * gb, T2 * gb)`` (27 multiply-adds per block)."""
    return _matrix_row_contract(H, 0, ga), _matrix_row_contract(H, 1, ga), _matrix_row_contract(H, 2, ga)


@wp.func
def hessian_block(U: Any, V: Any, Q: Any, d: Any, twist: Any, flip: Any, ga: Any, gb: Any, project: int):
    """3x3 block of the Hessian contracted with two vectors: sum_m lambda_m (Q_m ga)(Q_m gb)^T.

    Q_m are the nine 3x3 eigenmatrices (see module docstring), lambda_m their eigenvalues,
    clamped at 0 when ``project != 0`` (SPD projection). In index form
    H[3i+j, 3k+l] = hessian_block(e_j, e_l)[i, k]; for an element, block (a, b) of the
    stiffness is weight * hessian_block(..., dN_a/dX, dN_b/dX, project).

    One-shot form from the full eigensystem (``material_eigensystem``). Element loops should hoist
    the per-point work instead, as ``warpfem.kernels.fem.qp_hessian_kernel`` does
    (``material_hessian_parts``, then :func:`hessian_point_prepare` + :func:`hessian_point_block`,
    or :func:`hessian_point_matrix` + :func:`hessian_matrix_rows`): this function redoes
    Q diag(d) Q^T and the clamps on every call.

    The contraction is done in the rotated frame a = V^T ga, b = V^T gb, then rotated back with U:
    scaling part  M_pq = (Q diag(d) Q^T)_pq a_p b_q,
    pair (i, j)   M_ii += (t+f)/2 a_j b_j, M_jj += (t+f)/2 a_i b_i,
                  M_ij += (f-t)/2 a_j b_i, M_ji += (f-t)/2 a_i b_j.
    """
    half = U.dtype(0.5)
    A = Q * wp.diag(_clamp_if(d, project)) * wp.transpose(Q)
    tw = _clamp_if(twist, project)
    fl = _clamp_if(flip, project)
    Vt = wp.transpose(V)
    return hessian_point_block(U, A, half * (tw + fl), half * (fl - tw), Vt * ga, Vt * gb)
