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
from warpfem.kernels.generic import both_precisions, splittable
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
    "gather_blocks_kernel",
    "gather_force_kernel",
    "element_slot_maps",
    "no_rows",
]

wp.set_module_options({"enable_backward": False})

#: the fewest quadrature points worth a CPU thread of their own (``kernels.generic.splittable``): a
#: chunk's dispatch costs tens of microseconds; a point's Hessian a few, its force or energy ~0.05; a
#: sequence with a split launch is not captured as a graph (the 864-tet beam's step lost more by that
#: than its Hessian gained)
_HESSIAN_POINTS_MIN = 2048
_POINTS_MIN = 8192


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
def _put_block(values: wp.array(dtype=Any), block_index: wp.array(dtype=wp.int32), slots: int, base: int, k: int,
               a: int, b: int, u: int, blk: Any):
    """Block (a, b) (a <= b) of an element (``block_index`` rows of k x k from ``base``): into its point
    slot u (``slots != 0``), or added with atomics at (a, b) and, for a != b, its transpose at (b, a)."""
    if slots != 0:
        values[u] = blk
    else:
        wp.atomic_add(values, block_index[base + a * k + b], blk)
        if b != a:
            wp.atomic_add(values, block_index[base + b * k + a], wp.transpose(blk))


@splittable("start", _HESSIAN_POINTS_MIN, when=7)
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
    slots: int,
    start: int,
):
    """values[block(e, a, b)] += scale * w d2(psi)/dx_a dx_b (N/m), in place in a fixed pattern
    (``slots == 0``, atomics); or, with ``slots != 0``, the point's upper blocks a <= b written to
    its own slots ``values[q * k (k + 1) / 2 + u]`` (u: the pairs a <= b in row order), which
    ``gather_blocks_kernel`` sums into the matrix in a fixed order (deterministic whatever the
    thread count). ``start``: the first point of this launch (a range split across CPU threads).

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
    q = wp.tid() + start
    k = points.k
    e = points.element[q]
    F = point_deformation_gradient(x, points, q)
    U0, V0, A0, tw, fl = material_hessian_parts(material.kind, F, material.mu, material.lam)
    c = scale * points.weight[q]
    npair = k * (k + 1) // 2
    if k > 4:
        H = hessian_point_matrix(U0, V0, A0, tw, fl, project)
        u = q * npair
        for a in range(k):
            T0, T1, T2 = hessian_matrix_rows(H, points.dNdX[q * k + a])
            for b in range(a, k):  # symmetric: compute a <= b, add the transpose (as OpenTissue's assembly)
                gb = points.dNdX[q * k + b]
                blk = c * wp.matrix_from_rows(T0 * gb, T1 * gb, T2 * gb)
                _put_block(values, block_index, slots, e * k * k, k, a, b, u, blk)
                u += 1
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
        u = q * 10
        _put_block(values, block_index, slots, base, 4, 0, 0, u, K00)
        _put_block(values, block_index, slots, base, 4, 0, 1, u + 1, K01)
        _put_block(values, block_index, slots, base, 4, 0, 2, u + 2, K02)
        _put_block(values, block_index, slots, base, 4, 0, 3, u + 3, K03)
        _put_block(values, block_index, slots, base, 4, 1, 1, u + 4, K11)
        _put_block(values, block_index, slots, base, 4, 1, 2, u + 5, K12)
        _put_block(values, block_index, slots, base, 4, 1, 3, u + 6, K13)
        _put_block(values, block_index, slots, base, 4, 2, 2, u + 7, K22)
        _put_block(values, block_index, slots, base, 4, 2, 3, u + 8, K23)
        _put_block(values, block_index, slots, base, 4, 3, 3, u + 9, K33)
    else:
        U, Vt, A, cp, cm = hessian_point_prepare(U0, V0, A0, tw, fl, project)
        u = q * npair
        for a in range(k):
            ra = Vt * points.dNdX[q * k + a]
            for b in range(a, k):
                blk = c * hessian_point_block(U, A, cp, cm, ra, Vt * points.dNdX[q * k + b])
                _put_block(values, block_index, slots, e * k * k, k, a, b, u, blk)
                u += 1


@splittable("start", 2048)
@both_precisions(contrib="m[]", values="m[]")
@wp.kernel
def gather_blocks_kernel(offsets: wp.array(dtype=wp.int32), entries: wp.array(dtype=wp.int32),
                         contrib: wp.array(dtype=Any), values: wp.array(dtype=Any), start: int):
    """values[p] += sum of the point slots of block p, in the order of ``entries[offsets[p]:offsets[p + 1]]``
    (each entry 2 x slot + 1 for the transpose of the slot's block): the gather half of the
    deterministic assembly (``qp_hessian_kernel`` with ``slots != 0`` wrote the slots)."""
    p = wp.tid() + start
    lo = offsets[p]
    hi = offsets[p + 1]
    if hi > lo:
        acc = values[p]
        for i in range(lo, hi):
            t = entries[i]
            blk = contrib[t >> 1]
            if (t & 1) != 0:
                acc += wp.transpose(blk)
            else:
                acc += blk
        values[p] = acc


@splittable("start", 2048)
@both_precisions(contrib="v[]", f="v[]", f_abs="v[]")
@wp.kernel
def gather_force_kernel(offsets: wp.array(dtype=wp.int32), entries: wp.array(dtype=wp.int32),
                        contrib: wp.array(dtype=Any), f: wp.array(dtype=Any), f_abs: wp.array(dtype=Any),
                        with_abs: int, rows: wp.array(dtype=wp.float64), row_block: int, start: int):
    """f[v] -= sum of the point slots of vertex v, in the order of ``entries[offsets[v]:offsets[v + 1]]``:
    the gather half of the deterministic force (``qp_force_and_abs_kernel`` with ``slots != 0`` wrote
    the slots). ``with_abs`` 1: f_abs[v] += the slots' component-wise magnitudes; 2: f_abs[v] = them
    (no zeroing pass before). ``row_block > 0`` (with ``with_abs``): rows[v / row_block] += f_abs[v] .
    f_abs[v] in float64 afterwards, the partial sums of the magnitude's dot product in blocks of
    vertices of a fixed size (``forms.ElasticForm``: a launch whose chunks start on a block
    boundary gives the same rows whatever the split)."""
    v = wp.tid() + start
    lo = offsets[v]
    hi = offsets[v + 1]
    m = type(f[v])()
    if hi > lo:
        s = m
        for i in range(lo, hi):
            c = contrib[entries[i]]
            s += c
            m += type(c)(wp.abs(c[0]), wp.abs(c[1]), wp.abs(c[2]))
        f[v] = f[v] - s
    if with_abs != 0:
        if with_abs == 1:
            m = f_abs[v] + m
        f_abs[v] = m
        if row_block > 0:
            wp.atomic_add(rows, v / row_block, wp.float64(wp.dot(m, m)))


_NO_ROWS: dict = {}


def no_rows(device):
    """A one-entry float64 array for ``gather_force_kernel``'s ``rows`` when it adds none (``row_block`` 0)."""
    key = str(device)
    a = _NO_ROWS.get(key)
    if a is None:
        a = _NO_ROWS[key] = wp.zeros(1, dtype=wp.float64, device=device)
    return a


@splittable("reduce", _POINTS_MIN, acc=3, slot=4, n_add=2)
@both_precisions(x="v[]", points="qp", material="mat")
@wp.kernel
def qp_energy_sum_kernel(
    x: wp.array(dtype=Any),
    points: Any,
    material: Any,
    acc: wp.array(dtype=wp.float64),
    slot: int,
    start: int,
    row_block: int,
    row_stride: int,
):
    """acc[slot] += sum_q w_q psi(F_q), acc[slot + 1] += sum_q |w_q psi(F_q)| (J, float64 sums):
    the energy and the scale of its round-off, with no per-point array read back. Points q of one
    block of ``row_block`` add to row q / row_block (``row_stride`` apart; 0: one row): partial sums
    that ``kernels.generic.launch`` adds in a fixed order (deterministic whatever the thread count)."""
    q = wp.tid() + start
    r = slot + (q / row_block) * row_stride
    F = point_deformation_gradient(x, points, q)
    e = wp.float64(points.weight[q] * material_psi(material.kind, F, material.mu, material.lam))
    wp.atomic_add(acc, r, e)
    wp.atomic_add(acc, r + 1, wp.abs(e))


@splittable("start", _POINTS_MIN, when=6)
@both_precisions(x="v[]", points="qp", material="mat", scale="s", f="v[]", f_abs="v[]")
@wp.kernel
def qp_force_and_abs_kernel(
    x: wp.array(dtype=Any),
    points: Any,
    material: Any,
    scale: Any,
    f: wp.array(dtype=Any),
    f_abs: wp.array(dtype=Any),
    slots: int,
    start: int,
):
    """``qp_force_kernel`` plus the size of the contributions whose cancellation gives the nodal
    force (the scale of its round-off), in one pass (F and P evaluated once):
    f[node] += -scale w P dN/dX, f_abs[node] += |scale w P dN/dX| component-wise (atomics); with
    ``slots != 0``, f[q k + a] = scale w P dN_a/dX into the point's own slots, which
    ``gather_force_kernel`` sums per vertex in a fixed order (f_abs unused). ``start``: the first
    point of this launch."""
    q = wp.tid() + start
    k = points.k
    e = points.element[q]
    F = point_deformation_gradient(x, points, q)
    P = material_pk1(material.kind, F, material.mu, material.lam)
    c = scale * points.weight[q]
    for a in range(k):
        v = c * (P * points.dNdX[q * k + a])
        if slots != 0:
            f[q * k + a] = v
        else:
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


def element_slot_maps(point_element, elements_flat, k: int, block_index=None, num_vertices: int = 0,
                      nnz: int = 0):
    """The maps of the deterministic (gather) assembly of one quadrature-point set, built once per
    mesh and pattern (numpy int32 arrays, CSR-style):

    - ``(force_offsets, force_entries)``: vertex v's force slots ``q k + a`` (point q's node a is v),
      ``force_entries[force_offsets[v]:force_offsets[v + 1]]`` in increasing order;
    - ``(block_offsets, block_entries)`` (when ``block_index`` is given): block p's entries
      2 x slot (+ 1: the transpose), slot ``q k (k + 1) / 2 + u`` the u-th upper block a <= b of
      point q, in increasing order.

    ``point_element``: per point its element; ``elements_flat``: the connectivity (k per element);
    ``block_index``: (element, a, b) -> block position (``BlockPattern.block_index``)."""
    import numpy as np

    pe = np.asarray(point_element, dtype=np.int64)
    E = np.asarray(elements_flat, dtype=np.int64).reshape(-1, k)
    nq = len(pe)
    nodes = E[pe].ravel()  # (q, a) -> vertex, slot q * k + a
    nv = max(int(num_vertices), int(nodes.max()) + 1 if nodes.size else 0)
    order = np.argsort(nodes, kind="stable")
    f_off = np.zeros(nv + 1, dtype=np.int64)
    np.cumsum(np.bincount(nodes, minlength=nv), out=f_off[1:])
    out = [f_off.astype(np.int32), order.astype(np.int32)]
    if block_index is not None:
        bi = np.asarray(block_index, dtype=np.int64).reshape(-1, k, k)
        a_idx, b_idx = np.triu_indices(k)  # row order: (0,0), (0,1), ..., (k-1,k-1)
        npair = len(a_idx)
        slot = (np.arange(nq, dtype=np.int64)[:, None] * npair + np.arange(npair)[None, :])
        p_ab = bi[pe][:, a_idx, b_idx]  # (nq, npair)
        p_ba = bi[pe][:, b_idx, a_idx]
        off = a_idx != b_idx
        pos = np.concatenate([p_ab.ravel(), p_ba[:, off].ravel()])
        code = np.concatenate([2 * slot.ravel(), 2 * slot[:, off].ravel() + 1])
        o = np.lexsort((code, pos))
        nb = max(int(nnz), int(pos.max()) + 1 if pos.size else 0)
        b_off = np.zeros(nb + 1, dtype=np.int64)
        np.cumsum(np.bincount(pos, minlength=nb), out=b_off[1:])
        out += [b_off.astype(np.int32), code[o].astype(np.int32)]
    return tuple(out)
