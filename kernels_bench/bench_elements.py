"""Accuracy per second of each element type on the cantilever under self-weight.

Beam x in [0, 10], y, z in [0, 1], E = 1e4, nu = 0, rho g = 1 in -z, x = 0 clamped; quantity: mean
tip u_z, Timoshenko 1.512 (shared/reference section 1). For each element type and mesh: DOFs,
Newton iterations, CG iterations, seconds per Newton iteration (Hessian assembly + gradient + PCG
solve; linear elasticity converges in one), cost relative to Tet4 on the same cells (the baseline
measured in the same run), quadrature points, time of one Hessian assembly alone, and the
tip-deflection error.

    .venv/bin/python kernels_bench/bench_elements.py [--device cpu] [--precision float64] [--quick]

Two more tables (instead of the accuracy table):

``--assembly``: Hessian assembly alone (the kernel the Newton solver calls once per iteration) per
element type, for linear elasticity and stable neo-Hookean at a deformed state: the library kernel
(per-point work hoisted: dP/dF prepared once per quadrature point, per block only the contraction)
against the baseline ``legacy_qp_hessian_kernel`` below (a verbatim copy of the kernel before the
hoist, which rebuilt Q diag(d) Q^T and the clamps for every (a, b) block), run alternately in the
same process (so machine load hits both alike); ms per assembly (median of ``--repeats``), million
quadrature points per second and the speed-up.

``--incompressible``: nu = 0.4999, 20x2x2 beam, every material, Tet10 / Hex8 with selective
reduced integration / Hex8 full / Tet4: tip deflection per unit load at small strain (rho g = 1e-3)
and at rho g = 1 (geometrically nonlinear; 5 load steps), Newton with direct solves of the
Warp-assembled stiffness and an energy line search (PCG is too slow at nu -> 1/2).
"""

from __future__ import annotations

import argparse
import time

from typing import Any

import numpy as np
import warp as wp

import warpfem as wf
from warpfem.kernels.common import qp_deformation_gradient
from warpfem.kernels.generic import both_precisions
from warpfem.materials.dispatch import material_eigensystem
from warpfem.materials.eigensystem import pair_axes

TIMOSHENKO = 1.512


# -- baseline for --assembly: the Hessian kernel as it was before the per-point hoist (verbatim) ------
@wp.func
def legacy_hessian_block(U: Any, V: Any, Q: Any, d: Any, twist: Any, flip: Any, ga: Any, gb: Any, project: int):
    zero = U.dtype(0.0)
    half = U.dtype(0.5)
    Vt = wp.transpose(V)
    a = Vt * ga
    b = Vt * gb
    dd = d
    tw = twist
    fl = flip
    if project != 0:
        dd = wp.vector(wp.max(d[0], zero), wp.max(d[1], zero), wp.max(d[2], zero))
        tw = wp.vector(wp.max(twist[0], zero), wp.max(twist[1], zero), wp.max(twist[2], zero))
        fl = wp.vector(wp.max(flip[0], zero), wp.max(flip[1], zero), wp.max(flip[2], zero))
    A = Q * wp.diag(dd) * wp.transpose(Q)
    M = wp.diag(a) * A * wp.diag(b)
    I = wp.identity(n=3, dtype=U.dtype)
    for k in range(3):
        i, j = pair_axes(k)
        ei = I[i]
        ej = I[j]
        ta = a[j] * ei - a[i] * ej
        tb = b[j] * ei - b[i] * ej
        fa = a[j] * ei + a[i] * ej
        fb = b[j] * ei + b[i] * ej
        M = M + (half * tw[k]) * wp.outer(ta, tb) + (half * fl[k]) * wp.outer(fa, fb)
    return U * M * wp.transpose(U)


