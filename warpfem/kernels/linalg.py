"""Vector and block-sparse kernels for the solvers, generic over float32/float64.

Fixed degrees of freedom are a per-vertex mask (vec3, 1 = free, 0 = fixed). Matrices are assembled
as if nothing were fixed; the masked product skips fixed rows and columns and acts as the identity
on fixed components (OpenTissue's "skip the fixed columns"), so vertices can be fixed and
released between solves without touching the sparsity pattern.
"""

from __future__ import annotations

from typing import Any

import warp as wp

from warpfem.kernels.generic import both_precisions, launch, ordered_sums, splittable

wp.set_module_options({"enable_backward": False})

# the fewest vector entries worth a CPU thread of their own (``kernels.generic.splittable``): an
# element-wise pass costs a few ns per entry, a chunk's dispatch some microseconds
_VIEW_MIN = 32768
_REDUCE_MIN = 16384


@wp.func
def cw_mul(a: Any, b: Any):
    return wp.cw_mul(a, b)


@both_precisions(values="m[]", mask="v[]", x="v[]", y="v[]")
@wp.kernel
def bsr_masked_mv_kernel(
    offsets: wp.array(dtype=wp.int32),
    columns: wp.array(dtype=wp.int32),
    values: wp.array(dtype=Any),
    mask: wp.array(dtype=Any),
    x: wp.array(dtype=Any),
    y: wp.array(dtype=Any),
    identity_on_fixed: int,
):
    """y = P A P x (+ (I - P) x when identity_on_fixed), P = diag(mask)."""
    i = wp.tid()
    acc = x[i] - x[i]
    for p in range(offsets[i], offsets[i + 1]):
        j = columns[p]
        acc += values[p] * cw_mul(mask[j], x[j])
    r = cw_mul(mask[i], acc)
    if identity_on_fixed != 0:
        r += x[i] - cw_mul(mask[i], x[i])
    y[i] = r


@splittable("start", 2048)
@both_precisions(values="m[]", x="v[]", alpha="s", y="v[]")
@wp.kernel
def bsr_mv_kernel(
    offsets: wp.array(dtype=wp.int32),
    columns: wp.array(dtype=wp.int32),
    values: wp.array(dtype=Any),
    x: wp.array(dtype=Any),
    alpha: Any,
    y: wp.array(dtype=Any),
    start: int,
):
    """y += alpha A x (no mask)."""
    i = wp.tid() + start
    acc = x[i] - x[i]
    for p in range(offsets[i], offsets[i + 1]):
        acc += values[p] * x[columns[p]]
    y[i] = y[i] + alpha * acc


@both_precisions(values="m[]", mask="v[]", inv_diag="m[]")
@wp.kernel
def block_jacobi_setup_kernel(
    offsets: wp.array(dtype=wp.int32),
    columns: wp.array(dtype=wp.int32),
    values: wp.array(dtype=Any),
    mask: wp.array(dtype=Any),
    inv_diag: wp.array(dtype=Any),
):
    """inv_diag[i] = (P_i A_ii P_i + I - P_i)^-1, the block-Jacobi preconditioner of the masked system."""
    i = wp.tid()
    D = values[offsets[i]] - values[offsets[i]]
    for p in range(offsets[i], offsets[i + 1]):
        if columns[p] == i:
            D = values[p]
    m = mask[i]
    S = wp.diag(m) * D * wp.diag(m)
    one = type(m[0])(1.0)
    S += wp.diag(type(m)(one, one, one) - m)
    if wp.abs(wp.determinant(S)) > type(m[0])(0.0):
        inv_diag[i] = wp.inverse(S)
    else:
        inv_diag[i] = wp.diag(type(m)(one, one, one))


@splittable("view", _VIEW_MIN)
@both_precisions(M="m[]", x="v[]", y="v[]")
@wp.kernel
def block_apply_kernel(M: wp.array(dtype=Any), x: wp.array(dtype=Any), y: wp.array(dtype=Any)):
    i = wp.tid()
    y[i] = M[i] * x[i]


@both_precisions(a="v[]", b="v[]")
@wp.kernel
def dot_kernel(a: wp.array(dtype=Any), b: wp.array(dtype=Any), out: wp.array(dtype=wp.float64)):
    i = wp.tid()
    wp.atomic_add(out, 0, wp.float64(wp.dot(a[i], b[i])))


@splittable("view", _VIEW_MIN)
@both_precisions(alpha="s", x="v[]", y="v[]")
@wp.kernel
def axpy_kernel(alpha: Any, x: wp.array(dtype=Any), y: wp.array(dtype=Any)):
    """y += alpha x."""
    i = wp.tid()
    y[i] = y[i] + alpha * x[i]


