"""Quadrature-point kernels: deformation gradient, energy, force scatter, Hessian assembly.

One kernel per quantity serves every element type and every material: the element is described by
its flat connectivity with stride ``k`` and per-point shape-function gradients, the material by an
int ``kind`` (see ``warpfem.materials``). Kernels are generic over float32/float64. Every kernel
takes the positions ``x``, the point set ``points`` (a ``QuadraturePoints32/64`` struct: rest
positions, connectivity, k, point -> element, weights, dN/dX) and, where it evaluates the
material, ``material`` (a ``MaterialParams32/64``: kind, mu, lam), both from
``warpfem.kernels.structs``; then its own scale, flags and outputs.

F = I + sum_a (x_a - X_a) (dN_a/dX)^T         (for Tet4: F = Ds Dm^-1, Sifakis & Barbič 2012 course notes)
f_a -= w P(F) dN_a/dX                          (per-element force -vol P Dm^-T, scattered with atomics)
K_ab += w sum_m lambda_m (Q_m dN_a/dX)(Q_m dN_b/dX)^T   (Hessian from the material eigen-system,
                                                        per-point work hoisted out of the block loop)
"""

from __future__ import annotations

from typing import Any

import warp as wp

from warpfem.kernels.common import point_deformation_gradient, qp_deformation_gradient
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
    "qp_parameter_work_kernel",
]

wp.set_module_options({"enable_backward": False})


@both_precisions(x="v[]", points="qp", F_out="m[]")
@wp.kernel
def qp_deformation_gradient_kernel(x: wp.array(dtype=Any), points: Any, F_out: wp.array(dtype=Any)):
    q = wp.tid()
    F_out[q] = point_deformation_gradient(x, points, q)


@both_precisions(x="v[]", points="qp", material="mat", energy_out="s[]")
@wp.kernel
def qp_energy_kernel(x: wp.array(dtype=Any), points: Any, material: Any, energy_out: wp.array(dtype=Any)):
    """energy_out[q] = w_q psi(F_q) (J)."""
    q = wp.tid()
    F = point_deformation_gradient(x, points, q)
    energy_out[q] = points.weight[q] * material_psi(material.kind, F, material.mu, material.lam)


@both_precisions(x="v[]", points="qp", material="mat", scale="s", f="v[]")
@wp.kernel
def qp_force_kernel(x: wp.array(dtype=Any), points: Any, material: Any, scale: Any, f: wp.array(dtype=Any)):
    """f[node] += -scale * w P dN/dX (N): elastic force, scattered with atomics."""
    q = wp.tid()
    k = points.k
    e = points.element[q]
    F = point_deformation_gradient(x, points, q)
    P = material_pk1(material.kind, F, material.mu, material.lam)
    c = -scale * points.weight[q]
    for a in range(k):
        wp.atomic_add(f, points.elements[e * k + a], c * (P * points.dNdX[q * k + a]))


@both_precisions(x="v[]", points="qp", material="mat", P_out="m[]")
@wp.kernel
def qp_stress_kernel(x: wp.array(dtype=Any), points: Any, material: Any, P_out: wp.array(dtype=Any)):
    """P_out[q] = first Piola-Kirchhoff stress at point q (Pa)."""
    q = wp.tid()
    F = point_deformation_gradient(x, points, q)
    P_out[q] = material_pk1(material.kind, F, material.mu, material.lam)


@wp.func
def _add_block(values: wp.array(dtype=Any), block_index: wp.array(dtype=wp.int32), base: int, a: int, b: int, blk: Any):
    wp.atomic_add(values, block_index[base + a * 4 + b], blk)


@wp.func
def _add_pair(values: wp.array(dtype=Any), block_index: wp.array(dtype=wp.int32), base: int, a: int, b: int, blk: Any):
    """Blocks (a, b) and (b, a) = blk^T of a 4-node element (``block_index`` rows of 16)."""
    wp.atomic_add(values, block_index[base + a * 4 + b], blk)
    wp.atomic_add(values, block_index[base + b * 4 + a], wp.transpose(blk))


