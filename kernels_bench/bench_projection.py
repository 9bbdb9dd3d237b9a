"""Newton iterations per step and step time with ``hessian_projection = "always"`` (projected
Newton: every element's dP/dF clamped to SPD) against ``"on_demand"`` (the exact Hessian until a
Newton system is indefinite, gives no descent direction or its full step fails; Longva et al.
2023, "Pitfalls of Projection: A study of Newton-type solvers for incremental potentials").

Cases (backward Euler, float64, default tolerances tol 1e-6 / cg_tol 1e-4 unless said):

* ``box03`` / ``box49``: a 2 x 0.5 x 0.5 m box of 12,288 tets, stable neo-Hookean E 1e5, rho 1000,
  clamped at x = 0, gravity, dt 1/60, nu 0.3 / 0.49 (the boxes of bench_scale.py);
* ``bunny``: examples/scenes/bunny.toml (22,874 tets, nu 0.4, base fixed, ears moved by a handle,
  mass damping 1) at dt 1/60 and at its own dt 1/24;
* ``squeeze``: ``stability_cases.squeezed_beam``, also in tests/test_projection_on_demand.py (1 x 0.2 x
  0.2 m, 144 tets, both ends held, the right end pushed 25 % in and 5 cm sideways over the run), dt 1/60 and dt 1 s (nearly
  quasi-static: it buckles and the exact Hessian is indefinite);
* ``bunny_fine``: examples/meshes/bunny.off tetrahedralised at ``max_edge_length = 0.004`` (TetGen,
  the ``mesh`` extra: 189,851 tets, 34,948 vertices, a scanned-statue-sized mesh), E 5e4, nu 0.4,
  base fixed, no damping, dt 1/24, multigrid unless ``--solver`` says otherwise (not in the default
  list: about a minute per step and mode here);
* ``twist``: the static two-turn twist of a bar clamped at both ends (kernels_bench/stability_cases.py
  ``clamped_bar``, 16 x 2 x 2 cells, 8 load steps).

Prints, per case and mode: Newton iterations per step (mean, max), projected retries, linear
iterations per Newton solve, seconds per step, converged steps, and the largest position difference
between the two modes after the last step.

    python kernels_bench/bench_projection.py [--cases box03 box49 bunny squeeze twist] [--steps 10]
        [--solver auto] [--markdown PATH]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)

import numpy as np  # noqa: E402

import warpfem as wf  # noqa: E402

MODES = ("always", "on_demand")


def _box(nu, solver, mode):
    mesh = wf.box_tet_mesh(size=(2.0, 0.5, 0.5), cells=(32, 8, 8))
    mat = wf.make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=nu, density=1000.0)
    model = wf.Model(mesh, mat, gravity=(0.0, 0.0, -9.81))
    model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (1e-6, 1, 1)))
    sim = wf.Simulator(model, dt=1.0 / 60.0, linear_solver=solver, hessian_projection=mode)
    return sim, lambda k: sim.step()


def _bunny(dt, solver, mode):
    from warpfem.scenes import load_scene

    scene = load_scene(os.path.join(ROOT, "examples", "scenes", "bunny.toml"))
    scene.spec.integrator.update(dt=dt, linear_solver=solver, hessian_projection=mode)
    run = scene.build(device="cpu", precision="float64")

    def advance(k):
        return run.sim.step()  # the handle stays where the scene starts it: the body settles under gravity

    return run.sim, advance


def _bunny_fine(solver, mode):
    mesh = wf.load_mesh(os.path.join(ROOT, "examples", "meshes", "bunny.off"), max_edge_length=0.004)
    mat = wf.make_material("stable_neo_hookean", youngs_modulus=5e4, poisson_ratio=0.4, density=1000.0)
    model = wf.Model(mesh, mat, gravity=(0.0, -9.81, 0.0))
    model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (1, 0.038, 1)))
    sim = wf.Simulator(model, dt=1.0 / 24.0, linear_solver="multigrid" if solver == "auto" else solver,
                       hessian_projection=mode)
    return sim, lambda k: sim.step()


def _squeeze(dt, solver, mode, steps):
    from kernels_bench.stability_cases import squeezed_beam

    return squeezed_beam(steps, dt=dt, linear_solver=solver, hessian_projection=mode)


def _twist(solver, mode, steps):
    from kernels_bench import stability_cases as S

    L = 2.0
    mesh = wf.box_tet_mesh(size=(L, 0.5, 0.5), cells=(16, 2, 2))
    X = mesh.vertices
    model = wf.Model(mesh, S.material("stable_neo_hookean"))
    left, right = np.flatnonzero(X[:, 0] < 1e-9), np.flatnonzero(X[:, 0] > L - 1e-9)
    model.fix(np.concatenate([left, right]))
    sim = wf.Simulator(model, linear_solver=solver, hessian_projection=mode, tol=1e-8, max_iters=60)
    c = np.array([0.0, 0.25, 0.25])

    def advance(k):
        ang = 4.0 * np.pi * (k + 1) / steps
        R = np.array([[1, 0, 0], [0, np.cos(ang), -np.sin(ang)], [0, np.sin(ang), np.cos(ang)]])
        sim.set_targets(right, (X[right] - c) @ R.T + c)
        return sim.solve_static()

    return sim, advance


def build(case, solver, mode, steps):
    if case == "box03":
        return _box(0.3, solver, mode)
    if case == "box49":
        return _box(0.49, solver, mode)
    if case == "bunny":
        return _bunny(1.0 / 60.0, solver, mode)
    if case == "bunny24":
        return _bunny(1.0 / 24.0, solver, mode)
    if case == "bunny_fine":
        return _bunny_fine(solver, mode)
    if case == "squeeze":
        return _squeeze(1.0 / 60.0, solver, mode, steps)
    if case == "squeeze_dt1":
        return _squeeze(1.0, solver, mode, steps)
    if case == "twist":
        return _twist(solver, mode, steps)
    raise SystemExit(f"unknown case {case!r}")


def run(case, solver, mode, steps):
    import warnings

    sim, advance = build(case, solver, mode, steps)
    its, retries, lin, secs, conv = [], 0, 0, [], 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for k in range(steps):
            t0 = time.perf_counter()
            st = advance(k)
            secs.append(time.perf_counter() - t0)
            its.append(st.newton_iterations)
            retries += st.projected_retries
            lin += st.linear_iterations
            conv += bool(st.converged)
    return dict(case=case, mode=mode, newton_mean=float(np.mean(its)), newton_max=int(np.max(its)), retries=retries,
                linear_per_newton=lin / max(sum(its), 1), seconds=float(np.median(secs[1:] if steps > 1 else secs)),
                converged=conv, steps=steps, x=sim.positions())


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--cases", nargs="*", default=["box03", "box49", "bunny", "bunny24", "squeeze", "squeeze_dt1", "twist"])
    p.add_argument("--steps", type=int, default=10)
    p.add_argument("--solver", default="auto")
    p.add_argument("--markdown", default=None)
    a = p.parse_args(argv)
    lines = [f"CPU {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load "
             f"{os.getloadavg()[0]:.1f} at the start; solver {a.solver}; {a.steps} steps per case (twist: load steps)",
             "", "| case | mode | Newton/step (max) | projected retries | linear it./Newton | s/step (median) | converged | max dx (m) |",
             "|---|---|---|---|---|---|---|---|"]
    print("\n".join(lines), flush=True)
    for case in a.cases:
        rows = [run(case, a.solver, m, a.steps) for m in MODES]
        dx = float(np.abs(rows[0]["x"] - rows[1]["x"]).max())
        for r in rows:
            line = (f"| {case} | {r['mode']} | {r['newton_mean']:.2f} ({r['newton_max']}) | {r['retries']} | "
                    f"{r['linear_per_newton']:.1f} | {r['seconds']:.3f} | {r['converged']}/{r['steps']} | {dx:.1e} |")
            lines.append(line)
            print(line, flush=True)
    if a.markdown:
        with open(a.markdown, "w") as f:
            f.write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
