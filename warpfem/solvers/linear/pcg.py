"""Block-Jacobi preconditioned conjugate gradients with the scalars kept on the device.

The classic loop (one host read-back per dot product to form alpha and beta) is replaced by a
loop whose alpha, beta and stopping decisions are computed by the kernels themselves from float64
scalars in device memory. The host reads a 4-number report once per chunk of ``check_every``
iterations; iterations after convergence inside a chunk are no-ops (each kernel checks the device
status first). Per iteration: three launches (masked product + p.Ap; x, r, z update + r.z, r.r;
direction update), per chunk one bookkeeping launch and one read-back.

Every launch of a chunk has fixed arguments: the launches are recorded once (``record_cmd``) and
replayed, which skips Warp's per-launch argument handling, and on CUDA the chunk is captured once
as a graph and replayed (``use_cuda_graph``); the right-hand side and solution are copied through internal
buffers so the graph does not depend on the caller's arrays. The scalars of iteration j live in
slot j of small per-chunk arrays (rz, rr, pAp, status, iteration count), so no kernel reads a
value another thread of the same launch writes.

Algorithm: preconditioned CG as in "An Introduction to the Conjugate Gradient Method Without the
Agonizing Pain" (Shewchuk), with the masked operator (P A P + I - P) of the Newton systems.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import warp as wp

from warpfem.kernels.generic import (COUNTERS, RecordedLaunch, both_precisions, ordered_sum_launches, ordered_sums,
                                     splittable)
from warpfem.kernels.linalg import cw_mul
from warpfem.solvers.linear.base import LinearSolver, LinearSolveResult
from warpfem.transfer import read, strict_device

log = logging.getLogger(__name__)

wp.set_module_options({"enable_backward": False})

# status codes (device): 1 running; the rest say why the iteration stopped
_RUNNING, _CONVERGED, _MAXITER, _NEGATIVE, _NONFINITE = 1, 2, 3, 4, 5
_REASONS = {_CONVERGED: "converged", _MAXITER: "iteration cap", _NEGATIVE: "non-positive curvature",
            _NONFINITE: "non-finite residual"}


@both_precisions(b="v[]", inv_diag="m[]", x="v[]", r="v[]", z="v[]", p="v[]")
@wp.kernel
def _pcg_init_kernel(b: wp.array(dtype=Any), inv_diag: wp.array(dtype=Any), x: wp.array(dtype=Any),
                     r: wp.array(dtype=Any), z: wp.array(dtype=Any), p: wp.array(dtype=Any),
                     rz: wp.array(dtype=wp.float64), rr: wp.array(dtype=wp.float64), slot: int, row_block: int,
                     row_stride: int):
    """x = 0, r = b, z = M^-1 r, p = z; rz[slot] += r.z, rr[slot] += r.r (index i adds into entry
    slot + (i // row_block) row_stride: a row of its own for the fixed-order sums, ``DevicePCG``)."""
    i = wp.tid()
    bi = b[i]
    zi = inv_diag[i] * bi
    x[i] = bi - bi
    r[i] = bi
    z[i] = zi
    p[i] = zi
    q = slot + (i // row_block) * row_stride
    wp.atomic_add(rz, q, wp.float64(wp.dot(bi, zi)))
    wp.atomic_add(rr, q, wp.float64(wp.dot(bi, bi)))


@wp.kernel
def _pcg_start_kernel(rr: wp.array(dtype=wp.float64), status: wp.array(dtype=wp.int32),
                      iters: wp.array(dtype=wp.int32), bb: wp.array(dtype=wp.float64),
                      report: wp.array(dtype=wp.float64), slot: int):
    """Status of the first iteration from ||b||^2 (zero: done; non-finite: failed)."""
    b2 = rr[slot]
    bb[0] = b2
    iters[slot] = 0
    st = int(_RUNNING)
    if not wp.isfinite(b2):
        st = int(_NONFINITE)
    elif b2 <= wp.float64(0.0):
        st = int(_CONVERGED)
    status[slot] = st
    report[0] = wp.float64(st)
    report[1] = wp.float64(0.0)
    report[2] = b2
    report[3] = b2


@wp.kernel
def _pcg_carry_kernel(rz: wp.array(dtype=wp.float64), rr: wp.array(dtype=wp.float64),
                      pap: wp.array(dtype=wp.float64), status: wp.array(dtype=wp.int32),
                      iters: wp.array(dtype=wp.int32), k: int):
    """Start of a chunk: slot 0 takes the last slot of the previous chunk; the others are zeroed."""
    rz[0] = rz[k]
    rr[0] = rr[k]
    status[0] = status[k]
    iters[0] = iters[k]
    for j in range(k + 1):
        pap[j] = wp.float64(0.0)
        if j > 0:
            rz[j] = wp.float64(0.0)
            rr[j] = wp.float64(0.0)


@both_precisions(values="m[]", mask="v[]", p="v[]", Ap="v[]")
@wp.kernel
def _pcg_matvec_kernel(offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32),
                       values: wp.array(dtype=Any), mask: wp.array(dtype=Any), p: wp.array(dtype=Any),
                       Ap: wp.array(dtype=Any), status: wp.array(dtype=wp.int32),
                       pap: wp.array(dtype=wp.float64), j: int, start: int, row_block: int, row_stride: int):
    """Ap = (P A P + I - P) p and pap[j] += p.Ap, while running (rows of partial sums:
    ``kernels.generic.splittable``)."""
    i = wp.tid() + start
    if status[j] != int(_RUNNING):
        return
    pi = p[i]
    acc = pi - pi
    for q in range(offsets[i], offsets[i + 1]):
        c = columns[q]
        acc += values[q] * cw_mul(mask[c], p[c])
    m = mask[i]
    y = cw_mul(m, acc) + pi - cw_mul(m, pi)
    Ap[i] = y
    wp.atomic_add(pap, j + (i // row_block) * row_stride, wp.float64(wp.dot(pi, y)))


@both_precisions(inv_diag="m[]", x="v[]", r="v[]", z="v[]", p="v[]", Ap="v[]")
@wp.kernel
def _pcg_update_kernel(inv_diag: wp.array(dtype=Any), x: wp.array(dtype=Any), r: wp.array(dtype=Any),
                       z: wp.array(dtype=Any), p: wp.array(dtype=Any), Ap: wp.array(dtype=Any),
                       status: wp.array(dtype=wp.int32), iters: wp.array(dtype=wp.int32),
                       rz: wp.array(dtype=wp.float64), rr: wp.array(dtype=wp.float64),
                       pap: wp.array(dtype=wp.float64), j: int, rz_out: wp.array(dtype=wp.float64),
                       rr_out: wp.array(dtype=wp.float64), row_block: int, row_stride: int):
    """alpha = rz/pAp; x += alpha p; r -= alpha Ap; z = M^-1 r; r.z and r.r accumulated into
    rz_out, rr_out at j + 1 + (i // row_block) row_stride (rz, rr themselves, or rows of the
    fixed-order sums). With non-positive curvature on the first iteration, x = z (the
    preconditioned residual)."""
    i = wp.tid()
    if status[j] != int(_RUNNING):
        return
    a = pap[j]
    if not (a > wp.float64(0.0)) or not wp.isfinite(a):
        if iters[j] == 0:
            x[i] = z[i]
        return
    xi = x[i]
    alpha = type(xi[0])(rz[j] / a)
    x[i] = xi + alpha * p[i]
    ri = r[i] - alpha * Ap[i]
    r[i] = ri
    zi = inv_diag[i] * ri
    z[i] = zi
    q = j + 1 + (i // row_block) * row_stride
    wp.atomic_add(rz_out, q, wp.float64(wp.dot(ri, zi)))
    wp.atomic_add(rr_out, q, wp.float64(wp.dot(ri, ri)))


@both_precisions(z="v[]", p="v[]")
@wp.kernel
def _pcg_direction_kernel(z: wp.array(dtype=Any), p: wp.array(dtype=Any), status: wp.array(dtype=wp.int32),
                          iters: wp.array(dtype=wp.int32), rz: wp.array(dtype=wp.float64),
                          rr: wp.array(dtype=wp.float64), pap: wp.array(dtype=wp.float64),
                          bb: wp.array(dtype=wp.float64), tol2: wp.array(dtype=wp.float64),
                          maxiter: wp.array(dtype=wp.int32), report: wp.array(dtype=wp.float64), j: int,
                          start: int):
    """Stopping test on the device; p = z + beta p while running. Thread 0 writes slot j+1's
    status and iteration count and the report the host reads."""
    i = wp.tid() + start
    st = status[j]
    it = iters[j]
    res2 = rr[j]
    new_st = st
    if st == int(_RUNNING):
        a = pap[j]
        if not (a > wp.float64(0.0)) or not wp.isfinite(a):
            new_st = int(_NEGATIVE)
        else:
            it = it + 1
            res2 = rr[j + 1]
            if not wp.isfinite(res2):
                new_st = int(_NONFINITE)
            elif res2 <= tol2[0] * bb[0]:
                new_st = int(_CONVERGED)
            elif it >= maxiter[0]:
                new_st = int(_MAXITER)
            else:
                beta = type(p[i][0])(rz[j + 1] / rz[j])
                p[i] = z[i] + beta * p[i]
    if i == 0:
        status[j + 1] = new_st
        iters[j + 1] = it
        rr[j + 1] = res2  # unchanged while running; carries the last residual once stopped
        report[0] = wp.float64(new_st)
        report[1] = wp.float64(it)
        report[2] = res2
        report[3] = bb[0]


# the recorded launches of the multigrid's CG split these across CPU threads (``RecordedLaunch``)
splittable("reduce", 2048, acc=7, slot=8, written=lambda a: a[8])(_pcg_matvec_kernel)
splittable("start", 8192)(_pcg_direction_kernel)


@both_precisions(values="m[]", mask="v[]", inv_diag="m[]", b="v[]", x="v[]", r="v[]", z="v[]", p="v[]", Ap="v[]",
                 pm="v[]")
@wp.kernel
def _pcg_serial_kernel(offsets: wp.array(dtype=wp.int32), columns: wp.array(dtype=wp.int32),
                       values: wp.array(dtype=Any), mask: wp.array(dtype=Any), inv_diag: wp.array(dtype=Any),
                       b: wp.array(dtype=Any), x: wp.array(dtype=Any), r: wp.array(dtype=Any), z: wp.array(dtype=Any),
                       p: wp.array(dtype=Any), Ap: wp.array(dtype=Any), pm: wp.array(dtype=Any),
                       tol2: wp.array(dtype=wp.float64),
                       maxiter: wp.array(dtype=wp.int32), report: wp.array(dtype=wp.float64)):
    """The whole solve in one launch of one thread, for the CPU (where a launch's threads run one
    after the other anyway, and launches, not arithmetic, cost the time on small meshes): the same
    iteration, in the same order of operations, as the init / matvec / update / direction kernels.
    The masked direction pm = mask * p is kept next to p (formed once per row, not once per block
    of the product: the same numbers)."""
    n = b.shape[0]
    rz = wp.float64(0.0)
    rr = wp.float64(0.0)
    for i in range(n):
        bi = b[i]
        zi = inv_diag[i] * bi
        x[i] = bi - bi
        r[i] = bi
        z[i] = zi
        p[i] = zi
        pm[i] = cw_mul(mask[i], zi)
        rz += wp.float64(wp.dot(bi, zi))
        rr += wp.float64(wp.dot(bi, bi))
    bb = rr
    st = int(_RUNNING)
    if not wp.isfinite(bb):
        st = int(_NONFINITE)
    elif bb <= wp.float64(0.0):
        st = int(_CONVERGED)
    it = int(0)
    while st == int(_RUNNING):
        pap = wp.float64(0.0)
        for i in range(n):
            pi = p[i]
            acc = pi - pi
            for q in range(offsets[i], offsets[i + 1]):
                acc += values[q] * pm[columns[q]]
            m = mask[i]
            yv = cw_mul(m, acc) + pi - cw_mul(m, pi)
            Ap[i] = yv
            pap += wp.float64(wp.dot(pi, yv))
        if not (pap > wp.float64(0.0)) or not wp.isfinite(pap):
            if it == 0:
                for i in range(n):
                    x[i] = z[i]
            st = int(_NEGATIVE)
        else:
            rz1 = wp.float64(0.0)
            rr1 = wp.float64(0.0)
            for i in range(n):
                xi = x[i]
                alpha = type(xi[0])(rz / pap)
                x[i] = xi + alpha * p[i]
                ri = r[i] - alpha * Ap[i]
                r[i] = ri
                zi = inv_diag[i] * ri
                z[i] = zi
                rz1 += wp.float64(wp.dot(ri, zi))
                rr1 += wp.float64(wp.dot(ri, ri))
            it = it + 1
            rr = rr1
            if not wp.isfinite(rr1):
                st = int(_NONFINITE)
            elif rr1 <= tol2[0] * bb:
                st = int(_CONVERGED)
            elif it >= maxiter[0]:
                st = int(_MAXITER)
            else:
                for i in range(n):
                    pv = p[i]
                    beta = type(pv[0])(rz1 / rz)
                    pn = z[i] + beta * pv
                    p[i] = pn
                    pm[i] = cw_mul(mask[i], pn)
            rz = rz1
    report[0] = wp.float64(st)
    report[1] = wp.float64(it)
    report[2] = rr
    report[3] = bb


#: on a CPU with at least ``SPLIT_CORES`` cores (``warpfem.threads.available_cores``: a property of
#: the machine, not of the thread count asked for), systems of at least ``SPLIT_ROWS`` block rows are
#: solved with launches split across CPU threads (``cpu_serial`` asked for: the split path instead
#: of the one-thread launch). Its sums are rows of partial sums, so its numbers do not depend on the
#: thread count. On one thread it is ~1.5x slower than the serial launch (measured at 5k and 19k
#: rows, kernels_bench/bench_threads.py's notes in docs/benchmarks.md), hence only where there are
#: cores to win that back.
SPLIT_ROWS = 16384
SPLIT_CORES = 4


class DevicePCG(LinearSolver):
    """Block-Jacobi PCG with device-side scalars and a host check every ``check_every`` iterations.

    Args:
        pattern, vec_type, scalar: see :class:`~warpfem.solvers.linear.base.LinearSolver`.
        check_every: iterations between host read-backs of the residual (k). A solve makes
            ceil(iterations / k) read-backs (at least one), and runs at most k - 1 no-op
            iterations past convergence.
        use_cuda_graph: on CUDA, capture a chunk of k iterations as a graph and replay it (in strict
            device mode, ``warpfem.transfer``, also on the CPU: Warp's CPU graph, the same code path).
        cpu_serial: on the CPU, run the whole solve as one launch of one thread
            (``_pcg_serial_kernel``: the same iterations in the same order, one read-back per
            solve, no no-op iterations past convergence; the simulators turn it on, see
            ``linear.auto.simulator_options``). Ignored on CUDA and in strict device mode. From
            ``SPLIT_ROWS`` block rows on a machine of ``SPLIT_CORES`` cores or more, the CPU solve is
            instead a loop of launches split across CPU threads
            (``cpu_split``: the multigrid's CG with the block-Jacobi step, ``warpfem.threads``).
    """

    name = "pcg"

    def __init__(self, pattern, *, vec_type, scalar, check_every: int = 16, use_cuda_graph: bool = True,
                 cpu_serial: bool = False):
        if int(check_every) != check_every or check_every < 1:
            raise ValueError(f"check_every must be a positive integer, got {check_every!r}")
        self.check_every = int(check_every)
        self.use_cuda_graph = bool(use_cuda_graph)
        # strict device mode: the CPU runs the CUDA path (chunks, captured as a graph)
        strict = strict_device()
        self._serial_asked = bool(cpu_serial) and not pattern.device.is_cuda and not strict
        self.cpu_serial = self._serial_asked
        self.cpu_split = False
        self._graphs_on = self.use_cuda_graph and (pattern.device.is_cuda or strict)
        super().__init__(pattern, vec_type=vec_type, scalar=scalar)

    def _analyse(self, pattern):
        n, dev, k = pattern.num_rows, self.device, self.check_every
        vec = self.vec_type
        from warpfem.threads import available_cores

        self.cpu_split = self._serial_asked and n >= SPLIT_ROWS and available_cores() >= SPLIT_CORES
        self.cpu_serial = self._serial_asked and not self.cpu_split
        self._split_cmds, self._split_key = None, None
        self.b = wp.zeros(n, dtype=vec, device=dev)
        self.x = wp.zeros(n, dtype=vec, device=dev)
        self.r = wp.zeros(n, dtype=vec, device=dev)
        self.z = wp.zeros(n, dtype=vec, device=dev)
        self.p = wp.zeros(n, dtype=vec, device=dev)
        self.Ap = wp.zeros(n, dtype=vec, device=dev)
        self.pm = wp.zeros(n, dtype=vec, device=dev) if self.cpu_serial else None  # mask * p (serial kernel)
        self._rz = wp.zeros(k + 1, dtype=wp.float64, device=dev)
        self._rr = wp.zeros(k + 1, dtype=wp.float64, device=dev)
        self._pap = wp.zeros(k + 1, dtype=wp.float64, device=dev)
        self._status = wp.zeros(k + 1, dtype=wp.int32, device=dev)
        self._iters = wp.zeros(k + 1, dtype=wp.int32, device=dev)
        self._bb = wp.zeros(1, dtype=wp.float64, device=dev)
        self._tol2 = wp.zeros(1, dtype=wp.float64, device=dev)
        self._maxiter = wp.zeros(1, dtype=wp.int32, device=dev)
        self._report = wp.zeros(4, dtype=wp.float64, device=dev)
        # fixed-order sums (``kernels.generic.ORDERED_SUMS``, devices other than the CPU): the
        # chunked loop's kernels add index i's terms into entry slot + i of these row arrays,
        # summed into the scalars by recorded tree launches
        self._ordered = ordered_sums(dev) and not self.cpu_serial and not self.cpu_split
        self._rows = ((wp.zeros(n + k + 1, dtype=wp.float64, device=dev), wp.zeros(n + k + 1, dtype=wp.float64, device=dev))
                      if self._ordered else None)
        self._graph = None
        self._serial_cmd, self._serial_key = None, None
        self._start_cmds = None
        self._chunk_cmds, self._chunk_key = None, None
        self._chunk_runs = 0

    def _record(self, kernel, dim, inputs):
        return wp.launch(kernel, dim=dim, inputs=inputs, device=self.device, record_cmd=True)

    def _sums(self, slot, *targets):
        """(callables, launches): the fixed-order sums of rows[slot:slot + n] into each
        (rows, acc) target's acc[slot]."""
        n, dev = self.num_rows, self.device
        out = []
        for rows, acc in targets:
            out += ordered_sum_launches(rows[slot:slot + n], n, acc, slot, dev)
        return out, len(out)

    def _start_commands(self):
        """The solve's first launches, recorded once (their arrays are this object's buffers), as
        (callables in order, kernel launches among them)."""
        if self._start_cmds is None:
            n, k = self.num_rows, self.check_every
            first = [self.b, self.inv_diag, self.x, self.r, self.z, self.p]
            start = self._record(_pcg_start_kernel, 1, [self._rr, self._status, self._iters, self._bb, self._report, k])
            if self._ordered:
                ra, rb = self._rows
                sums, m = self._sums(k, (ra, self._rz), (rb, self._rr))
                self._start_cmds = ([ra.zero_, rb.zero_,
                                     self._record(_pcg_init_kernel, n, first + [ra, rb, k, 1, 1]).launch]
                                    + sums + [start.launch], 2 + m)
            else:
                self._start_cmds = ([self._record(_pcg_init_kernel, n, first + [self._rz, self._rr, k, max(n, 1), 0]).launch,
                                     start.launch], 2)
        return self._start_cmds

    def _chunk_commands(self):
        """The 3 k + 1 launches of a chunk (more with fixed-order sums: their zeroing and tree
        launches), recorded once per (values, mask) arrays: replaying a recorded launch skips
        Warp's per-launch argument inference and packing, which on the CPU cost more than the
        kernels of a small mesh. (callables in order, kernel launches among them)."""
        key = (self._values.ptr, self._mask.ptr)
        if self._chunk_key != key:
            pt, n, k = self.pattern, self.num_rows, self.check_every
            values, mask = self._values, self._mask
            cmds = [self._record(_pcg_carry_kernel, 1, [self._rz, self._rr, self._pap, self._status, self._iters,
                                                        k]).launch]
            launches = 1 + 3 * k
            for j in range(k):
                mv = [pt.offsets, pt.columns, values, mask, self.p, self.Ap, self._status]
                up = [self.inv_diag, self.x, self.r, self.z, self.p, self.Ap, self._status, self._iters, self._rz,
                      self._rr, self._pap, j]
                if self._ordered:
                    ra, rb = self._rows
                    s_mv, m_mv = self._sums(j, (ra, self._pap))
                    s_up, m_up = self._sums(j + 1, (ra, self._rz), (rb, self._rr))
                    cmds += [ra.zero_, self._record(_pcg_matvec_kernel, n, mv + [ra, j, 0, 1, 1]).launch, *s_mv,
                             ra.zero_, rb.zero_, self._record(_pcg_update_kernel, n, up + [ra, rb, 1, 1]).launch, *s_up]
                    launches += m_mv + m_up
                else:
                    cmds.append(self._record(_pcg_matvec_kernel, n, mv + [self._pap, j, 0, max(n, 1), 0]).launch)
                    cmds.append(self._record(_pcg_update_kernel, n, up + [self._rz, self._rr, max(n, 1), 0]).launch)
                cmds.append(self._record(_pcg_direction_kernel, n, [self.z, self.p, self._status, self._iters, self._rz,
                                                                    self._rr, self._pap, self._bb, self._tol2,
                                                                    self._maxiter, self._report, j, 0]).launch)
            self._chunk_cmds, self._chunk_key = (cmds, launches), key
            self._graph = None
        return self._chunk_cmds

    def _run_serial(self):
        """The whole solve (CPU): one recorded launch per (values, mask) arrays."""
        key = (self._values.ptr, self._mask.ptr)
        if self._serial_key != key:
            pt = self.pattern
            self._serial_cmd = self._record(_pcg_serial_kernel, 1, [
                pt.offsets, pt.columns, self._values, self._mask, self.inv_diag, self.b, self.x, self.r, self.z, self.p,
                self.Ap, self.pm, self._tol2, self._maxiter, self._report])
            self._serial_key = key
        self._serial_cmd.launch()
        COUNTERS["launches"] += 1

    def _split_commands(self):
        """The CPU split path's launches (``cpu_split``), recorded once per (values, mask) arrays:
        the CG of the multigrid solver (``linear.multigrid``: flat vectors, rows of partial sums)
        with z = M^-1 r by the block-Jacobi inverse."""
        key = (self._values.ptr, self._mask.ptr, self.inv_diag.ptr)
        if self._split_key != key:
            from warpfem.kernels import linalg as LK
            from warpfem.solvers.linear.multigrid import _mg_init_kernel, _mg_precond_finish_kernel, _mg_update_kernel

            pt, n, k, dev = self.pattern, self.num_rows, self.check_every, self.device
            R = lambda kern, dim, inputs: RecordedLaunch(kern, dim, inputs, dev)  # noqa: E731
            flat = lambda a: a.view(self.scalar).flatten()  # noqa: E731
            bf, xf, rf, zf, pf, Apf, mf = map(flat, (self.b, self.x, self.r, self.z, self.p, self.Ap, self._mask))
            precond = R(LK.block_apply_kernel, n, [self.inv_diag, self.r, self.z])
            start = [R(_mg_init_kernel, 3 * n, [bf, xf, rf, self._rr, k]),
                     R(_pcg_start_kernel, 1, [self._rr, self._status, self._iters, self._bb, self._report, k]),
                     precond,
                     R(_mg_precond_finish_kernel, 3 * n, [rf, zf, mf, pf, self._status, self._pap, self._rz, k, 1])]
            chunk = [R(_pcg_carry_kernel, 1, [self._rz, self._rr, self._pap, self._status, self._iters, k])]
            for j in range(k):
                chunk += [R(_pcg_matvec_kernel, n, [pt.offsets, pt.columns, self._values, self._mask, self.p, self.Ap,
                                                    self._status, self._pap, j]),
                          R(_mg_update_kernel, 3 * n, [xf, rf, zf, pf, Apf, self._status, self._iters, self._rz,
                                                       self._rr, self._pap, j]),
                          precond,
                          R(_mg_precond_finish_kernel, 3 * n, [rf, zf, mf, pf, self._status, self._pap, self._rz, j, 0]),
                          R(_pcg_direction_kernel, n, [self.z, self.p, self._status, self._iters, self._rz, self._rr,
                                                       self._pap, self._bb, self._tol2, self._maxiter, self._report, j])]
            self._split_cmds, self._split_key = (start, chunk), key
        return self._split_cmds

    def _launch_start(self):
        self._rz.zero_()
        self._rr.zero_()
        if self.cpu_split:
            cmds = self._split_commands()[0]
            for c in cmds:
                c()
            COUNTERS["launches"] += len(cmds)
            return
        cmds, launches = self._start_commands()
        for c in cmds:
            c()
        COUNTERS["launches"] += launches

    def _run_chunk(self):
        dev = self.device
        if self.cpu_split:
            cmds = self._split_commands()[1]
            for c in cmds:
                c()
            COUNTERS["launches"] += len(cmds)
            self._chunk_runs += 1
            return
        cmds, launches = self._chunk_commands()
        COUNTERS["launches"] += launches  # a replayed graph counts as its launches
        if self._graphs_on:
            if self._graph is None:
                if self._chunk_runs == 0:  # first run uncaptured: loads the modules
                    for c in cmds:
                        c()
                    self._chunk_runs += 1
                    return
                with wp.ScopedCapture(device=dev, force_module_load=False) as cap:
                    for c in cmds:
                        c()
                self._graph = cap.graph
            wp.capture_launch(self._graph)
        else:
            for c in cmds:
                c()
        self._chunk_runs += 1

    def _solve(self, b, x, *, tol, maxiter) -> LinearSolveResult:
        if maxiter < 1:
            raise ValueError(f"maxiter must be >= 1, got {maxiter}")
        wp.copy(self.b, b)
        self._tol2.fill_(float(tol) ** 2)
        self._maxiter.fill_(int(maxiter))
        if self.cpu_serial:
            self._run_serial()
            rep = read(self._report)
            wp.copy(x, self.x)
            return self._result(rep, tol, 1)
        self._launch_start()
        syncs = chunks = 0
        while True:
            self._run_chunk()
            chunks += 1
            rep = read(self._report)  # the one host read-back of the chunk
            syncs += 1
            if int(rep[0]) != _RUNNING:
                break
        self.last_chunks = chunks
        wp.copy(x, self.x)
        return self._result(rep, tol, syncs)

    def _result(self, rep, tol, syncs) -> LinearSolveResult:
        status, it, rr, bb = int(rep[0]), int(rep[1]), float(rep[2]), float(rep[3])
        if bb == 0.0:
            return LinearSolveResult(0, 0.0, True, host_syncs=syncs)
        rel = float(np.sqrt(max(rr, 0.0) / bb)) if np.isfinite(rr) and np.isfinite(bb) else float("nan")
        return LinearSolveResult(it, rel, bool(rel <= tol), host_syncs=syncs,
                                 negative_curvature=status == _NEGATIVE,
                                 failed="" if status != _NONFINITE else "non-finite residual")

    # -- a solve whose read-back is the caller's (the Newton loop reads it with its own numbers) --------
    last_chunks = 0  # chunks of check_every iterations the last solve ran

    def state_dict(self) -> dict:
        """The chunks the last solve ran (a deferred solve's first guess)."""
        return {"last_chunks": int(self.last_chunks)}

    def load_state_dict(self, view):
        self.last_chunks = view.integer("last_chunks")


    def can_defer(self) -> bool:
        return self._values is not None

    @property
    def deferred_chunks(self) -> int:
        """Chunks a deferred solve should run before the caller's read-back (0: solve normally)."""
        return 1 if self.cpu_serial else self.last_chunks

    def solve_deferred(self, b, x, *, tol, maxiter, chunks, report_out, report_offset, graphs=None):
        """Start a solve of (prepared matrix) x = b and run ``chunks`` chunks without reading back;
        x and the 4-number report (status, iterations, r.r, b.b) are copied on the device into
        ``x`` and ``report_out[report_offset:report_offset + 4]``. The caller reads the report
        (with whatever else it reads) and finishes with :meth:`complete_deferred`. ``graphs`` (a
        ``kernels.generic.CapturedSequences``): the CPU serial solve's copies, fills and launch are
        captured once per set of arrays and tolerance and replayed."""
        if maxiter < 1:
            raise ValueError(f"maxiter must be >= 1, got {maxiter}")

        def work():
            wp.copy(self.b, b)
            self._tol2.fill_(float(tol) ** 2)
            self._maxiter.fill_(int(maxiter))
            if self.cpu_serial:  # the solve is complete after its one launch
                self._run_serial()
            else:
                self._launch_start()
                for _ in range(max(1, int(chunks))):
                    self._run_chunk()
            wp.copy(x, self.x)
            wp.copy(report_out, self._report, dest_offset=int(report_offset), count=4)

        if graphs is not None and self.cpu_serial and self._values is not None:
            key = ("pcg", id(self), id(self.pattern), b.ptr, x.ptr, report_out.ptr, int(report_offset), self.b.ptr,
                   self._values.ptr, self._mask.ptr, float(tol), int(maxiter))
            graphs.run(key, work)
        else:
            work()
        self._deferred = (x, float(tol), max(1, int(chunks)))

    def complete_deferred(self, report):
        """(result, x changed): the solve started by :meth:`solve_deferred`, from the report the
        caller read; a solve still running is continued here (one read-back per further chunk) and
        then ``x`` has changed since the caller's launches used it."""
        x, tol, chunks = self._deferred
        self._deferred = None
        rep, syncs = np.asarray(report, dtype=np.float64), 0
        while int(rep[0]) == _RUNNING:
            self._run_chunk()
            chunks += 1
            rep = read(self._report)
            syncs += 1
        if syncs:
            wp.copy(x, self.x)
        self.last_chunks = chunks
        self.host_syncs += syncs
        return self._result(rep, tol, syncs), syncs > 0
