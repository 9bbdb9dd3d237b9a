"""Stiffness-warping (corotational linear FEM) kernels for Tet4, generic over float32/float64.

As in OpenTissue's ``fem_stiffness_assembly`` (Müller et al. 2002, "Stable real-time deformations"): each tet keeps its rest 12x12 linear stiffness
as 4x4 blocks K_e,ij (3x3). Every step the element rotation R_e is estimated from the deformation
gradient F = Ds Dm^-1 and

    K'_ij  = sum_e R_e K_e,ij R_e^T          (assembled for i <= j, the transpose added for j > i)
    f0'_i  = -sum_e R_e sum_j K_e,ij X_j     (X = rest positions)

so that the warped elastic force is f = -(K' x + f0') = -sum_e R_e K_e (R_e^T x - X).

Rotation kinds (runtime int, one kernel): 0 identity (plain linear FEM), 1 polar (R = U V^T from
the signed SVD, det U = det V = +1, so R is a proper rotation even for inverted elements),
2 "qr" (Gram-Schmidt on the columns of F, third column = c0 x c1, as OpenTissue did).

The fixed per-tet data (rest positions, connectivity, dN/dX, the blocks K_e) come as one
``WarpedTets32/64`` struct (``warpfem.kernels.structs``); the rotations R are passed on their own.
"""

from __future__ import annotations

from typing import Any

import warp as wp

from warpfem.kernels.common import qp_deformation_gradient
from warpfem.kernels.generic import both_precisions, splittable
from warpfem.materials.eigensystem import signed_svd

wp.set_module_options({"enable_backward": False})

ROTATION_IDENTITY = 0
ROTATION_POLAR = 1
ROTATION_QR = 2


@wp.func
def gram_schmidt_rotation(F: Any):
    """Columns c0 = F e0 / |F e0|, c1 = orthonormalised F e1, c2 = c0 x c1 (OpenTissue's QR).

    A degenerate F (first column or the orthogonalised second column shorter than 1e-12 times
    the largest column) gives the identity."""
    a0 = wp.vector(F[0, 0], F[1, 0], F[2, 0])
    a1 = wp.vector(F[0, 1], F[1, 1], F[2, 1])
    a2 = wp.vector(F[0, 2], F[1, 2], F[2, 2])
    scale = wp.max(wp.length(a0), wp.max(wp.length(a1), wp.length(a2)))
    tiny = F.dtype(1.0e-12) * scale
    R = wp.identity(n=3, dtype=F.dtype)
    l0 = wp.length(a0)
    if l0 > tiny:
        c0 = a0 / l0
        b1 = a1 - wp.dot(c0, a1) * c0
        l1 = wp.length(b1)
        if l1 > tiny:
            c1 = b1 / l1
            c2 = wp.cross(c0, c1)
            R = wp.matrix_from_cols(c0, c1, c2)
    return R


#: the fewest tets worth a CPU thread of their own (``kernels.generic.splittable``)
_TETS_MIN = 4096


@splittable("start", _TETS_MIN)
@both_precisions(x="v[]", tets="tets", R_out="m[]")
@wp.kernel
def element_rotation_kernel(x: wp.array(dtype=Any), tets: Any, rotation: int, R_out: wp.array(dtype=Any), start: int):
    """R_out[e] = rotation of tet e (kind ``rotation``: 0 identity, 1 polar, 2 Gram-Schmidt)."""
    e = wp.tid() + start
    F = qp_deformation_gradient(x, tets.X, tets.elements, 4, e, e, tets.dNdX)  # Tet4: one point per element
    R = wp.identity(n=3, dtype=F.dtype)
    if rotation == 1:
        U, s, V = signed_svd(F)
        R = U * wp.transpose(V)
    elif rotation == 2:
        R = gram_schmidt_rotation(F)
    R_out[e] = R


# split across CPU threads when it writes slots (``slots != 0``: each tet writes its own)
@splittable("start", _TETS_MIN, when=9)
@both_precisions(x="v[]", tets="tets", R="m[]", force_scale="s", values="m[]", f0="v[]", f_el="v[]", f0_slots="v[]",
                 fel_slots="v[]", blk_slots="m[]")