@splittable("view", _VIEW_MIN)
@both_precisions(x="v[]", beta="s", y="v[]")
@wp.kernel
def xpby_kernel(x: wp.array(dtype=Any), beta: Any, y: wp.array(dtype=Any)):
    """y = x + beta y."""
    i = wp.tid()
    y[i] = x[i] + beta * y[i]


@splittable("view", _VIEW_MIN)
@both_precisions(a="s", x="v[]", b="s", y="v[]", out="v[]")
@wp.kernel
def lincomb_kernel(a: Any, x: wp.array(dtype=Any), b: Any, y: wp.array(dtype=Any), out: wp.array(dtype=Any)):
    """out = a x + b y."""
    i = wp.tid()
    out[i] = a * x[i] + b * y[i]


@splittable("view", _VIEW_MIN)
@both_precisions(mask="v[]", x="v[]")
@wp.kernel
def mask_kernel(mask: wp.array(dtype=Any), x: wp.array(dtype=Any)):
    """x = P x."""
    i = wp.tid()
    x[i] = cw_mul(mask[i], x[i])


@splittable("view", _VIEW_MIN)
@both_precisions(mask="v[]", free="v[]", fixed="v[]", out="v[]")
@wp.kernel
def select_kernel(mask: wp.array(dtype=Any), free: wp.array(dtype=Any), fixed: wp.array(dtype=Any), out: wp.array(dtype=Any)):
    """out = P free + (I - P) fixed."""
    i = wp.tid()
    m = mask[i]
    out[i] = cw_mul(m, free[i]) + fixed[i] - cw_mul(m, fixed[i])


@wp.kernel
def scale_copy_kernel(src: wp.array(dtype=Any), a: Any, dst: wp.array(dtype=Any)):
    """dst = a src (vec3 or mat33 arrays)."""
    i = wp.tid()
    dst[i] = a * src[i]


both_precisions(src="v[]", a="s", dst="v[]")(scale_copy_kernel)
both_precisions(src="m[]", a="s", dst="m[]")(scale_copy_kernel)
splittable("view", _VIEW_MIN)(scale_copy_kernel)


@wp.kernel
def add_scaled_kernel(src: wp.array(dtype=Any), a: Any, dst: wp.array(dtype=Any)):
    """dst += a src (vec3 or mat33 arrays)."""
    i = wp.tid()
    dst[i] = dst[i] + a * src[i]


both_precisions(src="v[]", a="s", dst="v[]")(add_scaled_kernel)
both_precisions(src="m[]", a="s", dst="m[]")(add_scaled_kernel)
splittable("view", _VIEW_MIN)(add_scaled_kernel)


