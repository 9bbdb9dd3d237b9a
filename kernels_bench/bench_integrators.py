"""Error vs step size and wall time of each time integrator on the 480-tet cantilever.

The `make demo` beam (examples/scenes/cantilever.toml: 1 x 0.2 x 0.2 m, 480 tets, stable
neo-Hookean E = 1e6 Pa, nu = 0.3, rho = 1000 kg/m^3, clamped at x = 0, gravity -y, from rest; the
scene's solver settings tol = 1e-5, cg_tol = 1e-3) for ``--duration`` seconds, with backward Euler,
BDF2, Newmark (average acceleration) and stiffness warping (polar, each scheme) at dt = 1/60,
1/120, 1/240 s.

Quantity: the mean y displacement of the tip face x = 1, sampled every 1/60 s. Error = RMS over
the samples of (tip - tip_ref) / peak |tip_ref|. Reference: Newmark at dt = 1/960 s with tol =
cg_tol = 1e-9 (second order: its own error is ~16x below Newmark's at 1/240); BDF2 at the same step
is run too and their difference printed as the reference's uncertainty. Time: wall-clock seconds
per simulated second on this device (every kernel compiled by a warm-up first).

    .venv/bin/python kernels_bench/bench_integrators.py [--duration 0.5] [--json PATH] [--plot docs/images/integrators_convergence.png]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402
import warp as wp  # noqa: E402

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
import warpfem as wf  # noqa: E402
from warpfem.scenes import load_scene  # noqa: E402

SCENE = os.path.join(ROOT, "examples", "scenes", "cantilever.toml")
FRAME = 1.0 / 60.0
DTS = (1 / 60, 1 / 120, 1 / 240)


def model(youngs_modulus=None):
    m = load_scene(SCENE).build(device="cpu", precision="float64").model  # the model is device independent
    if youngs_modulus is not None:  # the stiff variant: same beam, another material
        mat = m.material
        m = wf.Model(m.mesh, type(mat)(youngs_modulus=youngs_modulus, poisson_ratio=mat.poisson_ratio,
                                       density=mat.density), gravity=m.gravity)
        m.fix(np.flatnonzero(m.rest_positions[:, 0] < 1e-9))
    return m


DEVICE = "cpu"


def run(m, kind, integrator, dt, duration, **solver):
    if kind == "newton":
        sim = wf.Simulator(m, device=DEVICE, dt=dt, integrator=integrator, **solver)
    else:
        sim = wf.StiffnessWarpingSimulator(m, device=DEVICE, dt=dt, integrator=integrator, rotation="polar",
                                           cg_tol=solver.get("cg_tol", 1e-3))
    tip = np.flatnonzero(m.rest_positions[:, 0] > 1.0 - 1e-9)
    y0 = m.rest_positions[tip, 1].mean()
    sub = int(round(FRAME / dt))
    frames = int(round(duration / FRAME))
    samples, newton, seconds = [], 0, 0.0
    for _ in range(frames):
        wp.synchronize_device(DEVICE)
        t0 = time.perf_counter()
        for _ in range(sub):
            newton += sim.step().newton_iterations
        wp.synchronize_device(DEVICE)
        seconds += time.perf_counter() - t0
        samples.append(sim.positions()[tip, 1].mean() - y0)
    return np.array(samples), seconds / duration, newton / (frames * sub)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=0.5)
    ap.add_argument("--json")
    ap.add_argument("--plot")
    ap.add_argument("--youngs-modulus", type=float, help="run the beam with this E (Pa) instead of the scene's 1e6")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--quick", action="store_true", help="0.25 s instead of --duration")
    args = ap.parse_args(argv)
    global DEVICE
    DEVICE = args.device
    if args.quick:
        args.duration = 0.25
    wp.config.quiet = True
    m = model(args.youngs_modulus)
    scene_solver = dict(tol=1e-5, cg_tol=1e-3, max_iters=30)
    tight = dict(tol=1e-9, cg_tol=1e-9, max_iters=50)
    # warm-up: compile every kernel (both simulators, every integrator)
    for kind in ("newton", "warping"):
        for integ in ("backward_euler", "bdf2", "newmark"):
            run(m, kind, integ, 1 / 60, FRAME * 2, **scene_solver)
    ref, t_ref, _ = run(m, "newton", "newmark", 1 / 960, args.duration, **tight)
    ref_b, _, _ = run(m, "newton", "bdf2", 1 / 960, args.duration, **tight)
    peak = np.abs(ref).max()
    ref_unc = float(np.sqrt(np.mean((ref - ref_b) ** 2)) / peak)
    rows = []
    for kind in ("newton", "warping"):
        for integ in ("backward_euler", "bdf2", "newmark"):
            for dt in DTS:
                tip, spss, nwt = run(m, kind, integ, dt, args.duration, **scene_solver)
                err = float(np.sqrt(np.mean((tip - ref) ** 2)) / peak)
                rows.append(dict(simulator=kind, integrator=integ, dt=dt, error=err, seconds_per_second=spss,
                                 newton_per_step=nwt))
    load = os.getloadavg()[0]
    print(f"480-tet cantilever (E = {m.material.youngs_modulus:g} Pa), {args.duration} s, {wp.get_device(DEVICE)} ({platform.machine()}, {os.cpu_count()} cores, load {load:.1f}); "
          f"reference Newmark dt 1/960 (peak tip {peak:.4f} m; BDF2 at the same dt differs by {ref_unc:.1e})")
    print(f"{'simulator':9s} {'integrator':15s} {'dt':>7s} {'error':>9s} {'s/sim s':>8s} {'newton/step':>11s}")
    for r in rows:
        print(f"{r['simulator']:9s} {r['integrator']:15s} 1/{1 / r['dt']:<5.0f} {r['error']:9.2e} "
              f"{r['seconds_per_second']:8.2f} {r['newton_per_step']:11.2f}")
    for kind in ("newton", "warping"):
        for integ in ("backward_euler", "bdf2", "newmark"):
            e = [r["error"] for r in rows if r["simulator"] == kind and r["integrator"] == integ]
            slope = np.polyfit(np.log(DTS), np.log(e), 1)[0]
            print(f"  {kind} {integ}: fitted order {slope:.2f}")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(dict(rows=rows, reference_uncertainty=ref_unc, peak=float(peak), load=load,
                           duration=args.duration), f, indent=1)
    if args.plot:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, ax = plt.subplots(figsize=(6, 4.2))
        styles = {"backward_euler": "o-", "bdf2": "s-", "newmark": "^-"}
        for kind, alpha in (("newton", 1.0), ("warping", 0.45)):
            for integ in ("backward_euler", "bdf2", "newmark"):
                e = [r["error"] for r in rows if r["simulator"] == kind and r["integrator"] == integ]
                ax.loglog(DTS, e, styles[integ], alpha=alpha,
                          label=f"{'Newton' if kind == 'newton' else 'warping'} {integ.replace('_', ' ')}")
        ax.set_xlabel("time step dt (s)")
        ax.set_ylabel("RMS tip error / peak tip displacement")
        ax.set_title(f"480-tet cantilever (E = {m.material.youngs_modulus:.0e} Pa): error vs step size")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=7)
        fig.tight_layout()
        os.makedirs(os.path.dirname(os.path.abspath(args.plot)), exist_ok=True)
        fig.savefig(args.plot, dpi=120)
        print(f"wrote {args.plot}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