@both_precisions(x="v[]", points="qp", material="mat", scale="s", values="m[]")
@wp.kernel
def qp_hessian_kernel(
    x: wp.array(dtype=Any),
    points: Any,
    material: Any,
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
    (``hessian_point_prepare`` / ``hessian_point_block``, gradients rotated into the singular frame),
    with 6 contractions instead of 10: the gradients of a 4-node element sum to zero (partition of
    unity), so the last node's blocks are sums of the others' (the same matrix up to round-off).
    """
    q = wp.tid()
    k = points.k
    e = points.element[q]
    F = point_deformation_gradient(x, points, q)
    U0, V0, A0, tw, fl = material_hessian_parts(material.kind, F, material.mu, material.lam)
    c = scale * points.weight[q]
    if k > 4:
        H = hessian_point_matrix(U0, V0, A0, tw, fl, project)
        for a in range(k):
            T0, T1, T2 = hessian_matrix_rows(H, points.dNdX[q * k + a])
            for b in range(a, k):  # symmetric: compute a <= b, add the transpose (as OpenTissue's assembly)
                gb = points.dNdX[q * k + b]
                blk = c * wp.matrix_from_rows(T0 * gb, T1 * gb, T2 * gb)
                wp.atomic_add(values, block_index[(e * k + a) * k + b], blk)
                if b != a:
                    wp.atomic_add(values, block_index[(e * k + b) * k + a], wp.transpose(blk))
    elif k == 4:
        # four nodes: the gradients sum to zero (partition of unity), so the blocks of the last node
        # are sums of the others' (K_a3 = -sum_b<3 K_ab, K_33 = -sum_a<3 K_a3): 6 contractions, not 10
        U, Vt, A, cp, cm = hessian_point_prepare(U0, V0, A0, tw, fl, project)
        base = e * 16
        r0 = Vt * points.dNdX[q * 4]
        r1 = Vt * points.dNdX[q * 4 + 1]
        r2 = Vt * points.dNdX[q * 4 + 2]
        K00 = c * hessian_point_block(U, A, cp, cm, r0, r0)
        K01 = c * hessian_point_block(U, A, cp, cm, r0, r1)
        K02 = c * hessian_point_block(U, A, cp, cm, r0, r2)
        K11 = c * hessian_point_block(U, A, cp, cm, r1, r1)
        K12 = c * hessian_point_block(U, A, cp, cm, r1, r2)
        K22 = c * hessian_point_block(U, A, cp, cm, r2, r2)
        K03 = -(K00 + K01 + K02)
        K13 = -(wp.transpose(K01) + K11 + K12)
        K23 = -(wp.transpose(K02) + wp.transpose(K12) + K22)
        # K_33 = sum_{a, b < 3} K_ab = D + O + O^T, D = K00 + K11 + K22, O = K01 + K02 + K12, summed so
        # that it is exactly symmetric in floating point
        D = K00 + K11 + K22
        O = K01 + K02 + K12
        K33 = type(c)(0.5) * (D + wp.transpose(D)) + (O + wp.transpose(O))
        _add_block(values, block_index, base, 0, 0, K00)
        _add_pair(values, block_index, base, 0, 1, K01)
        _add_pair(values, block_index, base, 0, 2, K02)
        _add_pair(values, block_index, base, 0, 3, K03)
        _add_block(values, block_index, base, 1, 1, K11)
        _add_pair(values, block_index, base, 1, 2, K12)
        _add_pair(values, block_index, base, 1, 3, K13)
        _add_block(values, block_index, base, 2, 2, K22)
        _add_pair(values, block_index, base, 2, 3, K23)
        _add_block(values, block_index, base, 3, 3, K33)
    else:
        U, Vt, A, cp, cm = hessian_point_prepare(U0, V0, A0, tw, fl, project)
        for a in range(k):
            ra = Vt * points.dNdX[q * k + a]
            for b in range(a, k):
                blk = c * hessian_point_block(U, A, cp, cm, ra, Vt * points.dNdX[q * k + b])
                wp.atomic_add(values, block_index[(e * k + a) * k + b], blk)
                if b != a:
                    wp.atomic_add(values, block_index[(e * k + b) * k + a], wp.transpose(blk))


@both_precisions(x="v[]", points="qp", material="mat")
@wp.kernel
def qp_energy_sum_kernel(
    x: wp.array(dtype=Any),
    points: Any,
    material: Any,
    acc: wp.array(dtype=wp.float64),
    slot: int,
):
    """acc[slot] += sum_q w_q psi(F_q), acc[slot + 1] += sum_q |w_q psi(F_q)| (J, float64 sums):
    the energy and the scale of its round-off, with no per-point array read back."""
    q = wp.tid()
    F = point_deformation_gradient(x, points, q)
    e = wp.float64(points.weight[q] * material_psi(material.kind, F, material.mu, material.lam))
    wp.atomic_add(acc, slot, e)
    wp.atomic_add(acc, slot + 1, wp.abs(e))


@both_precisions(x="v[]", points="qp", material="mat", scale="s", f="v[]", f_abs="v[]")
@wp.kernel
def qp_force_and_abs_kernel(
    x: wp.array(dtype=Any),
    points: Any,
    material: Any,
    scale: Any,
    f: wp.array(dtype=Any),
    f_abs: wp.array(dtype=Any),
):
    """``qp_force_kernel`` plus the size of the contributions whose cancellation gives the nodal
    force (the scale of its round-off), in one pass (F and P evaluated once):
    f[node] += -scale w P dN/dX, f_abs[node] += |scale w P dN/dX| component-wise."""
    q = wp.tid()
    k = points.k
    e = points.element[q]
    F = point_deformation_gradient(x, points, q)
    P = material_pk1(material.kind, F, material.mu, material.lam)
    c = scale * points.weight[q]
    for a in range(k):
        v = c * (P * points.dNdX[q * k + a])
        node = points.elements[e * k + a]
        wp.atomic_add(f, node, -v)
        wp.atomic_add(f_abs, node, type(v)(wp.abs(v[0]), wp.abs(v[1]), wp.abs(v[2])))


@both_precisions(x="v[]", points="qp", material="mat", w="v[]", out="s[,]")
@wp.kernel
def qp_parameter_work_kernel(x: wp.array(dtype=Any), points: Any, material: Any, w: wp.array(dtype=Any),
                             out: wp.array2d(dtype=Any)):
    """out[q] = (P(F; 1, 0) : G, P(F; 0, 1) : G), G = sum_a w_a (dN_a/dX)^T: the work of the two
    unit-parameter stresses on the field w at point q (unweighted). Every material's stress is
    linear in its kernel parameters, P = mu P(F; 1, 0) + lam P(F; 0, 1), so w . dV/dmu and
    w . dV/dlam are sums of weight x these, and P(F) : G their combination (the adjoint's
    parameter gradients, ``warpfem.solvers.adjoint``: one pass, no atomics)."""
    q = wp.tid()
    k = points.k
    e = points.element[q]
    F = point_deformation_gradient(x, points, q)
    G = F - F
    for a in range(k):
        G = G + wp.outer(w[points.elements[e * k + a]], points.dNdX[q * k + a])
    one = type(material.mu)(1.0)
    zero = material.mu - material.mu
    out[q, 0] = wp.ddot(material_pk1(material.kind, F, one, zero), G)
    out[q, 1] = wp.ddot(material_pk1(material.kind, F, zero, one), G)
