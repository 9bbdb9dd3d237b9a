"""Reduced-space (subspace) kernels: cubature force/stiffness and reconstruction (An, Kim & James 2008,
"Optimizing cubature for efficient integration of subspace deformations").

The basis U (3n x r) is stored as a 2-d array of vec3, ``U[v, j]`` = the displacement of vertex v
in column j, so x = X + U q is ``x[v] = X[v] + sum_j U[v, j] q[j]``.

Per cubature element c (element e, weight w_c; ``cub_weight[c] = w_c * vol_e``):

    u_a = sum_j U[n_a, j] q_j                          (gather, O(4 r))
    F   = I + sum_a u_a (dN_a/dX)^T,   P = P(F)
    f_a = -cub_weight P dN_a/dX                         (element node forces, N)
    H_ab = cub_weight * C[dN_a/dX, dN_b/dX]            (element stiffness blocks, N/m)
    f_r[j]    += sum_a U[n_a, j] . f_a                  (r-vector)
    K_r[j, l] += sum_ab U[n_a, j]^T H_ab U[n_b, l]      (r x r)

The cubature points come as a ``QuadraturePoints32/64`` struct and the material as a
``MaterialParams32/64`` (``warpfem.kernels.structs``, as the kernels of ``fem.py``).
Only cubature elements are touched. Two launches: one per element (material evaluation, dim =
number of cubature points), one per entry (j, l) of the reduced stiffness for the projections (dim
(r, r)), each summing over the cubature points in their order: no atomics, the same sums on every
device and thread count.

The reduced simulator's hot path uses :func:`cubature_point_kernel` instead: F is affine in the
reduced coordinates, F_c = I + G_c z with G_c = dF/dz (9 x r, constant), so the host forms F for
every cubature point with one matrix-vector product and the kernel only evaluates the material
per point: w psi, w P and (when asked) the 9 x 9 w dP/dF. The reductions f_r = -sum_c G_c^T vec(w P)
and K_r = sum_c G_c^T (w dP/dF) G_c are dense products on the host (``warpfem.reduced.simulator``).
"""

from __future__ import annotations

from typing import Any

import warp as wp

from warpfem.kernels.generic import both_precisions, splittable
from warpfem.materials.dispatch import material_hessian_parts, material_pk1, material_psi
from warpfem.materials.eigensystem import cofactor, hessian_point_block, hessian_point_prepare

wp.set_module_options({"enable_backward": False})


_both = both_precisions  # roles include "v[,]" (2-d array of vec3)


@wp.func
def _gather(U: wp.array2d(dtype=Any), q: wp.array(dtype=Any), node: int):
    u = U[node, 0] * q[0]
    for j in range(1, U.shape[1]):
        u += U[node, j] * q[j]
    return u


@_both(U="v[,]", q="s[]", points="qp", material="mat", energy_out="s[]", f_out="v[]", H_out="m[]")
@wp.kernel
def cubature_element_kernel(
    U: wp.array2d(dtype=Any),
    q: wp.array(dtype=Any),
    points: Any,
    material: Any,
    want_hessian: int,
    project: int,
    energy_out: wp.array(dtype=Any),
    f_out: wp.array(dtype=Any),
    H_out: wp.array(dtype=Any),
):
    """Per cubature point: energy w psi (J), node forces f_a (N), stiffness blocks H_ab (N/m).

    ``points``: the cubature points as a ``QuadraturePoints32/64`` (``warpfem.kernels.structs``)
    over the cubature tets only: Tet4 (k = 4), one point per tet (``element[c] = c``), weight =
    cubature weight x volume; its rest positions are not used (F comes from the displacement U q).
    """
    c = wp.tid()
    e = points.element[c]
    g0 = points.dNdX[c * 4]
    F = wp.outer(_gather(U, q, points.elements[e * 4]), g0)
    for a in range(1, 4):
        F += wp.outer(_gather(U, q, points.elements[e * 4 + a]), points.dNdX[c * 4 + a])
    one = type(g0[0])(1.0)
    F = F + wp.diag(type(g0)(one, one, one))
    w = points.weight[c]
    kind, mu, lam = material.kind, material.mu, material.lam
    energy_out[c] = w * material_psi(kind, F, mu, lam)
    P = material_pk1(kind, F, mu, lam)
    for a in range(4):
        f_out[c * 4 + a] = -w * (P * points.dNdX[c * 4 + a])
    if want_hessian != 0:
        # dP/dF once per point (shared with the full assembly, warpfem.kernels.fem), then the
        # 10 blocks a <= b from gradients rotated into the singular frame; H_ba = H_ab^T.
        U0, V0, A0, tw, fl = material_hessian_parts(kind, F, mu, lam)
        Uh, Vt, A, cp, cm = hessian_point_prepare(U0, V0, A0, tw, fl, project)
        for a in range(4):
            ra = Vt * points.dNdX[c * 4 + a]
            for b in range(a, 4):
                blk = w * hessian_point_block(Uh, A, cp, cm, ra, Vt * points.dNdX[c * 4 + b])
                H_out[c * 16 + a * 4 + b] = blk
                if b != a:
                    H_out[c * 16 + b * 4 + a] = wp.transpose(blk)


