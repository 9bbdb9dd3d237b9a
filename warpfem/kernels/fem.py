"""Quadrature-point kernels: deformation gradient, energy, force scatter, Hessian assembly.

One kernel per quantity serves every element type and every material: the element is described by
its flat connectivity with stride ``k`` and per-point shape-function gradients, the material by an
int ``kind`` (see ``warpfem.materials``). Kernels are generic over float32/float64.

F = I + sum_a (x_a - X_a) (dN_a/dX)^T         (for Tet4: F = Ds Dm^-1, seed 004)
f_a -= w P(F) dN_a/dX                          (per-element force -vol P Dm^-T, scattered with atomics)
K_ab += w sum_m lambda_m (Q_m dN_a/dX)(Q_m dN_b/dX)^T   (Hessian from the material eigen-system)
"""

from __future__ import annotations

from typing import Any

import warp as wp

from warpfem.kernels.generic import both_precisions
from warpfem.materials.dispatch import material_eigensystem, material_pk1, material_psi
from warpfem.materials.eigensystem import hessian_block

wp.set_module_options({"enable_backward": False})


@wp.func
def qp_deformation_gradient(
    x: wp.array(dtype=Any),
    X: wp.array(dtype=Any),
    elements: wp.array(dtype=wp.int32),
    k: int,
    e: int,
    q: int,
    qp_dNdX: wp.array(dtype=Any),
):
    """F = I + sum_a (x_a - X_a) (dN_a/dX)^T: from displacements, so float32 keeps small strains
    accurate wherever the body sits (sum_a X_a dN_a^T = I exactly for any complete element)."""
    n0 = elements[e * k]
    g0 = qp_dNdX[q * k]
    F = wp.outer(x[n0] - X[n0], g0)
    for a in range(1, k):
        n = elements[e * k + a]
        F += wp.outer(x[n] - X[n], qp_dNdX[q * k + a])
    one = type(g0[0])(1.0)
    return F + wp.diag(type(g0)(one, one, one))


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


@both_precisions(x="v[]", X="v[]", qp_dNdX="v[]", qp_weight="s[]", mu="s", lam="s", scale="s", f_abs="v[]")
@wp.kernel
def qp_force_abs_kernel(
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
    f_abs: wp.array(dtype=Any),
):
    """f_abs[node] += |scale w P dN/dX| component-wise: the size of the contributions whose
    cancellation gives the nodal force, i.e. the scale of the force's round-off error."""
    q = wp.tid()
    e = qp_element[q]
    F = qp_deformation_gradient(x, X, elements, k, e, q, qp_dNdX)
    P = material_pk1(kind, F, mu, lam)
    c = scale * qp_weight[q]
    for a in range(k):
        v = c * (P * qp_dNdX[q * k + a])
        wp.atomic_add(f_abs, elements[e * k + a], type(v)(wp.abs(v[0]), wp.abs(v[1]), wp.abs(v[2])))


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
    """
    q = wp.tid()
    e = qp_element[q]
    F = qp_deformation_gradient(x, X, elements, k, e, q, qp_dNdX)
    U, V, Qs, ds, tw, fl = material_eigensystem(kind, F, mu, lam)
    c = scale * qp_weight[q]
    for a in range(k):
        ga = qp_dNdX[q * k + a]
        for b in range(a, k):  # symmetric: compute a <= b, add the transpose (seed 001)
            blk = c * hessian_block(U, V, Qs, ds, tw, fl, ga, qp_dNdX[q * k + b], project)
            wp.atomic_add(values, block_index[(e * k + a) * k + b], blk)
            if b != a:
                wp.atomic_add(values, block_index[(e * k + b) * k + a], wp.transpose(blk))
