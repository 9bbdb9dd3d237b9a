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

__all__ = ["signed_svd", "cofactor", "scaling_eigensystem", "pair_axes", "hessian_block"]


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
def hessian_block(U: Any, V: Any, Q: Any, d: Any, twist: Any, flip: Any, ga: Any, gb: Any, project: int):
    """3x3 block of the Hessian contracted with two vectors: sum_m lambda_m (Q_m ga)(Q_m gb)^T.

    Q_m are the nine 3x3 eigenmatrices (see module docstring), lambda_m their eigenvalues,
    clamped at 0 when ``project != 0`` (SPD projection). In index form
    H[3i+j, 3k+l] = hessian_block(e_j, e_l)[i, k]; for an element, block (a, b) of the
    stiffness is weight * hessian_block(..., dN_a/dX, dN_b/dX, project).

    The contraction is done in the rotated frame a = V^T ga, b = V^T gb, then rotated back with U:
    scaling part  M_pq = (Q diag(d) Q^T)_pq a_p b_q,
    pair (i, j)   M_ii += (t+f)/2 a_j b_j, M_jj += (t+f)/2 a_i b_i,
                  M_ij += (f-t)/2 a_j b_i, M_ji += (f-t)/2 a_i b_j.
    """
    zero = U.dtype(0.0)
    half = U.dtype(0.5)
    Vt = wp.transpose(V)
    a = Vt * ga
    b = Vt * gb
    dd = d
    tw = twist
    fl = flip
    if project != 0:
        dd = wp.vector(wp.max(d[0], zero), wp.max(d[1], zero), wp.max(d[2], zero))
        tw = wp.vector(wp.max(twist[0], zero), wp.max(twist[1], zero), wp.max(twist[2], zero))
        fl = wp.vector(wp.max(flip[0], zero), wp.max(flip[1], zero), wp.max(flip[2], zero))
    A = Q * wp.diag(dd) * wp.transpose(Q)
    M = wp.diag(a) * A * wp.diag(b)
    I = wp.identity(n=3, dtype=U.dtype)
    for k in range(3):
        i, j = pair_axes(k)
        ei = I[i]
        ej = I[j]
        # twist: T a = (a_j e_i - a_i e_j)/sqrt2 ; flip: Fl a = (a_j e_i + a_i e_j)/sqrt2
        ta = a[j] * ei - a[i] * ej
        tb = b[j] * ei - b[i] * ej
        fa = a[j] * ei + a[i] * ej
        fb = b[j] * ei + b[i] * ej
        M = M + (half * tw[k]) * wp.outer(ta, tb) + (half * fl[k]) * wp.outer(fa, fb)
    return U * M * wp.transpose(U)