@_both(U="v[,]", points="qp", f_in="v[]", H_in="m[]", force="s[]", K="s[,]")
@wp.kernel
def cubature_project_kernel(
    U: wp.array2d(dtype=Any),
    points: Any,
    f_in: wp.array(dtype=Any),
    H_in: wp.array(dtype=Any),
    want_hessian: int,
    count: int,
    force: wp.array(dtype=Any),
    K: wp.array2d(dtype=Any),
):
    """Thread (j, l) (dim (r, r), or (r, 1) without the Hessian): force[j] += sum_c sum_a U[n_a, j] . f_a
    (l = 0) and K[j, l] += sum_c sum_b y_b . U[n_b, l], y_b = sum_a H_ab^T U[n_a, j], the sums over
    the ``count`` cubature points taken in their order (no atomics: the same numbers on every
    device)."""
    j, l = wp.tid()
    fs = f_in[0][0] - f_in[0][0]
    ks = fs
    for c in range(count):
        e = points.element[c]
        n0 = points.elements[e * 4]
        n1 = points.elements[e * 4 + 1]
        n2 = points.elements[e * 4 + 2]
        n3 = points.elements[e * 4 + 3]
        u0 = U[n0, j]
        u1 = U[n1, j]
        u2 = U[n2, j]
        u3 = U[n3, j]
        b = c * 4
        if l == 0:
            fs += wp.dot(u0, f_in[b]) + wp.dot(u1, f_in[b + 1]) + wp.dot(u2, f_in[b + 2]) + wp.dot(u3, f_in[b + 3])
        if want_hessian != 0:
            h = c * 16
            y0 = wp.transpose(H_in[h + 0]) * u0 + wp.transpose(H_in[h + 4]) * u1 + wp.transpose(H_in[h + 8]) * u2 + wp.transpose(H_in[h + 12]) * u3
            y1 = wp.transpose(H_in[h + 1]) * u0 + wp.transpose(H_in[h + 5]) * u1 + wp.transpose(H_in[h + 9]) * u2 + wp.transpose(H_in[h + 13]) * u3
            y2 = wp.transpose(H_in[h + 2]) * u0 + wp.transpose(H_in[h + 6]) * u1 + wp.transpose(H_in[h + 10]) * u2 + wp.transpose(H_in[h + 14]) * u3
            y3 = wp.transpose(H_in[h + 3]) * u0 + wp.transpose(H_in[h + 7]) * u1 + wp.transpose(H_in[h + 11]) * u2 + wp.transpose(H_in[h + 15]) * u3
            ks += wp.dot(y0, U[n0, l]) + wp.dot(y1, U[n1, l]) + wp.dot(y2, U[n2, l]) + wp.dot(y3, U[n3, l])
    if l == 0:
        force[j] = force[j] + fs
    if want_hessian != 0:
        K[j, l] = K[j, l] + ks