@both_precisions(x="v[]", X="v[]", qp_dNdX="v[]", qp_weight="s[]", mu="s", lam="s", scale="s", values="m[]")
@wp.kernel
def legacy_qp_hessian_kernel(
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
    q = wp.tid()
    e = qp_element[q]
    F = qp_deformation_gradient(x, X, elements, k, e, q, qp_dNdX)
    U, V, Qs, ds, tw, fl = material_eigensystem(kind, F, mu, lam)
    c = scale * qp_weight[q]
    for a in range(k):
        ga = qp_dNdX[q * k + a]
        for b in range(a, k):
            blk = c * legacy_hessian_block(U, V, Qs, ds, tw, fl, ga, qp_dNdX[q * k + b], project)
            wp.atomic_add(values, block_index[(e * k + a) * k + b], blk)
            if b != a:
                wp.atomic_add(values, block_index[(e * k + b) * k + a], wp.transpose(blk))


def beam(et, cells):
    if et == "tet4":
        return wf.box_tet_mesh(size=(10, 1, 1), cells=cells)
    if et == "tet10":
        return wf.tet10_from_tet4(wf.box_tet_mesh(size=(10, 1, 1), cells=cells))
    return wf.box_hex_mesh(size=(10, 1, 1), cells=cells, order=1 if et == "hex8" else 2)


def run(et, cells, device, precision, repeats=2):
    mesh = beam(et, cells)
    model = wf.Model(mesh, wf.LinearElastic(youngs_modulus=1e4, poisson_ratio=0.0, density=1.0), gravity=(0, 0, -1.0))
    model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (0, 2, 2)))
    best = None
    for _ in range(repeats):  # the first run includes any kernel load; keep the fastest
        sim = wf.Simulator(model, device=device, precision=precision, tol=1e-8, cg_tol=1e-8, max_cg_iters=20000)
        wp.synchronize_device(device)
        t = time.perf_counter()
        st = sim.solve_static()
        wp.synchronize_device(device)
        t = time.perf_counter() - t
        if best is None or t < best[0]:
            best = (t, st, sim)
    t, st, sim = best
    vals = sim.assemble_stiffness()
    wp.synchronize_device(device)
    ta = time.perf_counter()
    for _ in range(3):
        vals.zero_()
        sim.assemble_stiffness(sim.x, vals)
    wp.synchronize_device(device)
    ta = (time.perf_counter() - ta) / 3
    X = mesh.vertices
    tip = np.abs(X[:, 0] - 10) < 1e-9
    d = -(sim.positions() - X)[tip, 2].mean()
    free = int((~model.fixed).sum())
    return dict(element=et, cells="x".join(map(str, cells)), dofs=free, newton=st.newton_iterations, cg=st.cg_iterations,
                s_per_newton=t / max(st.newton_iterations, 1), assembly=ta, qp=sim.num_points, tip=d, err=d / TIMOSHENKO - 1, converged=st.converged)


def assembly_rows(device, precision, repeats):
    """Hessian assembly time per element type / material at a deformed state (u ~ 1 % random):
    library kernel vs the pre-hoist baseline, alternated in one process."""
    plan = [("tet4", (40, 4, 4)), ("tet10", (20, 2, 2)), ("hex8", (40, 4, 4)), ("hex27", (20, 2, 2))]
    print("| element | cells | material | quad. points | ms baseline (per-block) | ms hoisted | M points/s hoisted | speed-up |")
    print("|---|---|---|---|---|---|---|---|")
    rows = []
    for et, cells in plan:
        mesh = beam(et, cells)
        x = mesh.vertices + 0.01 * np.random.default_rng(0).standard_normal(mesh.vertices.shape)
        for name in ("linear", "stable_neo_hookean"):
            mat = wf.make_material(name, youngs_modulus=1e4, poisson_ratio=0.3, density=1.0)
            sim = wf.Simulator(wf.Model(mesh, mat), device=device, precision=precision)
            xa = sim.new_vector(x)
            vals_new, vals_old = sim.new_matrix_values(), sim.new_matrix_values()

            def new():
                sim.assemble_stiffness(xa, vals_new)

            p, m = sim.quadrature_points, sim.material_params  # the baseline takes the structs' fields positionally
            legacy_args = [p.X, p.elements, p.k, p.element, p.weight, p.dNdX, m.kind, sim.scalar_type(m.mu), sim.scalar_type(m.lam)]

            def old():
                wp.launch(legacy_qp_hessian_kernel, dim=sim.num_points,
                          inputs=[xa, *legacy_args, sim.scalar_type(1.0), 1, sim.pattern.block_index, vals_old], device=device)

            new(), old()  # load the modules; then both must agree
            a, b = vals_new.numpy(), vals_old.numpy()
            assert np.abs(a - b).max() <= 1e-9 * np.abs(b).max(), "hoisted and baseline assemblies differ"
            times = {"old": [], "new": []}
            for _ in range(repeats):
                for key, fn, vals in (("old", old, vals_old), ("new", new, vals_new)):
                    vals.zero_()
                    wp.synchronize_device(device)
                    t = time.perf_counter()
                    fn()
                    wp.synchronize_device(device)
                    times[key].append(time.perf_counter() - t)
            t_old, t_new = float(np.median(times["old"])), float(np.median(times["new"]))
            r = dict(element=et, cells="x".join(map(str, cells)), material=name, qp=sim.num_points, ms_old=1e3 * t_old,
                     ms=1e3 * t_new, mqps=sim.num_points / t_new / 1e6, speedup=t_old / t_new)
            rows.append(r)
            print(f"| {et} | {r['cells']} | {name} | {r['qp']} | {r['ms_old']:.2f} | {r['ms']:.2f} | {r['mqps']:.3f} | "
                  f"{r['speedup']:.2f}x |", flush=True)
    return rows


