"""Throughput and effective bandwidth of every warpfem kernel family, with numpy baselines.

Families (all on one box mesh of ``--cells`` hex cells split into 6 tets each, stable neo-Hookean,
positions perturbed from rest so nothing is trivially zero):

  force        F, P and the atomic scatter of -w P dN/dX (``kernels.fem.qp_force_kernel``)
  hessian      per-tet 12x12 SPD-projected stiffness from the analytic eigensystem, accumulated
               into the fixed block-sparse pattern (``Simulator.assemble_stiffness``)
  pcg-matvec   one masked block-sparse mat-vec y = P A P x + (I - P) x (``bsr_masked_mv_kernel``)
  pcg-iter     one block-Jacobi PCG iteration (``BlockJacobiPCG.solve`` run for a fixed number of
               iterations: mat-vec, 3 dot products, 2 axpy, block apply, xpby, 3 host read-backs)
  cubature     reduced force by cubature (``kernels.subspace``: per-point F, P and node forces, then
               the (point, column) projection onto the basis), ``--modes`` columns, every tet a
               cubature point (a random basis: throughput does not depend on the values)
  skinning     x_surface = W x with 4 weights per point (``SurfaceSkinner.apply``), ``--points``
               points at random barycentric positions in random tets

Per family: items per second (tets, rows = vertices, cubature points or surface points), the
effective bandwidth = compulsory bytes / time, where compulsory bytes count every array the kernel
reads once and every array it writes once (an atomic accumulation or a read-modify-write counts
twice), gathers through an index array counted once per array (perfect cache reuse), so the figure
is a lower bound on the traffic actually moved; and that bandwidth as a fraction of the device's
memory bandwidth measured in the same run:
  cpu:  STREAM-like copy (a[:] = b) and triad (a = b + s c, counted as 3 arrays) in numpy, and the
        same copy/triad as a Warp kernel on the device, on ``--stream-mb`` MB arrays (the Warp CPU
        backend and these numpy operations are single-threaded);
  cuda: wp.copy device-to-device and the Warp triad kernel.
The reference bandwidth is the best of those copy/triad figures. Baseline: the same operation
vectorised in numpy/scipy (same precision, single-threaded BLAS unless OPENBLAS_NUM_THREADS is set),
in the same run, and the speed-up warp/numpy.

Timing: every kernel is compiled and run once first; then ``wp.synchronize_device`` around a batch
of repeats; best of 3 batches, the Warp and the numpy batches alternating so that both see the same
machine load (the machine may be shared). PCG iteration: a ``--pcg-iters`` solve with tol 0 minus
one preconditioner set-up, divided by the iterations.

    .venv/bin/python kernels_bench/bench_kernels.py [--device cpu] [--precision float32|float64]
        [--cells 40 10 10] [--modes 20] [--points 100000] [--quick] [--json PATH] [--markdown PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

# numpy baselines single-threaded, like Warp's CPU backend (and a multi-threaded BLAS on a shared
# 2-core machine makes small dot products 10-50x slower); set before numpy loads its BLAS
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import scipy.sparse  # noqa: E402
import warp as wp  # noqa: E402

import warpfem as wf  # noqa: E402
from warpfem.kernels import fem as FK
from warpfem.kernels import linalg as LK
from warpfem.kernels import subspace as RK
from warpfem.reduced import CubatureForces
from warpfem.skinning import SurfaceSkinner
from warpfem.skinning.embedding import Embedding

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from bench_forces import numpy_linear_hessian_blocks, numpy_snh_forces  # noqa: E402

I32 = 4


@wp.kernel
def triad_f32_kernel(a: wp.array(dtype=wp.float32), b: wp.array(dtype=wp.float32), s: wp.float32,
                     c: wp.array(dtype=wp.float32)):
    i = wp.tid()
    a[i] = b[i] + s * c[i]


def best_time(fn, device, *, repeats, batches=3, warm=True):
    """Seconds per call: best of ``batches`` timed batches of ``repeats`` calls, after one warm call."""
    if warm:
        fn()
    wp.synchronize_device(device)
    best = np.inf
    for _ in range(batches):
        wp.synchronize_device(device)
        t = time.perf_counter()
        for _ in range(repeats):
            fn()
        wp.synchronize_device(device)
        best = min(best, (time.perf_counter() - t) / repeats)
    return best


def np_time(fn, *, repeats, batches=3, warm=True):
    if warm:
        fn()
    best = np.inf
    for _ in range(batches):
        t = time.perf_counter()
        for _ in range(repeats):
            fn()
        best = min(best, (time.perf_counter() - t) / repeats)
    return best


def paired_time(warp_fn, numpy_fn, device, *, warp_repeats, numpy_repeats, batches=3):
    """(warp s, numpy s) per call, best of ``batches`` alternating batches, so both see the same machine load."""
    warp_fn()
    numpy_fn()
    wp.synchronize_device(device)
    tw = tn = np.inf
    for _ in range(batches):
        tw = min(tw, best_time(warp_fn, device, repeats=warp_repeats, batches=1, warm=False))
        tn = min(tn, np_time(numpy_fn, repeats=numpy_repeats, batches=1, warm=False))
    return tw, tn


def memory_bandwidth(device, mb):
    """Measured copy/triad bandwidths (bytes/s) on the device and in numpy (CPU)."""
    n = int(mb * 2**20 // 4)
    out = {}
    if device.is_cpu:
        a, b, c = (np.full(n // 2, k, dtype=np.float64) for k in (0.0, 1.0, 2.0))
        nb = a.nbytes
        out["numpy_copy"] = 2 * nb / np_time(lambda: np.copyto(a, b), repeats=3)

        def triad():
            np.multiply(c, 3.0, out=a)
            np.add(a, b, out=a)

        out["numpy_triad"] = 3 * nb / np_time(triad, repeats=3)
        del a, b, c
    wa, wb, wc = (wp.full(n, k, dtype=wp.float32, device=device) for k in (0.0, 1.0, 2.0))
    nb = 4 * n
    out["warp_copy"] = 2 * nb / best_time(lambda: wp.copy(wa, wb), device, repeats=3)
    out["warp_triad"] = 3 * nb / best_time(lambda: wp.launch(triad_f32_kernel, dim=n, inputs=[wa, wb, wp.float32(3.0), wc],
                                                            device=device), device, repeats=3)
    return out


def perturbed_beam(cells, precision, device):
    mesh = wf.box_tet_mesh(size=(4.0, 1.0, 1.0), cells=tuple(cells))
    mat = wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
    model = wf.Model(mesh, mat, gravity=(0.0, 0.0, -9.81))
    model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (1e-6, 2, 2)))
    sim = wf.Simulator(model, device=device, precision=precision)
    rng = np.random.default_rng(0)
    x_np = mesh.vertices + 0.01 * rng.standard_normal(mesh.vertices.shape)
    sim.set_positions(x_np)
    return mesh, mat, model, sim, x_np


def bench_force_hessian(mesh, mat, sim, x_np, args, s):
    dev, m, n = sim.device, mesh.num_tets, mesh.num_vertices
    f = sim.new_vector()
    vals = sim.new_matrix_values()
    nnz = sim.pattern.nnz

    def warp_forces():
        f.zero_()
        wp.launch(FK.qp_force_kernel, dim=sim.num_points, inputs=[sim.x, sim.quadrature_points, sim.material_params, sim.scalar_type(1.0), f], device=dev)

    def warp_hessian():
        vals.zero_()
        sim.assemble_stiffness(sim.x, vals)

    X, tets = mesh.vertices, mesh.tets
    Dm = np.stack([X[tets[:, i]] - X[tets[:, 0]] for i in (1, 2, 3)], axis=2)
    Dm_inv, vol = np.linalg.inv(Dm), np.linalg.det(Dm) / 6
    g = sim.model.quadrature.qp_dNdX.reshape(m, 4, 3)
    dt = np.float32 if s == 4 else np.float64
    Xd, xd, Dmi, vold, gd = (a.astype(dt) for a in (X, x_np, Dm_inv, vol, g))
    t_wf, t_nf = paired_time(warp_forces, lambda: numpy_snh_forces(Xd, tets, xd, mat.kernel_mu, mat.kernel_lam, Dmi, vold), dev,
                             warp_repeats=args.repeats, numpy_repeats=1)
    t_wh, t_nh = paired_time(warp_hessian, lambda: numpy_linear_hessian_blocks(gd, vold, mat.kernel_mu, mat.kernel_lam), dev,
                             warp_repeats=max(2, args.repeats // 5), numpy_repeats=1)
    ref = numpy_snh_forces(X, tets, x_np, mat.kernel_mu, mat.kernel_lam, Dm_inv, vol)
    err = float(np.abs(sim.elastic_forces() - ref).max() / np.abs(ref).max())
    # compulsory bytes: x, X (n vec3), elements (4m), qp_element (m), dNdX (4m vec3), weight (m), f RMW
    b_in = 2 * n * 3 * s + 5 * m * I32 + 4 * m * 3 * s + m * s
    b_force = b_in + 2 * n * 3 * s
    b_hess = b_in + 16 * m * I32 + 2 * nnz * 9 * s
    return [
        dict(family="force", kernel="F, P, atomic scatter (qp_force_kernel)", items=m, unit="tets", warp_s=t_wf, numpy_s=t_nf,
             bytes=b_force, check=f"max |f_warp - f_numpy| / max |f| = {err:.1e}",
             byte_model="x, X, f (RMW) per vertex; 4 ids + element id + 4 dN/dX + weight per tet",
             numpy="vectorised F, P (stable neo-Hookean), np.add.at scatter"),
        dict(family="hessian", kernel="12x12 eigen-projected blocks into BSR (qp_hessian_kernel)", items=m, unit="tets",
             warp_s=t_wh, numpy_s=t_nh, bytes=b_hess,
             byte_model="force inputs + 16 block ids per tet + BSR values read-modify-write (nnz 3x3 blocks)",
             numpy="linear-elastic 12x12 blocks by einsum only (no SVD, no projection, no scatter): a lower bound on a numpy assembly"),
    ]


def bench_pcg(mesh, sim, args, s):
    dev, n = sim.device, mesh.num_vertices
    pt = sim.pattern
    vals = pt.new_values()
    sim.assemble_stiffness(sim.x, vals)
    # a backward-Euler-like SPD system: M + h^2 K
    h2 = (1.0 / 60.0) ** 2
    wp.launch(LK.scale_copy_kernel, dim=pt.nnz, inputs=[vals, sim.scalar_type(h2), vals], device=dev)
    wp.launch(LK.add_scaled_kernel, dim=pt.nnz, inputs=[sim.mass_values, sim.scalar_type(1.0), vals], device=dev)
    mask = sim.free_mask
    if mask is None:
        free = np.repeat(~sim.model.fixed[:, None], 3, axis=1) if sim.model.fixed.ndim == 1 else ~sim.model.fixed
        mask = wp.array(free.astype(sim.numpy_dtype), dtype=sim.vector_type, device=dev)
    rng = np.random.default_rng(1)
    b_np = rng.standard_normal((n, 3)) * mask.numpy()
    b = wp.array(b_np.astype(sim.numpy_dtype), dtype=sim.vector_type, device=dev)
    x = sim.new_vector()
    y = sim.new_vector()
    pcg = sim.linear_solver
    iters = args.pcg_iters

    res = pcg.solve(vals, mask, b, x, tol=0.0, maxiter=iters)
    t_setup = best_time(lambda: wp.launch(LK.block_jacobi_setup_kernel, dim=n,
                                          inputs=[pt.offsets, pt.columns, vals, mask, pcg.inv_diag], device=dev),
                        dev, repeats=args.repeats)

    # numpy/scipy baseline: the same masked system as a scipy BSR matrix, the same PCG iteration
    A = pt.to_scipy(vals).tobsr(blocksize=(3, 3))
    mk = mask.numpy().reshape(-1).astype(A.dtype)
    P = scipy.sparse.diags(mk)
    Am = (P @ A @ P + scipy.sparse.diags(1.0 - mk)).tobsr(blocksize=(3, 3)).astype(sim.numpy_dtype)
    bb = b_np.reshape(-1).astype(sim.numpy_dtype)
    diag_blocks = np.zeros((n, 3, 3), dtype=sim.numpy_dtype)
    Acsr = Am.tocsr()
    for a in range(3):
        for c in range(3):
            diag_blocks[:, a, c] = Acsr[np.arange(n) * 3 + a, np.arange(n) * 3 + c].A1
    Dinv = np.linalg.inv(diag_blocks)

    def numpy_matvec():
        return Am @ bb

    def numpy_pcg():
        xx = np.zeros_like(bb)
        r = bb.copy()
        z = np.einsum("nij,nj->ni", Dinv, r.reshape(n, 3)).reshape(-1)
        p = z.copy()
        rz = r @ z
        for _ in range(iters):
            Ap = Am @ p
            alpha = rz / (p @ Ap)
            xx += alpha * p
            r -= alpha * Ap
            _ = np.sqrt(r @ r)
            z = np.einsum("nij,nj->ni", Dinv, r.reshape(n, 3)).reshape(-1)
            rz_new = r @ z
            p = z + (rz_new / rz) * p
            rz = rz_new
        return xx

    t_mv, t_nmv = paired_time(lambda: pcg.matvec(vals, mask, b, y), numpy_matvec, dev, warp_repeats=args.repeats,
                              numpy_repeats=args.repeats)
    t_solve, t_npcg = paired_time(lambda: pcg.solve(vals, mask, b, x, tol=0.0, maxiter=iters), numpy_pcg, dev,
                                  warp_repeats=1, numpy_repeats=1)
    t_npcg /= iters
    it = max(res.iterations, 1)
    t_it = max(t_solve - t_setup, 0.0) / it
    pcg.matvec(vals, mask, b, y)
    err = float(np.abs(y.numpy().reshape(-1) - Am @ bb).max() / np.abs(Am @ bb).max())
    nnz = pt.nnz
    vec = n * 3 * s
    b_mv = nnz * (9 * s + I32) + (n + 1) * I32 + 3 * vec  # values, columns, offsets; mask, x, y
    b_it = b_mv + (n * 9 * s + 2 * vec) + 6 * vec + 3 * 3 * vec  # + block apply, 3 dots, axpy x2, xpby
    return [
        dict(family="pcg-matvec", kernel="masked block-sparse mat-vec (bsr_masked_mv_kernel)", items=n, unit="rows",
             warp_s=t_mv, numpy_s=t_nmv, bytes=b_mv, check=f"max rel. diff vs scipy {err:.1e}",
             byte_model=f"nnz = {nnz} 3x3 blocks + column ids, row offsets; mask, x, y (vec3 per row)",
             numpy="scipy.sparse BSR (3x3 blocks) @ vector"),
        dict(family="pcg-iter", kernel=f"block-Jacobi PCG iteration (BlockJacobiPCG.solve, {it} iterations)", items=n,
             unit="rows", warp_s=t_it, numpy_s=t_npcg, bytes=b_it,
             byte_model="mat-vec + block apply (inverse blocks, r, z) + 3 dots (2 vectors each) + 2 axpy + xpby (3 vectors each)",
             numpy="the same iteration with scipy BSR mat-vec and numpy vector operations"),
    ]


def bench_cubature(mesh, model, x_np, args, precision, device, s):
    n, m, r = mesh.num_vertices, mesh.num_tets, args.modes
    rng = np.random.default_rng(2)
    U = 0.01 * rng.standard_normal((3 * n, r))
    cf = CubatureForces(model, U, np.arange(m), np.ones(m), device=device, precision=precision)
    q = 0.1 * rng.standard_normal(r)
    cf._q.assign(q.astype(cf._npdt))

    def warp_cubature():
        wp.launch(RK.cubature_element_kernel, dim=cf.c,
                  inputs=[cf.U, cf._q, cf.points, cf.material, 0, 1, cf._energy, cf._f, cf._H], device=cf.device)
        cf._force.zero_()
        wp.launch(RK.cubature_project_kernel, dim=(cf.r, 1),
                  inputs=[cf.U, cf.points, cf._f, cf._H, 0, cf.c, cf._force, cf._K], device=cf.device)

    # numpy baseline: the same sum over all elements with weight 1 (= the exact reduced force)
    dt = np.float32 if s == 4 else np.float64
    X, tets = mesh.vertices, mesh.tets
    Dm = np.stack([X[tets[:, i]] - X[tets[:, 0]] for i in (1, 2, 3)], axis=2)
    Dm_inv, vol = np.linalg.inv(Dm), np.linalg.det(Dm) / 6
    U3 = U.reshape(n, 3, r).astype(dt)
    Xd, Dmi, vold, qd = X.astype(dt), Dm_inv.astype(dt), vol.astype(dt), q.astype(dt)
    mat = model.material

    def numpy_cubature():
        x = Xd + U3 @ qd
        f = numpy_snh_forces(Xd, tets, x, mat.kernel_mu, mat.kernel_lam, Dmi, vold)
        return np.einsum("nkr,nk->r", U3, f)

    t_w, t_n = paired_time(warp_cubature, numpy_cubature, cf.device, warp_repeats=max(2, args.repeats // 2),
                           numpy_repeats=1)
    _, f_w, _ = cf.evaluate(q)
    f_n = numpy_cubature().astype(np.float64)
    err = float(np.abs(f_w - f_n).max() / np.abs(f_n).max())
    c = m
    rows = min(4 * c, n)
    b = 2 * rows * r * 3 * s + r * s + 5 * c * I32 + c * s + 4 * c * 3 * s + c * s + 2 * 4 * c * 3 * s + 2 * r * s
    return [dict(family="cubature", kernel=f"reduced force by cubature, r = {r} (cubature_element + project kernels)",
                 items=c, unit="cubature points", warp_s=t_w, numpy_s=t_n, bytes=b,
                 check=f"max |f_r warp - numpy| / max |f_r| = {err:.1e}",
                 byte_model="basis rows of the touched vertices read by both kernels (r vec3 each), q, ids, weight, 4 dN/dX, "
                            "energy and node forces written then read, f_r accumulated",
                 numpy="x = X + U q, vectorised stable neo-Hookean forces, U^T f (all tets, weight 1)")]


def bench_skinning(mesh, x_np, args, precision, device, s):
    n, m, p = mesh.num_vertices, mesh.num_tets, args.points
    rng = np.random.default_rng(3)
    ti = rng.integers(0, m, p)
    w = rng.dirichlet(np.ones(4), p)
    emb = Embedding(tet_index=ti, vertex_ids=mesh.tets[ti].astype(np.int64), weights=w, distances=np.zeros(p),
                    outside=np.zeros(p, bool), num_vertices=n)
    sk = SurfaceSkinner(emb, mesh.tets, device=device, precision=precision)
    dt = np.float32 if s == 4 else np.float64
    x = wp.array(x_np.astype(dt), dtype=sk.vec_type, device=sk.device)
    out = wp.empty(p, dtype=sk.vec_type, device=sk.device)
    xd, wd, vids = x_np.astype(dt), w.astype(dt), emb.vertex_ids

    def numpy_skin():
        return np.einsum("pa,pak->pk", wd, xd[vids])

    t_w, t_n = paired_time(lambda: sk.apply(x, out), numpy_skin, sk.device, warp_repeats=args.repeats, numpy_repeats=3)
    err = float(np.abs(out.numpy() - emb.apply(x_np)).max())
    b = p * (4 * I32 + 4 * s + 3 * s) + n * 3 * s
    return [dict(family="skinning", kernel="x_surface = W x, 4 weights per point (SurfaceSkinner.apply)", items=p,
                 unit="surface points", warp_s=t_w, numpy_s=t_n, bytes=b, check=f"max |x_warp - x_numpy| = {err:.1e} m",
                 byte_model="4 vertex ids + 4 weights read and a vec3 written per point; mesh positions once",
                 numpy="einsum over gathered positions (Embedding.apply)")]


def run(args):
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    s = 4 if args.precision == "float32" else 8
    t0 = time.perf_counter()
    bw = memory_bandwidth(device, args.stream_mb)
    peak = max(bw.values())
    mesh, mat, model, sim, x_np = perturbed_beam(args.cells, args.precision, device)
    rows = []
    rows += bench_force_hessian(mesh, mat, sim, x_np, args, s)
    rows += bench_pcg(mesh, sim, args, s)
    rows += bench_cubature(mesh, model, x_np, args, args.precision, device, s)
    rows += bench_skinning(mesh, x_np, args, args.precision, device, s)
    for r in rows:
        r["items_per_s"] = r["items"] / r["warp_s"]
        r["numpy_items_per_s"] = r["items"] / r["numpy_s"]
        r["speedup_vs_numpy"] = r["numpy_s"] / r["warp_s"]
        r["effective_bandwidth_GBps"] = r["bytes"] / r["warp_s"] / 1e9
        r["fraction_of_device_bandwidth"] = r["bytes"] / r["warp_s"] / peak
    dev_name = f"{device.alias} ({platform.processor() or platform.machine()}, {os.cpu_count()} cores)" if device.is_cpu \
        else f"{device.alias} ({device.name})"
    res = dict(device=dev_name, precision=args.precision, cells=list(args.cells), tets=mesh.num_tets,
               vertices=mesh.num_vertices, bsr_blocks=sim.pattern.nnz, modes=args.modes, points=args.points,
               memory_bandwidth_GBps={k: v / 1e9 for k, v in bw.items()}, reference_bandwidth_GBps=peak / 1e9,
               seconds=time.perf_counter() - t0, results=rows)
    return res


def markdown(res):
    bw = ", ".join(f"{k} {v:.1f}" for k, v in res["memory_bandwidth_GBps"].items())
    L = [f"### Kernel families: {res['device']}, {res['precision']}", "",
         f"Mesh {res['tets']} tets / {res['vertices']} vertices ({res['bsr_blocks']} 3x3 blocks); measured memory "
         f"bandwidth (GB/s): {bw}; reference = best = {res['reference_bandwidth_GBps']:.1f} GB/s.", "",
         "| family | kernel | items | Warp M items/s | numpy M items/s | speed-up | eff. GB/s | of device BW |",
         "|---|---|---|---|---|---|---|---|"]
    for r in res["results"]:
        L.append(f"| {r['family']} | {r['kernel']} | {r['items']} {r['unit']} | {r['items_per_s'] / 1e6:.3f} | "
                 f"{r['numpy_items_per_s'] / 1e6:.3f} | {r['speedup_vs_numpy']:.1f}x | {r['effective_bandwidth_GBps']:.2f} | "
                 f"{100 * r['fraction_of_device_bandwidth']:.0f} % |")
    L += ["", "Byte models and baselines:", ""]
    for r in res["results"]:
        chk = f" Check: {r['check']}." if "check" in r else ""
        L.append(f"- **{r['family']}**: bytes = {r['byte_model']} ({r['bytes'] / 1e6:.2f} MB). numpy: {r['numpy']}.{chk}")
    return "\n".join(L) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--precision", default="float32", choices=["float32", "float64"])
    ap.add_argument("--cells", type=int, nargs=3, default=None, help="box cells (default 80 20 20; 40 10 10 with --quick)")
    ap.add_argument("--modes", type=int, default=20, help="basis columns r for the cubature kernels")
    ap.add_argument("--points", type=int, default=None, help="skinned points (default 200000; 50000 with --quick)")
    ap.add_argument("--pcg-iters", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=None)
    ap.add_argument("--stream-mb", type=float, default=None, help="array size for the bandwidth measurement (MB)")
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--json", default=None)
    ap.add_argument("--markdown", default=None)
    args = ap.parse_args(argv)
    args.cells = args.cells or ([40, 10, 10] if args.quick else [80, 20, 20])
    args.points = args.points or (50000 if args.quick else 200000)
    args.repeats = args.repeats or (5 if args.quick else 20)
    args.stream_mb = args.stream_mb or (64 if args.quick else 256)
    res = run(args)
    md = markdown(res)
    print(md)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(res, fh, indent=2)
    if args.markdown:
        with open(args.markdown, "w") as fh:
            fh.write(md)
    return res


if __name__ == "__main__":
    main()
