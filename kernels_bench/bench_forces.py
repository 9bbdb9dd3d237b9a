"""Throughput of the per-element force kernel (F, P, scatter) and of Hessian assembly.

Usage: python kernels_bench/bench_forces.py [--device cpu|cuda:0] [--precision float32|float64]
                                           [--material stable_neo_hookean] [--cells 40 10 10] [--json PATH]

Baseline: the same computation vectorised in numpy (F = Ds Dm^-1, stable neo-Hookean P,
-vol P Dm^-T scattered with np.add.at; Hessian blocks from an explicit dP/dF contraction),
measured in the same run. Reported: elements per second and the ratio ``speedup_vs_numpy``.
"""

from __future__ import annotations

import argparse
import json
import platform
import time

import numpy as np
import warp as wp

import warpfem as wf
from warpfem.kernels import fem as FK


def numpy_snh_forces(X, tets, x, mu, lam, Dm_inv, vol):
    Ds = np.stack([x[tets[:, i]] - x[tets[:, 0]] for i in (1, 2, 3)], axis=2)
    F = Ds @ Dm_inv
    J = np.linalg.det(F)
    cof = np.stack([np.cross(F[:, :, 1], F[:, :, 2]), np.cross(F[:, :, 2], F[:, :, 0]), np.cross(F[:, :, 0], F[:, :, 1])], axis=2)
    P = mu * F + (lam * (J - 1 - mu / lam))[:, None, None] * cof
    H = -vol[:, None, None] * P @ Dm_inv.transpose(0, 2, 1)
    f = np.zeros_like(x)
    for i in range(3):
        np.add.at(f, tets[:, i + 1], H[:, :, i])
    np.add.at(f, tets[:, 0], -H.sum(axis=2))
    return f


def numpy_linear_hessian_blocks(g, vol, mu, lam):
    """Element blocks K_ab = vol (mu (ga.gb) I + mu gb ga^T + lam ga gb^T) (linear elasticity)."""
    gg = np.einsum("eai,ebi->eab", g, g)
    I = np.eye(3)
    K = mu * gg[:, :, :, None, None] * I + mu * np.einsum("ebi,eaj->eabij", g, g) + lam * np.einsum("eai,ebj->eabij", g, g)
    return vol[:, None, None, None, None] * K


def timeit(fn, repeats):
    fn()  # warm (compile)
    t = time.perf_counter()
    for _ in range(repeats):
        fn()
    return (time.perf_counter() - t) / repeats


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--precision", default="float32", choices=["float32", "float64"])
    ap.add_argument("--material", default="stable_neo_hookean")
    ap.add_argument("--cells", type=int, nargs=3, default=[40, 10, 10])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    wp.config.quiet = True
    wp.init()

    mesh = wf.box_tet_mesh(size=(4.0, 1.0, 1.0), cells=tuple(args.cells))
    mat = wf.make_material(args.material, youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
    model = wf.Model(mesh, mat)
    sim = wf.Simulator(model, device=args.device, precision=args.precision)
    rng = np.random.default_rng(0)
    x_np = mesh.vertices + 0.01 * rng.standard_normal(mesh.vertices.shape)
    sim.set_positions(x_np)
    m = mesh.num_tets
    dev = sim.device
    f = sim.new_vector()
    vals = sim.new_matrix_values()

    def warp_forces():
        f.zero_()
        wp.launch(FK.qp_force_kernel, dim=sim.num_points, inputs=[sim.x, sim.quadrature_points, sim.material_params, sim.scalar_type(1.0), f], device=dev)
        wp.synchronize_device(dev)

    def warp_hessian():
        vals.zero_()
        sim.assemble_stiffness(sim.x, vals)
        wp.synchronize_device(dev)

    X, tets = mesh.vertices, mesh.tets
    Dm = np.stack([X[tets[:, i]] - X[tets[:, 0]] for i in (1, 2, 3)], axis=2)
    Dm_inv, vol = np.linalg.inv(Dm), np.linalg.det(Dm) / 6
    g = sim.model.quadrature.qp_dNdX.reshape(m, 4, 3)
    dtype = np.float32 if args.precision == "float32" else np.float64
    Xd, xd, Dmi, vold, gd = (a.astype(dtype) for a in (X, x_np, Dm_inv, vol, g))

    t_wf = timeit(warp_forces, args.repeats)
    t_wh = timeit(warp_hessian, max(3, args.repeats // 4))
    t_nf = timeit(lambda: numpy_snh_forces(Xd, tets, xd, mat.kernel_mu, mat.kernel_lam, Dmi, vold), 3)
    t_nh = timeit(lambda: numpy_linear_hessian_blocks(gd, vold, mat.kernel_mu, mat.kernel_lam), 3)

    # correctness guard: Warp and numpy forces agree (stable neo-Hookean only)
    if args.material == "stable_neo_hookean":
        ref = numpy_snh_forces(X, tets, x_np, mat.kernel_mu, mat.kernel_lam, Dm_inv, vol)
        err = np.abs(sim.elastic_forces() - ref).max() / np.abs(ref).max()
        assert err < (1e-3 if args.precision == "float32" else 1e-9), err

    device_name = f"{dev.alias} ({platform.processor() or platform.machine()})" if dev.is_cpu else f"{dev.alias} ({dev.name})"
    rows = [
        {"kernel": "force (F, P, scatter)", "warp_s": t_wf, "numpy_s": t_nf},
        {"kernel": "hessian assembly (12x12, eigen-projected)", "warp_s": t_wh, "numpy_s": t_nh,
         "note": "numpy baseline assembles linear-elastic blocks only (no SVD, no projection, no scatter): a lower bound on its cost"},
    ]
    for r in rows:
        r["elements_per_s"] = m / r["warp_s"]
        r["numpy_elements_per_s"] = m / r["numpy_s"]
        r["speedup_vs_numpy"] = r["numpy_s"] / r["warp_s"]
    result = {"device": device_name, "precision": args.precision, "material": args.material,
              "elements": m, "vertices": mesh.num_vertices, "results": rows}
    print(f"device {device_name}, {args.precision}, {args.material}, {m} tets, {mesh.num_vertices} vertices")
    print(f"{'kernel':45s} {'warp Melem/s':>13s} {'numpy Melem/s':>14s} {'speedup':>8s}")
    for r in rows:
        print(f"{r['kernel']:45s} {r['elements_per_s'] / 1e6:13.3f} {r['numpy_elements_per_s'] / 1e6:14.3f} {r['speedup_vs_numpy']:8.1f}x")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=2)
    return result


if __name__ == "__main__":
    main()
