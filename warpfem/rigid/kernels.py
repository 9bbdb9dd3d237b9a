"""Kernels of the rigid (affine) bodies, generic over float32/float64 (docs/rigid.md).

The unknown q holds per rigid body four nodes (p, a_1, a_2, a_3: A's columns); a vertex of the
body is at p + sum_k X_k a_k. ``embed_kernel`` maps q to the vertices (X = E q), ``gather_kernel``
a vertex-space gradient back (g_q += E^T g_v, a fixed-order sum per node: deterministic) and
``hessian_map_kernel`` vertex-space Hessian blocks to the unknown's pattern (sum_ab w_a w_b H_ij,
a fixed-order sum per target block). ``orthogonality_*`` evaluate kappa V ||A^T A - I||_F^2.
"""

from __future__ import annotations

from typing import Any

import warp as wp

from warpfem.kernels.generic import both_precisions, splittable

wp.set_module_options({"enable_backward": False})


@both_precisions(q="v[]", local="v[]", out="v[]")
@wp.kernel
def embed_kernel(q: wp.array(dtype=Any), node: wp.array(dtype=wp.int32), rigid: wp.array(dtype=wp.int32),
                 local: wp.array(dtype=Any), out: wp.array(dtype=Any)):
    """out[v] = q[node_v] (soft), or q[p] + X_0 q[p + 1] + X_1 q[p + 2] + X_2 q[p + 3] (rigid)."""
    v = wp.tid()
    k = node[v]
    r = q[k]
    if rigid[v] != 0:
        X = local[v]
        r = r + X[0] * q[k + 1] + X[1] * q[k + 2] + X[2] * q[k + 3]
    out[v] = r


@both_precisions(gv="v[]", local="v[]", g="v[]")
@wp.kernel
def gather_kernel(gv: wp.array(dtype=Any), start: wp.array(dtype=wp.int32), count: wp.array(dtype=wp.int32),
                  comp: wp.array(dtype=wp.int32), local: wp.array(dtype=Any), g: wp.array(dtype=Any)):
    """g[k] += sum over node k's vertices v (in order) of w_v gv[v]; w = 1 for comp 0 (a soft
    vertex, or p), else X_{comp - 1} of the vertex."""
    k = wp.tid()
    c = comp[k]
    acc = g[k] - g[k]
    for v in range(start[k], start[k] + count[k]):
        if c == 0:
            acc = acc + gv[v]
        else:
            acc = acc + local[v][c - 1] * gv[v]
    g[k] = g[k] + acc


@both_precisions(src="m[]", weight="s[]", dst="m[]")
@wp.kernel
def hessian_map_kernel(src: wp.array(dtype=Any), target: wp.array(dtype=wp.int32), start: wp.array(dtype=wp.int32),
                       source: wp.array(dtype=wp.int32), weight: wp.array(dtype=Any), dst: wp.array(dtype=Any)):
    """dst[target[t]] += sum_{e in [start[t], start[t + 1])} weight[e] src[source[e]]."""
    t = wp.tid()
    acc = src[0] - src[0]
    for e in range(start[t], start[t + 1]):
        acc = acc + weight[e] * src[source[e]]
    dst[target[t]] = dst[target[t]] + acc


@wp.func
def _columns(x: wp.array(dtype=Any), k: int):
    return x[k + 1], x[k + 2], x[k + 3]