@wp.kernel
def warped_assembly_kernel(
    x: wp.array(dtype=Any),
    tets: Any,
    R: wp.array(dtype=Any),
    force_scale: Any,
    assemble_matrix: int,
    block_index: wp.array(dtype=wp.int32),
    values: wp.array(dtype=Any),
    f0: wp.array(dtype=Any),
    f_el: wp.array(dtype=Any),
    slots: int,
    f0_slots: wp.array(dtype=Any),
    fel_slots: wp.array(dtype=Any),
    blk_slots: wp.array(dtype=Any),
    start: int,
):
    """Warped-stiffness assembly of one tet into a fixed block pattern.

    values[block(e, i, j)] += R K_ij R^T for i <= j and its transpose at block(e, j, i) for j > i
    (when ``assemble_matrix``); f0[i] -= R sum_j K_ij X_j; f_el[i] -= force_scale R sum_j K_ij u_j
    with u_j = R^T (x_j - x_0) - (X_j - X_0): algebraically -(K' x + f0')_i, but free of the
    cancellation between K' x and f0' (sum_j K_ij = 0 removes the reference node's offset).

    ``slots == 0``: scattered with atomics. ``slots != 0``: the tet's terms go to slots of its own
    (``f0_slots[4 e + i]``, ``fel_slots[4 e + i]`` the subtracted terms, ``blk_slots[10 e + u]``
    the u-th upper block i <= j in row order), for ``kernels.fem.gather_force_kernel`` and
    ``gather_blocks_kernel`` to sum in a fixed order (maps from ``kernels.fem.element_slot_maps``).
    """
    e = wp.tid() + start
    X, elements, Ke = tets.X, tets.elements, tets.Ke
    Re = R[e]
    RT = wp.transpose(Re)
    n0 = elements[e * 4]
    u = int(0)
    for i in range(4):
        ni = elements[e * 4 + i]
        Kx0 = X[ni] - X[ni]
        Ku = Kx0
        for j in range(4):
            nj = elements[e * 4 + j]
            Kij = Ke[(e * 4 + i) * 4 + j]
            Kx0 += Kij * X[nj]
            Ku += Kij * (RT * (x[nj] - x[n0]) - (X[nj] - X[n0]))
            if assemble_matrix != 0:
                if j >= i:
                    blk = Re * Kij * RT
                    if slots != 0:
                        blk_slots[e * 10 + u] = blk
                        u += 1
                    else:
                        wp.atomic_add(values, block_index[(e * 4 + i) * 4 + j], blk)
                        if j > i:
                            wp.atomic_add(values, block_index[(e * 4 + j) * 4 + i], wp.transpose(blk))
        if slots != 0:
            f0_slots[e * 4 + i] = Re * Kx0
            fel_slots[e * 4 + i] = force_scale * (Re * Ku)
        else:
            wp.atomic_sub(f0, ni, Re * Kx0)
            wp.atomic_sub(f_el, ni, force_scale * (Re * Ku))


@splittable("start", _TETS_MIN)
@both_precisions(x="v[]", tets="tets", R="m[]", energy_out="s[]")
@wp.kernel
def warped_energy_kernel(x: wp.array(dtype=Any), tets: Any, R: wp.array(dtype=Any), energy_out: wp.array(dtype=Any),
                         start: int):
    """energy_out[e] = 1/2 u^T K_e u with u_j = R^T (x_j - x_0) - (X_j - X_0) (J)."""
    e = wp.tid() + start
    X, elements, Ke = tets.X, tets.elements, tets.Ke
    RT = wp.transpose(R[e])
    n0 = elements[e * 4]
    acc = RT[0, 0] - RT[0, 0]
    for i in range(4):
        ni = elements[e * 4 + i]
        ui = RT * (x[ni] - x[n0]) - (X[ni] - X[n0])
        Ku = ui - ui
        for j in range(4):
            nj = elements[e * 4 + j]
            Ku += Ke[(e * 4 + i) * 4 + j] * (RT * (x[nj] - x[n0]) - (X[nj] - X[n0]))
        acc += wp.dot(ui, Ku)
    energy_out[e] = type(acc)(0.5) * acc