@splittable("reduce", _REDUCE_MIN, acc=3, slot=4, n_add=1)
@both_precisions(a="v[]", b="v[]")
@wp.kernel
def dot_slot_kernel(a: wp.array(dtype=Any), b: wp.array(dtype=Any), alpha: wp.float64, acc: wp.array(dtype=wp.float64),
                    slot: int, start: int, row_block: int, row_stride: int):
    """acc[slot] += alpha a . b (float64): several reductions land in one small array that is read
    back once (in rows of partial sums on the CPU: ``kernels.generic.splittable``)."""
    i = wp.tid() + start
    wp.atomic_add(acc, slot + (i // row_block) * row_stride, alpha * wp.float64(wp.dot(a[i], b[i])))


def launch_dot(a, b, out, device):
    """out[0] += a . b in float64: one launch of ``dot_kernel`` (on the CPU a launch's threads, and
    so its atomic adds, run in index order), or where sums are made in a fixed order
    (``generic.ORDERED_SUMS``: devices other than the CPU) ``dot_slot_kernel`` through the fixed-order
    reduction of ``generic.launch``."""
    if ordered_sums(device):
        launch(dot_slot_kernel, a.shape[0], [a, b, wp.float64(1.0), out, 0], device)
    else:
        launch(dot_kernel, a.shape[0], [a, b, out], device)


@splittable("reduce", 2048, acc=7, slot=8, n_add=1)
@both_precisions(values="m[]", x="v[]", x0="v[]", alpha="s", y="v[]")
@wp.kernel
def bsr_diff_mv_kernel(
    offsets: wp.array(dtype=wp.int32),
    columns: wp.array(dtype=wp.int32),
    values: wp.array(dtype=Any),
    x: wp.array(dtype=Any),
    x0: wp.array(dtype=Any),
    alpha: Any,
    y: wp.array(dtype=Any),
    acc: wp.array(dtype=wp.float64),
    slot: int,
    want_gradient: int,
    want_energy: int,
    start: int,
    row_block: int,
    row_stride: int,
):
    """With r = A (x - x0): y += alpha r (want_gradient) and acc[slot] += alpha/2 (x - x0) . r
    (want_energy, float64): a quadratic term's gradient or energy in one pass."""
    i = wp.tid() + start
    acc_r = x[i] - x[i]
    for p in range(offsets[i], offsets[i + 1]):
        j = columns[p]
        acc_r += values[p] * (x[j] - x0[j])
    if want_gradient != 0:
        y[i] = y[i] + alpha * acc_r
    if want_energy != 0:
        wp.atomic_add(acc, slot + (i // row_block) * row_stride,
                      wp.float64(0.5) * wp.float64(alpha * wp.dot(x[i] - x0[i], acc_r)))


@splittable("reduce", _REDUCE_MIN, acc=4, slot=5, n_add=1)
@both_precisions(g="v[]", fext="v[]", c="s", mask="v[]")
@wp.kernel
def gradient_finish_kernel(g: wp.array(dtype=Any), fext: wp.array(dtype=Any), c: Any, mask: wp.array(dtype=Any),
                           acc: wp.array(dtype=wp.float64), slot: int, start: int, row_block: int, row_stride: int):
    """g = P (g - c f_ext) and acc[slot] += |g_i|^2 (float64)."""
    i = wp.tid() + start
    v = cw_mul(mask[i], g[i] - c * fext[i])
    g[i] = v
    wp.atomic_add(acc, slot + (i // row_block) * row_stride, wp.float64(wp.dot(v, v)))


@splittable("reduce", _REDUCE_MIN, acc=6, slot=7, n_add=1, n_max=3)
@both_precisions(g="v[]", d="v[]", y="v[]", xb="v[]", s="s")
@wp.kernel
def newton_check_kernel(g: wp.array(dtype=Any), d: wp.array(dtype=Any), y: wp.array(dtype=Any),
                        xb: wp.array(dtype=Any), s: Any, use_xb: int, acc: wp.array(dtype=wp.float64), slot: int,
                        start: int, row_block: int, row_stride: int):
    """acc[slot] += g . d; acc[slot+1..3] = max |d|, max |y|, max |x| (x = x_b + s y, or y without
    x_b): the descent test and the resolution of a Newton step in one pass."""
    i = wp.tid() + start
    r = slot + (i // row_block) * row_stride
    wp.atomic_add(acc, r, wp.float64(wp.dot(g[i], d[i])))
    a = d[i]
    wp.atomic_max(acc, r + 1, wp.float64(wp.max(wp.max(wp.abs(a[0]), wp.abs(a[1])), wp.abs(a[2]))))
    b = y[i]
    wp.atomic_max(acc, r + 2, wp.float64(wp.max(wp.max(wp.abs(b[0]), wp.abs(b[1])), wp.abs(b[2]))))
    x = b
    if use_xb != 0:
        x = xb[i] + s * b
    wp.atomic_max(acc, r + 3, wp.float64(wp.max(wp.max(wp.abs(x[0]), wp.abs(x[1])), wp.abs(x[2]))))


@wp.kernel
def reduce_tree_kernel(src: wp.array(dtype=wp.float64), rows: int, width: int, n_add: int, n_max: int, block: int,
                       dst: wp.array(dtype=wp.float64)):
    """dst[g, j] = the sum (j < n_add; the maximum for the next n_max, the minimum for the rest) of
    src rows g block .. g block + block - 1 (fewer in the last group), column j, in row order: one
    pass of a reduction in a fixed order (``kernels.generic``, sums on devices other than the CPU)."""
    t = wp.tid()
    g = t / width
    j = t - g * width
    r0 = g * block
    r1 = wp.min(rows, r0 + block)
    v = src[r0 * width + j]
    for r in range(r0 + 1, r1):
        w = src[r * width + j]
        if j < n_add:
            v += w
        elif j < n_add + n_max:
            v = wp.max(v, w)
        else:
            v = wp.min(v, w)
    dst[g * width + j] = v


@wp.kernel
def reduce_rows_kernel(part: wp.array(dtype=wp.float64), rows: int, width: int, n_add: int, n_max: int,
                       acc: wp.array(dtype=wp.float64), slot: int):
    """acc[slot + j] += part[0, j] + part[1, j] + ... for j < n_add, in row order; the maximum of
    acc[slot + j] and the rows' for the next n_max, the minimum for the rest: the partial results of
    a reduction split into blocks (``kernels.generic.launch``)."""
    j = wp.tid()
    v = acc[slot + j]
    for r in range(rows):
        if j < n_add:
            v += part[r * width + j]
        elif j < n_add + n_max:
            v = wp.max(v, part[r * width + j])
        else:
            v = wp.min(v, part[r * width + j])
    acc[slot + j] = v


@wp.kernel
def init_rows_kernel(part: wp.array(dtype=wp.float64), width: int, n_add: int, n_max: int):
    """The rows of partial results before a reduction: 0 for sums, -inf for maxima, +inf for minima."""
    t = wp.tid()
    j = t % width
    v = wp.float64(0.0)
    if j >= n_add + n_max:
        v = wp.float64(wp.inf)
    elif j >= n_add:
        v = -wp.float64(wp.inf)
    part[t] = v