def _static_direct(sim, model, load_steps):
    """Newton on V(x) - x^T f_ext with direct solves of the unprojected stiffness and a backtracking
    line search on the energy; returns the positions (n, 3) and the Newton iteration count."""
    import scipy.sparse.linalg as spla

    x = model.rest_positions.copy()
    free = ~model.fixed.ravel()
    fext0 = model.external_forces().ravel()
    its = 0
    for step in range(1, load_steps + 1):
        fext = fext0 * step / load_steps
        for _ in range(40):
            r = (sim.elastic_forces(x).ravel() + fext)[free]
            K = sim.stiffness_matrix(x, project=False).tocsr()[free][:, free]
            dx = spla.spsolve(K.tocsc(), r)
            its += 1
            e0 = sim.elastic_energy(x) - x.ravel() @ fext
            t = 1.0
            while True:
                xt = x.copy()
                xt.reshape(-1)[free] += t * dx
                if sim.elastic_energy(xt) - xt.ravel() @ fext <= e0 + 1e-12 * abs(e0) or t < 1e-4:
                    break
                t *= 0.5
            x = xt
            if np.abs(dx).max() < 1e-8 * np.abs(x - model.rest_positions).max():
                break
    return x, its


def incompressible_rows(device, precision):
    print("| material | load rho g | Tet10 | Hex8 reduced | Hex8 full | Tet4 | Hex8 reduced vs Tet10 |")
    print("|---|---|---|---|---|---|---|")
    rows = []
    for name in ("linear", "stvk", "corotated", "stable_neo_hookean"):
        for g, steps in ((1e-3, 1), (1.0, 5)):
            tips = []
            for et, vi in (("tet10", "full"), ("hex8", "reduced"), ("hex8", "full"), ("tet4", "full")):
                mesh = beam(et, (20, 2, 2))
                mat = wf.make_material(name, youngs_modulus=1e4, poisson_ratio=0.4999, density=1.0)
                model = wf.Model(mesh, mat, gravity=(0, 0, -g), volumetric_integration=vi)
                model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (0, 2, 2)))
                x, _ = _static_direct(wf.Simulator(model, device=device, precision=precision), model, steps)
                tip = np.abs(mesh.vertices[:, 0] - 10) < 1e-9
                tips.append(-(x - mesh.vertices)[tip, 2].mean() / g)
            rows.append(dict(material=name, load=g, tips=tips))
            print(f"| {name} | {g:g} | " + " | ".join(f"{d:.4f}" for d in tips) + f" | {100 * (tips[1] / tips[0] - 1):+.1f} % |",
                  flush=True)
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--precision", default="float64", choices=["float32", "float64"])
    ap.add_argument("--quick", action="store_true", help="only the two coarsest meshes")
    ap.add_argument("--assembly", action="store_true", help="Hessian assembly timings only")
    ap.add_argument("--incompressible", action="store_true", help="nu = 0.4999 locking table, every material")
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args()
    wp.config.quiet = True
    wp.init()
    if args.assembly:
        return assembly_rows(args.device, args.precision, args.repeats)
    if args.incompressible:
        return incompressible_rows(args.device, args.precision)
    print("| element | cells | free DOFs | Newton its | CG its | ms / Newton it | cost vs Tet4 same cells | quad. points | ms Hessian assembly | tip u_z | error vs 1.512 |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    plan = [(10, 1, 1), (20, 2, 2), (40, 4, 4)] if args.quick else [(10, 1, 1), (20, 2, 2), (40, 4, 4), (80, 8, 8)]
    limit = {"tet10": 3, "hex27": 3}  # the quadratic elements reach the answer long before 80x8x8
    rows = []
    for i, cells in enumerate(plan):
        base = None
        for et in ("tet4", "tet10", "hex8", "hex27"):
            if i >= limit.get(et, len(plan)):
                continue
            r = run(et, cells, args.device, args.precision)
            base = base or r["s_per_newton"]
            r["ratio"] = r["s_per_newton"] / base
            rows.append(r)
            print(f"| {r['element']} | {r['cells']} | {r['dofs']} | {r['newton']} | {r['cg']} | "
                  f"{1e3 * r['s_per_newton']:.1f} | {r['ratio']:.2f} | {r['qp']} | {1e3 * r['assembly']:.1f} | {r['tip']:.5f} | {100 * r['err']:+.2f} % |"
                  + ("" if r["converged"] else " (not converged)"), flush=True)
    return rows


if __name__ == "__main__":
    main()