# sums through rows of partial results (``kernels.generic.splittable``): a fixed order on every device
@splittable("reduce", 4096, acc=3, slot=4, n_add=1)
@both_precisions(x="v[]", kv="s[]")
@wp.kernel
def orthogonality_energy_kernel(x: wp.array(dtype=Any), node: wp.array(dtype=wp.int32), kv: wp.array(dtype=Any),
                                acc: wp.array(dtype=wp.float64), slot: int, start: int, row_block: int, row_stride: int):
    """acc[slot] += kappa V sum_kl (a_k . a_l - delta_kl)^2 per rigid body (float64)."""
    b = wp.tid() + start
    a1, a2, a3 = _columns(x, node[b])
    one = wp.float64(1.0)
    c11 = wp.float64(wp.dot(a1, a1)) - one
    c22 = wp.float64(wp.dot(a2, a2)) - one
    c33 = wp.float64(wp.dot(a3, a3)) - one
    c12 = wp.float64(wp.dot(a1, a2))
    c13 = wp.float64(wp.dot(a1, a3))
    c23 = wp.float64(wp.dot(a2, a3))
    e = c11 * c11 + c22 * c22 + c33 * c33 + wp.float64(2.0) * (c12 * c12 + c13 * c13 + c23 * c23)
    wp.atomic_add(acc, slot + (b // row_block) * row_stride, wp.float64(kv[b]) * e)


@splittable("reduce", 4096, acc=5, slot=6, n_add=1)
@both_precisions(x="v[]", kv="s[]", scale="s", g="v[]")
@wp.kernel
def orthogonality_gradient_kernel(x: wp.array(dtype=Any), node: wp.array(dtype=wp.int32), kv: wp.array(dtype=Any),
                                  scale: Any, g: wp.array(dtype=Any), acc: wp.array(dtype=wp.float64), slot: int,
                                  start: int, row_block: int, row_stride: int):
    """g[a_m] += scale 4 kappa V sum_l C_ml a_l (C = A^T A - I); acc[slot] += |that|^2 (the caller
    passes its row's gradient slot)."""
    b = wp.tid() + start
    k = node[b]
    a1, a2, a3 = _columns(x, k)
    one = a1[0] - a1[0] + type(a1[0])(1.0)
    c11 = wp.dot(a1, a1) - one
    c22 = wp.dot(a2, a2) - one
    c33 = wp.dot(a3, a3) - one
    c12 = wp.dot(a1, a2)
    c13 = wp.dot(a1, a3)
    c23 = wp.dot(a2, a3)
    f = scale * type(scale)(4.0) * kv[b]
    g1 = f * (c11 * a1 + c12 * a2 + c13 * a3)
    g2 = f * (c12 * a1 + c22 * a2 + c23 * a3)
    g3 = f * (c13 * a1 + c23 * a2 + c33 * a3)
    g[k + 1] = g[k + 1] + g1
    g[k + 2] = g[k + 2] + g2
    g[k + 3] = g[k + 3] + g3
    wp.atomic_add(acc, slot + (b // row_block) * row_stride, wp.float64(wp.dot(g1, g1) + wp.dot(g2, g2) + wp.dot(g3, g3)))


@both_precisions(x="v[]", kv="s[]", scale="s", values="m[]")
@wp.kernel
def orthogonality_hessian_kernel(x: wp.array(dtype=Any), node: wp.array(dtype=wp.int32), kv: wp.array(dtype=Any),
                                 scale: Any, blocks: wp.array(dtype=wp.int32), project: int, values: wp.array(dtype=Any)):
    """values[block (m, n)] += scale 4 kappa V (C+_mn I + delta_mn A A^T + a_n a_m^T): the
    Gauss-Newton part (PSD) plus the curvature term with C = A^T A - I clamped to its PSD part
    C+ (``project`` 0: C itself, the exact Hessian). ``blocks``: 9 positions per body, row-major."""
    b = wp.tid()
    k = node[b]
    a1, a2, a3 = _columns(x, k)
    z = a1[0] - a1[0]
    one = z + type(z)(1.0)
    C = wp.matrix(wp.dot(a1, a1) - one, wp.dot(a1, a2), wp.dot(a1, a3),
                  wp.dot(a1, a2), wp.dot(a2, a2) - one, wp.dot(a2, a3),
                  wp.dot(a1, a3), wp.dot(a2, a3), wp.dot(a3, a3) - one, shape=(3, 3), dtype=type(z))
    if project != 0:
        Q, d = wp.eig3(C)
        D = wp.matrix(wp.max(d[0], z), z, z, z, wp.max(d[1], z), z, z, z, wp.max(d[2], z), shape=(3, 3), dtype=type(z))
        C = Q * D * wp.transpose(Q)
    A = wp.matrix_from_cols(a1, a2, a3)
    AAt = A * wp.transpose(A)
    I = wp.identity(n=3, dtype=type(z))
    f = scale * type(scale)(4.0) * kv[b]
    for m in range(3):
        for n in range(3):
            H = C[m, n] * I + wp.outer(A[:, n], A[:, m])
            if m == n:
                H = H + AAt
            p = blocks[9 * b + 3 * m + n]
            values[p] = values[p] + f * H
