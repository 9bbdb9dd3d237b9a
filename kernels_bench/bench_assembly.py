"""Where the time of the Hessian assembly goes: force vs Hessian Mtets/s, and the Hessian split into parts.

For box Tet4 meshes (``--cells`` hex cells x 6 tets each; defaults ~24k and ~200k tets), stable
neo-Hookean, positions perturbed from rest, float32 and float64, on the device (CPU by default):

  force       ``qp_force_kernel`` (F, P, atomic scatter of 4 vec3)
  hessian     ``values.zero_()`` + ``qp_hessian_kernel`` (what a Newton iteration pays)
  zero        ``values.zero_()`` alone (the BSR value array, nnz 3x3 blocks)
  kernel      ``qp_hessian_kernel`` alone (into values that are not re-zeroed)
  svd         bench-local kernel: F + ``signed_svd`` (``wp.svd3``) per point (the Hessian's SVD before the cheaper Jacobi SVD)
  svd_jacobi  bench-local kernel: F + ``jacobi_signed_svd`` per point (the SVD the Hessian kernels use now)
  parts       bench-local kernel: F + ``material_hessian_parts`` (SVD, scaling block A, twist/flip), no projection
  eigen       bench-local kernel: F + ``material_hessian_parts`` + ``hessian_point_prepare`` per point
              (SVD, scaling block, projection), one scalar written per point
  blocks      bench-local kernel: eigen + the 10 blocks of ``hessian_point_block`` summed in registers,
              one mat33 written per point (the full kernel without the scatter)
  blocks_legacy  the same with the block function as it was before the entry-wise M (same-run A/B)
  scatter     bench-local kernel: only the 16 atomic mat33 adds through ``block_index`` (a constant block)
  numpy       baseline in the same run: numpy's vectorised linear-elastic 12x12 blocks (einsum, no SVD,
              no projection, no scatter; ``bench_forces.numpy_linear_hessian_blocks``)

Each figure: seconds per call (best of ``--batches`` batches of ``--repeats`` calls, the parts
interleaved batch by batch; on the CPU process CPU time, which a shared machine inflates less than
wall time), Mtets/s, and ratios: hessian/force time, and
numpy/warp time for the Hessian. The bench-local kernels live only in this file (not compiled by
the tests).

    python kernels_bench/bench_assembly.py [--device cpu] [--sizes 40,10,10 84,20,20]
        [--precisions float32 float64] [--repeats 5] [--json PATH]
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import subprocess
import sys
import time
from typing import Any

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import warp as wp  # noqa: E402

import warpfem as wf  # noqa: E402
from warpfem.kernels import fem as FK  # noqa: E402
from warpfem.kernels.common import point_deformation_gradient  # noqa: E402
from warpfem.kernels.generic import both_precisions  # noqa: E402
from warpfem.materials.dispatch import material_hessian_parts  # noqa: E402
from warpfem.materials.eigensystem import (hessian_point_block, hessian_point_prepare, jacobi_signed_svd,  # noqa: E402
                                           signed_svd)

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_forces import numpy_linear_hessian_blocks  # noqa: E402

wp.set_module_options({"enable_backward": False})


@both_precisions(x="v[]", points="qp", material="mat", out="s[]")
@wp.kernel
def eigen_only_kernel(x: wp.array(dtype=Any), points: Any, material: Any, project: int, out: wp.array(dtype=Any)):
    q = wp.tid()
    F = point_deformation_gradient(x, points, q)
    U0, V0, A0, tw, fl = material_hessian_parts(material.kind, F, material.mu, material.lam)
    U, Vt, A, cp, cm = hessian_point_prepare(U0, V0, A0, tw, fl, project)
    out[q] = points.weight[q] * (A[0, 0] + A[1, 1] + A[2, 2] + cp[0] + cm[1] + U[0, 0] + Vt[1, 1])


@both_precisions(x="v[]", points="qp", out="s[]")
@wp.kernel
def svd_only_kernel(x: wp.array(dtype=Any), points: Any, out: wp.array(dtype=Any)):
    q = wp.tid()
    U, s, V = signed_svd(point_deformation_gradient(x, points, q))
    out[q] = s[0] + s[1] + s[2] + U[0, 1] + V[1, 2]


@both_precisions(x="v[]", points="qp", out="s[]")
@wp.kernel
def svd_jacobi_kernel(x: wp.array(dtype=Any), points: Any, out: wp.array(dtype=Any)):
    q = wp.tid()
    U, s, V = jacobi_signed_svd(point_deformation_gradient(x, points, q))
    out[q] = s[0] + s[1] + s[2] + U[0, 1] + V[1, 2]


@both_precisions(x="v[]", points="qp", material="mat", out="s[]")
@wp.kernel
def parts_no_projection_kernel(x: wp.array(dtype=Any), points: Any, material: Any, out: wp.array(dtype=Any)):
    q = wp.tid()
    F = point_deformation_gradient(x, points, q)
    U0, V0, A0, tw, fl = material_hessian_parts(material.kind, F, material.mu, material.lam)
    out[q] = A0[0, 0] + A0[1, 1] + A0[2, 2] + tw[0] + fl[1] + U0[0, 0] + V0[1, 1]


@both_precisions(x="v[]", points="qp", material="mat", out="m[]")
@wp.kernel
def blocks_no_scatter_kernel(x: wp.array(dtype=Any), points: Any, material: Any, project: int,
                             out: wp.array(dtype=Any)):
    q = wp.tid()
    k = points.k
    F = point_deformation_gradient(x, points, q)
    U0, V0, A0, tw, fl = material_hessian_parts(material.kind, F, material.mu, material.lam)
    U, Vt, A, cp, cm = hessian_point_prepare(U0, V0, A0, tw, fl, project)
    c = points.weight[q]
    acc = c * wp.transpose(U) * U * c  # same type as a block; overwritten below
    acc = acc - acc
    for a in range(k):
        ra = Vt * points.dNdX[q * k + a]
        for b in range(a, k):
            acc = acc + c * hessian_point_block(U, A, cp, cm, ra, Vt * points.dNdX[q * k + b])
    out[q] = acc


@wp.func
def legacy_point_block(U: Any, A: Any, cp: Any, cm: Any, a: Any, b: Any):
    """``hessian_point_block`` as it was before the entry-wise M (diag(a) A diag(b) as two products)."""
    M = wp.diag(a) * A * wp.diag(b)
    M[1, 1] = M[1, 1] + cp[0] * a[2] * b[2] + cp[2] * a[0] * b[0]
    M[2, 2] = M[2, 2] + cp[0] * a[1] * b[1] + cp[1] * a[0] * b[0]
    M[0, 0] = M[0, 0] + cp[1] * a[2] * b[2] + cp[2] * a[1] * b[1]
    M[1, 2] = M[1, 2] + cm[0] * a[2] * b[1]
    M[2, 1] = M[2, 1] + cm[0] * a[1] * b[2]
    M[0, 2] = M[0, 2] + cm[1] * a[2] * b[0]
    M[2, 0] = M[2, 0] + cm[1] * a[0] * b[2]
    M[0, 1] = M[0, 1] + cm[2] * a[1] * b[0]
    M[1, 0] = M[1, 0] + cm[2] * a[0] * b[1]
    return U * M * wp.transpose(U)


@both_precisions(x="v[]", points="qp", material="mat", out="m[]")
@wp.kernel
def blocks_legacy_kernel(x: wp.array(dtype=Any), points: Any, material: Any, project: int,
                         out: wp.array(dtype=Any)):
    q = wp.tid()
    k = points.k
    F = point_deformation_gradient(x, points, q)
    U0, V0, A0, tw, fl = material_hessian_parts(material.kind, F, material.mu, material.lam)
    U, Vt, A, cp, cm = hessian_point_prepare(U0, V0, A0, tw, fl, project)
    c = points.weight[q]
    acc = c * wp.transpose(U) * U * c
    acc = acc - acc
    for a in range(k):
        ra = Vt * points.dNdX[q * k + a]
        for b in range(a, k):
            acc = acc + c * legacy_point_block(U, A, cp, cm, ra, Vt * points.dNdX[q * k + b])
    out[q] = acc


@both_precisions(points="qp", blk="m[]", values="m[]")
@wp.kernel
def scatter_only_kernel(points: Any, blk: wp.array(dtype=Any), block_index: wp.array(dtype=wp.int32), values: wp.array(dtype=Any)):
    q = wp.tid()
    k = points.k
    e = points.element[q]
    B = blk[0]
    for a in range(k):
        for b in range(a, k):
            wp.atomic_add(values, block_index[(e * k + a) * k + b], B)
            if b != a:
                wp.atomic_add(values, block_index[(e * k + b) * k + a], wp.transpose(B))


def best_time(fn, device, repeats, batches=3, clock=time.perf_counter):
    fn()
    wp.synchronize_device(device)
    best = np.inf
    for _ in range(batches):
        t = clock()
        for _ in range(repeats):
            fn()
        wp.synchronize_device(device)
        best = min(best, (clock() - t) / repeats)
    return best


def loadavg():
    try:
        return os.getloadavg()[0]
    except OSError:
        return float("nan")


def cpu_model():
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, timeout=10).stdout
        for line in out.splitlines():
            if line.startswith("Model name"):
                return line.split(":", 1)[1].strip()
    except (OSError, subprocess.SubprocessError):
        pass
    return platform.processor() or "unknown"


def run_case(cells, precision, device, repeats, batches=5, noise=0.1):
    mesh = wf.box_tet_mesh(size=(4.0, 1.0, 1.0), cells=tuple(cells))
    mat = wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
    model = wf.Model(mesh, mat)
    sim = wf.Simulator(model, device=device, precision=precision)
    rng = np.random.default_rng(0)
    h = min(s / c for s, c in zip((4.0, 1.0, 1.0), cells))
    sim.set_positions(mesh.vertices + noise * h * rng.standard_normal(mesh.vertices.shape))
    dev, m = sim.device, mesh.num_tets
    S, qp, mp = sim.scalar_type, sim.quadrature_points, sim.material_params
    bi = sim.pattern.block_index
    f = sim.new_vector()
    vals = sim.new_matrix_values()
    out_s = wp.zeros(sim.num_points, dtype=S, device=dev)
    out_m = wp.zeros(sim.num_points, dtype=vals.dtype, device=dev)
    blk = wp.array(np.ones((1, 3, 3), dtype=sim.numpy_dtype), dtype=vals.dtype, device=dev)
    project = 1

    def force():
        f.zero_()
        wp.launch(FK.qp_force_kernel, dim=sim.num_points, inputs=[sim.x, qp, mp, S(1.0), f], device=dev)

    def kernel():
        wp.launch(FK.qp_hessian_kernel, dim=sim.num_points, inputs=[sim.x, qp, mp, S(1.0), project, bi, vals, 0, 0],
                  device=dev)  # slots 0: added with atomics (the gather of a Newton iteration: bench_threads.py)

    def hessian():
        vals.zero_()
        kernel()

    parts = {
        "force": force,
        "hessian": hessian,
        "zero": vals.zero_,
        "kernel": kernel,
        "svd": lambda: wp.launch(svd_only_kernel, dim=sim.num_points, inputs=[sim.x, qp, out_s], device=dev),
        "svd_jacobi": lambda: wp.launch(svd_jacobi_kernel, dim=sim.num_points, inputs=[sim.x, qp, out_s], device=dev),
        "parts": lambda: wp.launch(parts_no_projection_kernel, dim=sim.num_points, inputs=[sim.x, qp, mp, out_s], device=dev),
        "eigen": lambda: wp.launch(eigen_only_kernel, dim=sim.num_points, inputs=[sim.x, qp, mp, project, out_s], device=dev),
        "blocks": lambda: wp.launch(blocks_no_scatter_kernel, dim=sim.num_points, inputs=[sim.x, qp, mp, project, out_m],
                                    device=dev),
        "blocks_legacy": lambda: wp.launch(blocks_legacy_kernel, dim=sim.num_points, inputs=[sim.x, qp, mp, project, out_m],
                                           device=dev),
        "scatter": lambda: wp.launch(scatter_only_kernel, dim=sim.num_points, inputs=[qp, blk, bi, vals], device=dev),
    }
    g = sim.model.quadrature.qp_dNdX.reshape(m, 4, 3).astype(sim.numpy_dtype)
    vol = sim.model.quadrature.qp_weight.astype(sim.numpy_dtype) if hasattr(sim.model.quadrature, "qp_weight") else \
        np.full(m, 1.0, dtype=sim.numpy_dtype)
    parts["numpy"] = lambda: numpy_linear_hessian_blocks(g, vol, mat.kernel_mu, mat.kernel_lam)
    t = {}
    load0 = loadavg()
    # alternate the parts over batches so that all see the same load
    for name, fn in parts.items():
        fn()
    wp.synchronize_device(dev)
    for name in parts:
        t[name] = np.inf
    # CPU: process CPU time (Warp's CPU backend and these numpy calls run in this thread), so that
    # other jobs on a shared machine inflate the figures less than wall time would; CUDA: wall time
    clock = time.process_time if wp.get_device(dev).is_cpu else time.perf_counter
    for _ in range(batches):
        for name, fn in parts.items():
            reps = 1 if name == "numpy" else repeats
            t[name] = min(t[name], best_time(fn, dev, reps, batches=1, clock=clock))
    row = dict(tets=m, noise=noise, vertices=mesh.num_vertices, nnz_blocks=sim.pattern.nnz, precision=precision, cells=list(cells),
               seconds=t, mtets_per_s={k: m / v / 1e6 for k, v in t.items()},
               hessian_over_force=t["hessian"] / t["force"], numpy_over_hessian=t["numpy"] / t["hessian"],
               share_of_hessian={k: t[k] / t["hessian"] for k in ("zero", "kernel", "svd", "svd_jacobi", "parts", "eigen", "blocks", "blocks_legacy", "scatter")},
               load_before=load0, load_after=loadavg())
    return row


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", nargs="+", default=["40,10,10", "84,20,20"])
    ap.add_argument("--precisions", nargs="+", default=["float32", "float64"])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--batches", type=int, default=5)
    ap.add_argument("--noise", type=float, default=0.1,
                    help="vertex perturbation, standard deviation as a fraction of the smallest cell edge")
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    wp.config.quiet = True
    wp.init()
    rows = []
    for size in args.sizes:
        cells = [int(c) for c in size.split(",")]
        for prec in args.precisions:
            r = run_case(cells, prec, args.device, args.repeats, args.batches, args.noise)
            rows.append(r)
            mt = r["mtets_per_s"]
            print(f"{r['tets']:>7} tets {prec}: force {mt['force']:.2f} Mtets/s, hessian {mt['hessian']:.3f} Mtets/s "
                  f"(hessian/force time {r['hessian_over_force']:.1f}x, numpy-linear/hessian {r['numpy_over_hessian']:.2f}x) | "
                  + ", ".join(f"{k} {v * 100:.0f}%" for k, v in r["share_of_hessian"].items())
                  + f" | load {r['load_before']:.2f}->{r['load_after']:.2f}", flush=True)
    meta = dict(device=str(args.device), cpu=cpu_model(), date=datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="minutes"),
                warp=wp.__version__, clock="process CPU time" if wp.get_device(args.device).is_cpu else "wall",
                note="2-core machine shared with other jobs; load = 1-min load average")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(dict(meta=meta, rows=rows), fh, indent=1)
    return rows


if __name__ == "__main__":
    main()
