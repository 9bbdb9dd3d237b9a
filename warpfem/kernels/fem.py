"""Quadrature-point kernels: deformation gradient, energy, force scatter, Hessian assembly.

One kernel per quantity serves every element type and every material: the element is described by
its flat connectivity with stride ``k`` and per-point shape-function gradients, the material by an
int ``kind`` (see ``warpfem.materials``). Kernels are generic over float32/float64.

F = I + sum_a (x_a - X_a) (dN_a/dX)^T         (for Tet4: F = Ds Dm^-1, Sifakis & Barbič 2012 course notes)
f_a -= w P(F) dN_a/dX                          (per-element force -vol P Dm^-T, scattered with atomics)
K_ab += w sum_m lambda_m (Q_m dN_a/dX)(Q_m dN_b/dX)^T   (Hessian from the material eigen-system,
                                                        per-point work hoisted out of the block loop)
"""

from __future__ import annotations

from typing import Any

import warp as wp

from warpfem.kernels.common import qp_deformation_gradient
from warpfem.kernels.generic import both_precisions
from warpfem.materials.dispatch import material_hessian_parts, material_pk1, material_psi
from warpfem.materials.eigensystem import (hessian_matrix_rows, hessian_point_block, hessian_point_matrix,
                                           hessian_point_prepare)

__all__ = [
    "qp_deformation_gradient",
    "qp_deformation_gradient_kernel",
    "qp_energy_kernel",
    "qp_force_kernel",
    "qp_stress_kernel",
    "qp_hessian_kernel",
    "qp_energy_sum_kernel",
    "qp_force_and_abs_kernel",
]

wp.set_module_options({"enable_backward": False})


@both_precisions(x="v[]", X="v[]", qp_dNdX="v[]", F_out="m[]")
@wp.kernel
def qp_deformation_gradient_kernel(
    x: wp.array(dtype=Any),
    X: wp.array(dtype=Any),
    elements: wp.array(dtype=wp.int32),
    k: int,
    qp_element: wp.array(dtype=wp.int32),
    qp_dNdX: wp.array(dtype=Any),
    F_out: wp.array(dtype=Any),
):
    q = wp.tid()
    F_out[q] = qp_deformation_gradient(x, X, elements, k, qp_element[q], q, qp_dNdX)


@both_precisions(x="v[]", X="v[]", qp_dNdX="v[]", qp_weight="s[]", mu="s", lam="s", energy_out="s[]")
@wp.kernel
def qp_energy_kernel(
    x: wp.array(dtype=Any),
    X: wp.array(dtype=Any),
    elements: wp.array(dtype=wp.int32),
    k: int,
    qp_element: wp.array(dtype=wp.int32),
    qp_weight: wp.array(dtype=Any),
    qp_dNdX: wp.array(dtype=Any),
    kind: int,
    mu: Any,
    lam: Any,
    energy_out: wp.array(dtype=Any),
):
    """energy_out[q] = w_q psi(F_q) (J)."""
    q = wp.tid()
    F = qp_deformation_gradient(x, X, elements, k, qp_element[q], q, qp_dNdX)
    energy_out[q] = qp_weight[q] * material_psi(kind, F, mu, lam)


@both_precisions(x="v[]", X="v[]", qp_dNdX="v[]", qp_weight="s[]", mu="s", lam="s", scale="s", f="v[]")
@wp.kernel
def qp_force_kernel(
    x: wp.array(dtype=Any),
    X: wp.array(dtype=Any),
    elements: wp.array(dtype=wp.int32),
    k: int,
    qp_element: wp.array(dtype=wp.int32),
    qp_weight: wp.array(dtype=Any),
    qp_dNdX: wp.array(dtype=Any),
    kind: int,
    mu: Any,
    lam: Any,
    scale: Any,
    f: wp.array(dtype=Any),
):
    """f[node] += -scale * w P dN/dX (N): elastic force, scattered with atomics."""
    q = wp.tid()
    e = qp_element[q]
    F = qp_deformation_gradient(x, X, elements, k, e, q, qp_dNdX)
    P = material_pk1(kind, F, mu, lam)
    c = -scale * qp_weight[q]
    for a in range(k):
        wp.atomic_add(f, elements[e * k + a], c * (P * qp_dNdX[q * k + a]))


@both_precisions(x="v[]", X="v[]", qp_dNdX="v[]", mu="s", lam="s", P_out="m[]")
@wp.kernel
def qp_stress_kernel(
    x: wp.array(dtype=Any),
    X: wp.array(dtype=Any),
    elements: wp.array(dtype=wp.int32),
    k: int,
    qp_element: wp.array(dtype=wp.int32),
    qp_dNdX: wp.array(dtype=Any),
    kind: int,
    mu: Any,
    lam: Any,
    P_out: wp.array(dtype=Any),
):
    """P_out[q] = first Piola-Kirchhoff stress at point q (Pa)."""
    q = wp.tid()
    F = qp_deformation_gradient(x, X, elements, k, qp_element[q], q, qp_dNdX)
    P_out[q] = material_pk1(kind, F, mu, lam)