# split across CPU threads with the Hessian (a few microseconds per point; each point writes its own
# outputs) for 256 points or more; without it a point costs less than a chunk's dispatch
@splittable("start", 128, when=3)
@_both(F="m[]", points="qp", material="mat", psi_out="s[]", P_out="m[]", D_out="s[]")
@wp.kernel
def cubature_point_kernel(
    F: wp.array(dtype=Any),
    points: Any,
    material: Any,
    want_hessian: int,
    project: int,
    snh_closed_form: int,
    psi_out: wp.array(dtype=Any),
    P_out: wp.array(dtype=Any),
    D_out: wp.array(dtype=Any),
    start: int,
):
    """Per cubature point c at the given deformation gradient F[c]: psi_out[c] = w psi (J),
    P_out[c] = w P (N m), and with ``want_hessian`` D_out[81 c + 9 (3i+j) + 3k+l] = w dP_ij/dF_kl
    (row-major vec of F; SPD-projected per point when ``project != 0``). w = points.weight[c] (the
    cubature points, one per cubature tet); ``material``: kind and kernel parameters.

    ``snh_closed_form`` (the material is stable neo-Hookean, P = mu (F - cof F) + lam (J - 1) cof F)
    with ``project == 0``: the exact dP/dF in closed form, no SVD (about 5x cheaper):
    mu I + lam vec(cof F) vec(cof F)^T + (lam (J - 1) - mu) d cof(F)/dF, with
    d cof(F)_ij / dF_kl = e_ikm e_jln F_mn (e: the permutation symbol)."""
    c = wp.tid() + start
    Fc = F[c]
    w = points.weight[c]
    kind, mu, lam = material.kind, material.mu, material.lam
    psi_out[c] = w * material_psi(kind, Fc, mu, lam)
    P_out[c] = w * material_pk1(kind, Fc, mu, lam)
    if want_hessian != 0 and snh_closed_form != 0 and project == 0:
        Cf = cofactor(Fc)
        coef = lam * (wp.determinant(Fc) - type(w)(1.0)) - mu
        b = c * 81
        for i in range(3):
            for j in range(3):
                row = b + (3 * i + j) * 9
                for k in range(3):
                    for l in range(3):
                        val = lam * Cf[i, j] * Cf[k, l]
                        if i == k and j == l:
                            val = val + mu
                        if i != k and j != l:
                            t = coef * Fc[3 - i - k, 3 - j - l]
                            if ((k - i + 3) % 3 == 1) != ((l - j + 3) % 3 == 1):
                                t = -t
                            val = val + t
                        D_out[row + 3 * k + l] = w * val
    elif want_hessian != 0:
        # block (j, l) of dP/dF: B[i, k] = dP_ij/dF_kl, the element-block contraction
        # (hessian_point_block) with the unit gradients e_j, e_l (rotated: columns of V^T); 6 blocks
        # j <= l, the others by the symmetry of dP/dF. (Cheaper than the explicit 9 x 9 product.)
        U0, V0, A0, tw, fl = material_hessian_parts(kind, Fc, mu, lam)
        Uh, Vt, A, cp, cm = hessian_point_prepare(U0, V0, A0, tw, fl, project)
        b = c * 81
        for j in range(3):
            ej = type(Fc[0])(Vt[0, j], Vt[1, j], Vt[2, j])
            for l in range(j, 3):
                el = type(Fc[0])(Vt[0, l], Vt[1, l], Vt[2, l])
                blk = w * hessian_point_block(Uh, A, cp, cm, ej, el)
                for i in range(3):
                    for k in range(3):
                        D_out[b + (3 * i + j) * 9 + 3 * k + l] = blk[i, k]
                        if l != j:
                            D_out[b + (3 * k + l) * 9 + 3 * i + j] = blk[i, k]


@_both(X="v[]", U="v[,]", q="s[]", x_out="v[]")
@wp.kernel
def reconstruct_kernel(
    X: wp.array(dtype=Any),
    U: wp.array2d(dtype=Any),
    q: wp.array(dtype=Any),
    x_out: wp.array(dtype=Any),
):
    """x_out[v] = X[v] + sum_j U[v, j] q[j]: full mesh (U) or render surface (W U, W X), O(r) per point."""
    v = wp.tid()
    x_out[v] = X[v] + _gather(U, q, v)