@both_precisions(x="v[]", X="v[]", qp_dNdX="v[]", qp_weight="s[]", mu="s", lam="s", scale="s", values="m[]")
@wp.kernel
def qp_hessian_kernel(
    x: wp.array(dtype=Any),
    X: wp.array(dtype=Any),
    elements: wp.array(dtype=wp.int32),
    k: int,
    qp_element: wp.array(dtype=wp.int32),
    qp_weight: wp.array(dtype=Any),
    qp_dNdX: wp.array(dtype=Any),
    kind: int,
    mu: Any,
    lam: Any,
    scale: Any,
    project: int,
    block_index: wp.array(dtype=wp.int32),
    values: wp.array(dtype=Any),
):
    """values[block(e, a, b)] += scale * w d2(psi)/dx_a dx_b (N/m), in place in a fixed pattern.

    ``block_index[(e * k + a) * k + b]`` is the position of block (node a, node b) of element e in
    the block-sparse matrix, built once per mesh. ``project != 0`` clamps negative eigenvalues of
    dP/dF (SPD projection) before assembly.

    The per-point part of dP/dF (singular values, the scaling block A = d2Psi/ds2, the projection,
    which needs an eigen-solve of A only where A is indefinite) is done once per point; per block
    only the contraction with the two gradients remains. Two forms, chosen by k at run time
    (measured on CPU, docs/elements.md): for k > 4 (Tet10, Hex8, Hex27) the explicit projected
    9x9 dP/dF (``hessian_point_matrix``), contracted once per node a with dN_a/dX
    (``hessian_matrix_rows``), leaving 27 multiply-adds per block; for Tet4 (10 blocks per
    point, where building the 9x9 costs more than it saves) the compressed eigen form
    (``hessian_point_prepare`` / ``hessian_point_block``, gradients rotated into the singular frame).
    """
    q = wp.tid()
    e = qp_element[q]
    F = qp_deformation_gradient(x, X, elements, k, e, q, qp_dNdX)
    U0, V0, A0, tw, fl = material_hessian_parts(kind, F, mu, lam)
    c = scale * qp_weight[q]
    if k > 4:
        H = hessian_point_matrix(U0, V0, A0, tw, fl, project)
        for a in range(k):
            T0, T1, T2 = hessian_matrix_rows(H, qp_dNdX[q * k + a])
            for b in range(a, k):  # symmetric: compute a <= b, add the transpose (as OpenTissue's assembly)
                gb = qp_dNdX[q * k + b]
                blk = c * wp.matrix_from_rows(T0 * gb, T1 * gb, T2 * gb)
                wp.atomic_add(values, block_index[(e * k + a) * k + b], blk)
                if b != a:
                    wp.atomic_add(values, block_index[(e * k + b) * k + a], wp.transpose(blk))
    else:
        U, Vt, A, cp, cm = hessian_point_prepare(U0, V0, A0, tw, fl, project)
        for a in range(k):
            ra = Vt * qp_dNdX[q * k + a]
            for b in range(a, k):
                blk = c * hessian_point_block(U, A, cp, cm, ra, Vt * qp_dNdX[q * k + b])
                wp.atomic_add(values, block_index[(e * k + a) * k + b], blk)
                if b != a:
                    wp.atomic_add(values, block_index[(e * k + b) * k + a], wp.transpose(blk))


@both_precisions(x="v[]", X="v[]", qp_dNdX="v[]", qp_weight="s[]", mu="s", lam="s")
@wp.kernel
def qp_energy_sum_kernel(
    x: wp.array(dtype=Any),
    X: wp.array(dtype=Any),
    elements: wp.array(dtype=wp.int32),
    k: int,
    qp_element: wp.array(dtype=wp.int32),
    qp_weight: wp.array(dtype=Any),
    qp_dNdX: wp.array(dtype=Any),
    kind: int,
    mu: Any,
    lam: Any,
    acc: wp.array(dtype=wp.float64),
    slot: int,
):
    """acc[slot] += sum_q w_q psi(F_q), acc[slot + 1] += sum_q |w_q psi(F_q)| (J, float64 sums):
    the energy and the scale of its round-off, with no per-point array read back."""
    q = wp.tid()
    F = qp_deformation_gradient(x, X, elements, k, qp_element[q], q, qp_dNdX)
    e = wp.float64(qp_weight[q] * material_psi(kind, F, mu, lam))
    wp.atomic_add(acc, slot, e)
    wp.atomic_add(acc, slot + 1, wp.abs(e))


@both_precisions(x="v[]", X="v[]", qp_dNdX="v[]", qp_weight="s[]", mu="s", lam="s", scale="s", f="v[]", f_abs="v[]")
@wp.kernel
def qp_force_and_abs_kernel(
    x: wp.array(dtype=Any),
    X: wp.array(dtype=Any),
    elements: wp.array(dtype=wp.int32),
    k: int,
    qp_element: wp.array(dtype=wp.int32),
    qp_weight: wp.array(dtype=Any),
    qp_dNdX: wp.array(dtype=Any),
    kind: int,
    mu: Any,
    lam: Any,
    scale: Any,
    f: wp.array(dtype=Any),
    f_abs: wp.array(dtype=Any),
):
    """``qp_force_kernel`` plus the size of the contributions whose cancellation gives the nodal
    force (the scale of its round-off), in one pass (F and P evaluated once):
    f[node] += -scale w P dN/dX, f_abs[node] += |scale w P dN/dX| component-wise."""
    q = wp.tid()
    e = qp_element[q]
    F = qp_deformation_gradient(x, X, elements, k, e, q, qp_dNdX)
    P = material_pk1(kind, F, mu, lam)
    c = scale * qp_weight[q]
    for a in range(k):
        v = c * (P * qp_dNdX[q * k + a])
        node = elements[e * k + a]
        wp.atomic_add(f, node, -v)
        wp.atomic_add(f_abs, node, type(v)(wp.abs(v[0]), wp.abs(v[1]), wp.abs(v[2])))
