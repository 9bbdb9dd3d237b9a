"""Peer comparison: warpfem (backward Euler, BDF2, Newmark; pcg / direct / auto) vs the ``newton`` engine's VBD.

The same cantilever in both, on the same device in the same run: the `make demo` beam (1 m x 0.2 m
x 0.2 m, 20x2x2 cells split into 6 tets each: 480 tets, 189 vertices), stable neo-Hookean,
density 1000 kg/m^3 (total mass 40 kg), gravity 9.81 m/s^2 along -z, every vertex on the face
x = 0 clamped, no damping, released from rest at t = 0; three materials (``--beams``): soft
(E = 1e6 Pa, nu = 0.3), stiff (E = 1e8, nu = 0.3) and nearly incompressible (E = 1e6, nu = 0.48).
``--beam-set 864``: the 864-tet beams instead, 16x3x3 cells x 6 tets (864 tets, 272 vertices), soft
(E 1e6, nu 0.3), stiff (E 5e7, nu 0.3), nearly incompressible (E 1e6, nu 0.47).

Both codes use the same energy: newton's VBD tet energy is the stable neo-Hookean of Smith, de Goes
& Kim (2018, sec. 3.4) without the log term, reparametrised from the Lame parameters it is given
(``k_mu`` = mu_L, ``k_lambda`` = lambda_L) exactly as warpfem's ``StableNeoHookean`` is; both lump
rho V / 4 of each tet on its vertices. Builder quirks handled here: ``ModelBuilder(up_axis=Z,
gravity=(0, 0, -9.81))`` (the gravity argument must be a 3-vector), ``k_damp = 0`` passed explicitly
(its builder default, 0, could be changed by a caller), clamped particles get mass 0 and lose ``ParticleFlags.ACTIVE`` (so the particle mass sum
is 39 kg = 40 kg minus the clamped vertices' share; warpfem keeps that mass on fixed vertices, where
it has no effect), ``builder.color()`` before ``finalize`` (VBD needs the graph colouring). VBD
works in float32 only.

Quantity: the mean z displacement of the vertices on the tip face x = 1 (21 or 16), sampled every 1/60 s
for ``--duration`` seconds. Error = RMS over the samples of (tip - tip_ref), divided by the peak
|tip_ref| (the largest tip displacement of the reference). Reference: warpfem Newmark (second
order), float64, tol = cg_tol = 1e-8 (1e-6 with --quick), direct solves, at dt_r = 1/60 /
``--ref-substeps``; its own error is estimated from the run at 2 dt_r as |x(dt_r) - x(2 dt_r)| / 3
(Richardson's estimate for a second-order scheme) and printed. Time: seconds per simulated second,
both wall-clock and this process's CPU time (``wp.synchronize_device`` before and after; every
kernel compiled by a warm-up run first); the targets and frontiers use CPU time unless ``--time
wall`` (on a machine shared with other jobs wall time depends on their load; both codes run
single-threaded on the CPU). Targets, per beam: within the time of VBD's default setting (dt 1/60,
10 iterations) warpfem's error is >= 10x lower (aim 100x), within half that time >= 100x lower
and for every VBD point warpfem reaches its error in no more time.

    .venv/bin/python kernels_bench/bench_peer_vbd.py [--device cpu] [--quick] [--beam-set 480|864] [--beams soft,stiff,incompressible]
        [--time cpu|wall] [--json PATH] [--markdown PATH]

Skips with a message (exit code 0) when ``newton`` is not installed (``pip install newton`` or
``pip install -e .[peer]``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
import warnings

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):  # as in bench_kernels.py
    os.environ.setdefault(_var, "1")

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))  # this checkout's warpfem

import numpy as np  # noqa: E402
import warp as wp  # noqa: E402

import warpfem as wf  # noqa: E402

SIZE, CELLS = (1.0, 0.2, 0.2), (20, 2, 2)
E, NU, RHO, G = 1.0e6, 0.3, 1000.0, 9.81
FRAME_DT = 1.0 / 60.0
# the time the targets and frontiers use: CPU seconds of this process (both codes run single-threaded
# on the CPU: Warp's CPU kernels, PARDISO with MKL_NUM_THREADS=1), robust to other jobs on a shared
# machine; "--time wall" uses wall-clock seconds instead (equal on an idle machine)
TIME_KEY = "cpu_s_per_sim_s"


def beam():
    mesh = wf.box_tet_mesh(size=SIZE, cells=CELLS)  # CELLS: the beam set's (main sets it)
    fixed = np.flatnonzero(mesh.vertices[:, 0] < 1e-9)
    tip = np.flatnonzero(mesh.vertices[:, 0] > SIZE[0] - 1e-9)
    return mesh, fixed, tip


def lame(E, nu):
    return E / (2 * (1 + nu)), E * nu / ((1 + nu) * (1 - 2 * nu))


def run_warpfem(mesh, fixed, tip, *, device, precision, dt, tol, cg_tol, frames, E=E, nu=NU, integrator="backward_euler",
                linear_solver="auto", max_iters=50):
    """Tip z displacement per frame (frames,), wall seconds, Newton and linear iterations, unconverged steps."""
    mat = wf.StableNeoHookean(youngs_modulus=E, poisson_ratio=nu, density=RHO)
    model = wf.Model(mesh, mat, gravity=(0.0, 0.0, -G), mass_matrix="lumped")
    model.fix(fixed)
    sub = int(round(FRAME_DT / dt))
    assert abs(sub * dt - FRAME_DT) < 1e-12, "dt must divide 1/60 s"
    sim = wf.Simulator(model, device=device, precision=precision, dt=dt, tol=tol, cg_tol=cg_tol, integrator=integrator,
                       linear_solver=linear_solver, max_iters=max_iters, max_cg_iters=5000)
    z0 = mesh.vertices[tip, 2].mean()
    out = np.zeros(frames)
    newton = cg = bad = 0
    secs = cpu = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for k in range(frames):
            wp.synchronize_device(device)
            t, c = time.perf_counter(), time.process_time()
            try:
                for _ in range(sub):
                    st = sim.step()
                    newton += st.newton_iterations
                    cg += st.linear_iterations
                    bad += not st.converged
            except wf.SolveFailed:
                out[k:] = np.nan
                secs += time.perf_counter() - t
                cpu += time.process_time() - c
                break
            wp.synchronize_device(device)
            secs += time.perf_counter() - t
            cpu += time.process_time() - c
            out[k] = sim.positions()[tip, 2].mean() - z0  # read-back outside the timed region
    steps = frames * sub
    return dict(tip=out, seconds=secs, cpu_seconds=cpu, newton_per_step=newton / steps, cg_per_step=cg / steps,
                unconverged_steps=bad, steps=steps)


class VBDBeam:
    """The same beam in newton's SolverVBD (float32)."""

    def __init__(self, newton, mesh, fixed, *, device, E=E, nu=NU):
        self.newton, self.device = newton, device
        mu, lam = lame(E, nu)
        b = newton.ModelBuilder(up_axis=newton.Axis.Z, gravity=(0.0, 0.0, -G))
        b.add_soft_mesh(pos=(0.0, 0.0, 0.0), rot=wp.quat_identity(), scale=1.0, vel=(0.0, 0.0, 0.0),
                        vertices=mesh.vertices.tolist(), indices=mesh.tets.reshape(-1).tolist(),
                        density=RHO, k_mu=mu, k_lambda=lam, k_damp=0.0)
        active = int(newton.ParticleFlags.ACTIVE)
        for i in fixed:
            b.particle_mass[i] = 0.0
            b.particle_flags[i] = int(b.particle_flags[i]) & ~active
        b.color()
        self.model = b.finalize(device=device)
        pm = self.model.particle_mass.numpy()
        self.total_mass = float(pm.sum())
        self.gravity = np.asarray(self.model.gravity.numpy()).reshape(-1, 3)[0].tolist()
        self.num_tets = int(self.model.tet_count)

    def run(self, tip, *, iterations, substeps, frames):
        newton = self.newton
        solver = newton.solvers.SolverVBD(self.model, iterations=iterations, particle_enable_tile_solve=False)
        s0, s1, ctl = self.model.state(), self.model.state(), self.model.control()
        z0 = s0.particle_q.numpy()[tip, 2].mean()
        dt = FRAME_DT / substeps
        out = np.zeros(frames)
        secs = cpu = 0.0
        for k in range(frames):
            wp.synchronize_device(self.device)
            t, c = time.perf_counter(), time.process_time()
            for _ in range(substeps):
                s0.clear_forces()
                solver.step(s0, s1, ctl, None, dt)
                s0, s1 = s1, s0
            wp.synchronize_device(self.device)
            secs += time.perf_counter() - t
            cpu += time.process_time() - c
            out[k] = s0.particle_q.numpy()[tip, 2].mean() - z0
        return dict(tip=out, seconds=secs, cpu_seconds=cpu)


def pareto(points):
    """Indices of the (time, error) points not dominated by another (less time and less error)."""
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], np.inf
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


def compare(wf_rows, vbd_rows):
    """Error ratio at equal time and time ratio at equal error, for each warpfem frontier point."""
    out = []
    wf_front = pareto([(r[TIME_KEY], r["error"]) for r in wf_rows])
    for i in wf_front:
        r = wf_rows[i]
        t, e = r[TIME_KEY], r["error"]
        within = [v for v in vbd_rows if v[TIME_KEY] <= t and np.isfinite(v["error"])]
        reach = [v for v in vbd_rows if v["error"] <= e]
        row = dict(warpfem=r["config"], time=t, error=e)
        if within:
            v = min(within, key=lambda v: v["error"])
            row.update(vbd_best_within_time=v["config"], vbd_error=v["error"], error_ratio_vbd_over_warpfem=v["error"] / e)
        if reach:
            v = min(reach, key=lambda v: v[TIME_KEY])
            row.update(vbd_fastest_reaching_error=v["config"], vbd_time=v[TIME_KEY],
                       time_ratio_vbd_over_warpfem=v[TIME_KEY] / t)
        out.append(row)
    return out


def error_of(tip, ref, amp):
    return float(np.sqrt(np.mean((tip - ref) ** 2)) / amp) if np.all(np.isfinite(tip)) else float("inf")


BEAM_SETS = {  # name: (cells of the 1 x 0.2 x 0.2 m beam, each split into 6 tets; {beam: (Young's modulus, Poisson ratio)})
    # the `make demo` cantilever: 20x2x2 cells, 480 tets, 189 vertices
    "480": ((20, 2, 2), {"soft": (1.0e6, 0.3), "stiff": (1.0e8, 0.3), "incompressible": (1.0e6, 0.48)}),
    # the three 864-tet cantilevers (soft E 1e6, stiff E 5e7, nu 0.47): 16x3x3 cells (the near-cubic
    # subdivision of 144 cells: 0.0625 x 0.067 x 0.067 m), 864 tets, 272 vertices; soft and stiff at nu 0.3
    "864": ((16, 3, 3), {"soft": (1.0e6, 0.3), "stiff": (5.0e7, 0.3), "incompressible": (1.0e6, 0.47)}),
}
BEAMS = BEAM_SETS["480"][1]


def targets(wf_rows, vbd_rows):
    """The targets: (1) warpfem's best error within the time of VBD's default setting (dt 1/60,
    10 iterations) is >= 10x lower than VBD's (aim 100x), and >= 100x lower within half
    that time; (2) for every VBD point, warpfem reaches its error in no more time."""
    default = next(v for v in vbd_rows if v["dt"] == FRAME_DT and v["iterations"] == 10)

    def best_within(t):
        within = [r for r in wf_rows if r[TIME_KEY] <= t and np.isfinite(r["error"])]
        best = min(within, key=lambda r: r["error"]) if within else None
        return best, (default["error"] / best["error"] if best else 0.0)

    best, ratio = best_within(default[TIME_KEY])
    half, half_ratio = best_within(0.5 * default[TIME_KEY])
    reach = []
    for v in vbd_rows:
        cands = [r for r in wf_rows if r["error"] <= v["error"]]
        w = min(cands, key=lambda r: r[TIME_KEY]) if cands else None
        reach.append(dict(vbd=v["config"], vbd_time=v[TIME_KEY], vbd_error=v["error"],
                          warpfem=w["config"] if w else None, warpfem_time=w[TIME_KEY] if w else None,
                          met=bool(w is not None and w[TIME_KEY] <= v[TIME_KEY])))
    return dict(vbd_default=default["config"], vbd_default_time=default[TIME_KEY],
                vbd_default_error=default["error"], warpfem_best_within=best["config"] if best else None,
                warpfem_best_within_time=best[TIME_KEY] if best else None,
                warpfem_best_within_error=best["error"] if best else None, error_ratio=ratio,
                target_10x=bool(ratio >= 10.0), aim_100x=bool(ratio >= 100.0),
                warpfem_best_within_half=half["config"] if half else None,
                warpfem_best_within_half_time=half[TIME_KEY] if half else None,
                warpfem_best_within_half_error=half["error"] if half else None, error_ratio_half_time=half_ratio,
                target_100x_half_time=bool(half_ratio >= 100.0), reach=reach,
                frontier_reaches_every_vbd_error=all(r["met"] for r in reach))


def grids(quick):
    """warpfem settings (integrator, precision, substeps, tol, cg_tol, linear solver[, Newton iterations per step])
    and VBD (substeps, iterations)."""
    if quick:
        wf_grid = ([(i, "float64", sub, 1e-2, 1e-1, "auto") for i in ("backward_euler", "newmark", "bdf2") for sub in (1, 4)]
                   + [("newmark", "float64", 1, 1e-5, 1e-3, "auto"), ("newmark", "float32", 1, 1e-2, 1e-1, "auto"),
                      ("newmark", "float64", 1, 1e-2, 1e-1, "pcg"), ("newmark", "float64", 1, 1e-2, 1e-1, "direct")])
        vbd_grid = [(1, 10), (5, 5), (5, 20), (10, 5)]
    else:
        wf_grid = ([(i, "float64", sub, tol, cg, "auto") for i in ("backward_euler", "newmark", "bdf2") for sub in (1, 2, 4, 10)
                    for tol, cg in ((1e-2, 1e-1), (1e-5, 1e-3)) if sub < 10 or tol > 1e-3]
                   + [(i, "float32", sub, 1e-2, 1e-1, "auto") for i in ("backward_euler", "newmark") for sub in (1, 4)]
                   + [(i, "float64", sub, 1e-2, 1e-1, ls) for i in ("backward_euler", "newmark") for sub in (1, 4)
                      for ls in ("pcg", "direct")]
                   # one Newton iteration per step (a linearly implicit step, flagged as not converged)
                   + [(i, p, 1, 1e-2, 1e-1, "direct", 1) for i in ("newmark", "bdf2") for p in ("float32", "float64")])
        vbd_grid = [(1, 5), (1, 10), (1, 20), (2, 10), (5, 5), (5, 10), (10, 5), (10, 10), (20, 5)]
    return wf_grid, vbd_grid


def run_beam(newton, name, E_, nu_, args, device, duration, frames, ref_sub):
    mesh, fixed, tip = beam()
    wf_grid, vbd_grid = grids(args.quick)
    # reference: Newmark (second order), float64, tight tolerances, direct solves, at dt_r and 2 dt_r;
    # its own error is estimated as |x(dt_r) - x(2 dt_r)| / (2^2 - 1) (Richardson's estimate for order 2)
    t0 = time.perf_counter()
    ref_tol = 1e-6 if args.quick else 1e-8
    kw = dict(device=device, precision="float64", tol=ref_tol, cg_tol=ref_tol, frames=frames, E=E_, nu=nu_,
              integrator="newmark", linear_solver="direct")
    fine = run_warpfem(mesh, fixed, tip, dt=FRAME_DT / ref_sub, **kw)
    coarse = run_warpfem(mesh, fixed, tip, dt=FRAME_DT / (ref_sub // 2), **kw)
    ref = dict(tip=fine["tip"])
    amp = float(np.abs(ref["tip"]).max())
    ref_self = error_of(coarse["tip"], fine["tip"], amp) / 3.0
    print(f"[{name}] E = {E_:g} Pa, nu = {nu_:g}: device {device.alias}, beam {mesh.num_tets} tets / {mesh.num_vertices} vertices, "
          f"{duration:g} s simulated; reference = Newmark float64 dt 1/{60 * ref_sub}, tol {ref_tol:g}: peak tip displacement "
          f"{amp:.4g} m; its estimated error |x(dt) - x(2 dt)| / 3 = {ref_self:.2e} ({time.perf_counter() - t0:.0f} s)", flush=True)

    wf_rows = []
    for integ, prec, sub, tol, cg, ls, *cap in wf_grid:
        max_iters = cap[0] if cap else 50  # an optional 7th entry: Newton iterations per step
        r = run_warpfem(mesh, fixed, tip, device=device, precision=prec, dt=FRAME_DT / sub, tol=tol, cg_tol=cg, frames=frames,
                        E=E_, nu=nu_, integrator=integ, linear_solver=ls, max_iters=max_iters)
        one = f" max_iters={max_iters}" if cap else ""
        row = dict(code="warpfem", config=f"{integ} {prec} dt=1/{60 * sub} tol={tol:g} cg_tol={cg:g} {ls}{one}", integrator=integ,
                   precision=prec, dt=FRAME_DT / sub, tol=tol, cg_tol=cg, linear_solver=ls,
                   wall_s_per_sim_s=r["seconds"] / duration, cpu_s_per_sim_s=r["cpu_seconds"] / duration,
                   error=error_of(r["tip"], ref["tip"], amp), newton_per_step=r["newton_per_step"], cg_per_step=r["cg_per_step"],
                   unconverged_steps=r["unconverged_steps"], steps=r["steps"])
        wf_rows.append(row)
        print(f"  warpfem {row['config']:58s} {row['wall_s_per_sim_s']:7.2f} wall / {row['cpu_s_per_sim_s']:6.2f} cpu s/sim-s  err {row['error']:.3e}  "
              f"newton/step {row['newton_per_step']:.1f} lin/step {row['cg_per_step']:.0f} unconverged {row['unconverged_steps']}",
              flush=True)

    vb = VBDBeam(newton, mesh, fixed, device=device, E=E_, nu=nu_)
    vb.run(tip, iterations=1, substeps=1, frames=1)  # warm (compiles newton's kernels on first use)
    vbd_rows = []
    for sub, it in vbd_grid:
        r = vb.run(tip, iterations=it, substeps=sub, frames=frames)
        row = dict(code="newton-vbd", config=f"float32 dt=1/{60 * sub} iterations={it}", precision="float32",
                   dt=FRAME_DT / sub, iterations=it, wall_s_per_sim_s=r["seconds"] / duration,
                   cpu_s_per_sim_s=r["cpu_seconds"] / duration, error=error_of(r["tip"], ref["tip"], amp))
        vbd_rows.append(row)
        print(f"  vbd     {row['config']:58s} {row['wall_s_per_sim_s']:7.2f} wall / {row['cpu_s_per_sim_s']:6.2f} cpu s/sim-s  err {row['error']:.3e}", flush=True)
    tg = targets(wf_rows, vbd_rows)
    print(f"[{name}] VBD default {tg['vbd_default_time']:.2f} s/sim-s err {tg['vbd_default_error']:.2e}; warpfem best within "
          f"that time: {tg['warpfem_best_within']} err {tg['warpfem_best_within_error']} -> {tg['error_ratio']:.3g}x "
          f"(10x: {tg['target_10x']}, 100x: {tg['aim_100x']}); within half that time: {tg['warpfem_best_within_half']} "
          f"err {tg['warpfem_best_within_half_error']} -> {tg['error_ratio_half_time']:.3g}x (100x: {tg['target_100x_half_time']}); frontier reaches every VBD error in no more time: "
          f"{tg['frontier_reaches_every_vbd_error']}", flush=True)
    return dict(name=name, youngs_modulus=E_, poisson_ratio=nu_, tets=mesh.num_tets, vertices=mesh.num_vertices,
                reference=dict(integrator="newmark", dt=FRAME_DT / ref_sub, tol=ref_tol, peak_tip_m=amp,
                               estimated_error=ref_self, tip=ref["tip"].tolist()),
                vbd_particle_mass=vb.total_mass, warpfem=wf_rows, vbd=vbd_rows, comparison=compare(wf_rows, vbd_rows),
                targets=tg,
                warpfem_frontier=[wf_rows[i]["config"] for i in pareto([(r[TIME_KEY], r["error"]) for r in wf_rows])],
                vbd_frontier=[vbd_rows[i]["config"] for i in pareto([(r[TIME_KEY], r["error"]) for r in vbd_rows])])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--quick", action="store_true", help="0.35 s of simulation and a smaller grid of settings")
    ap.add_argument("--beam-set", choices=tuple(BEAM_SETS), default="480",
                    help="480: the make-demo cantilever (20x2x2 cells); 864: the 864-tet beams (16x3x3 cells, E 1e6 / 5e7, nu 0.47)")
    ap.add_argument("--beams", default=",".join(BEAM_SETS["480"][1]),
                    help=f"comma-separated subset of {', '.join(BEAM_SETS['480'][1])}")
    ap.add_argument("--duration", type=float, default=None, help="simulated seconds (default 0.5; 0.35 with --quick: to the first peak)")
    ap.add_argument("--ref-substeps", type=int, default=None, help="reference dt = 1/60 / this, even (default 32; 16 with --quick)")
    ap.add_argument("--time", choices=("cpu", "wall"), default="cpu",
                    help="time of the targets and frontiers: this process's CPU seconds (default) or wall seconds")
    ap.add_argument("--json", default=None)
    ap.add_argument("--markdown", default=None)
    args = ap.parse_args(argv)
    global TIME_KEY, CELLS, BEAMS
    TIME_KEY = f"{args.time}_s_per_sim_s"
    CELLS, BEAMS = BEAM_SETS[args.beam_set]
    wp.config.quiet = True
    try:
        import newton  # noqa: PLC0415
    except ImportError as exc:
        print(f"SKIP: the 'newton' package is not installed ({exc}); install it with "
              "`pip install newton` or `pip install -e .[peer]` to run the peer comparison.")
        return {"skipped": True, "reason": f"newton not installed: {exc}"}
    wp.init()
    device = wp.get_device(args.device)
    duration = args.duration or (0.35 if args.quick else 0.5)
    frames = int(round(duration / FRAME_DT))
    ref_sub = args.ref_substeps or (16 if args.quick else 32)
    names = [b.strip() for b in args.beams.split(",") if b.strip()]
    for b in names:
        if b not in BEAMS:
            ap.error(f"unknown beam {b!r}; choose from {', '.join(BEAMS)}")
    mesh, fixed, tip = beam()
    # warm-up: compile every kernel (both precisions, every integrator and linear solver)
    for integ in ("backward_euler", "newmark", "bdf2"):
        for prec in ("float32", "float64"):
            for ls in ("pcg", "direct"):
                run_warpfem(mesh, fixed, tip, device=device, precision=prec, dt=FRAME_DT, tol=1e-2, cg_tol=1e-3, frames=2,
                            integrator=integ, linear_solver=ls)
    t_all = time.perf_counter()
    beams = [run_beam(newton, b, *BEAMS[b], args, device, duration, frames, ref_sub) for b in names]
    device_name = f"{device.alias} ({platform.processor() or platform.machine()}, {os.cpu_count()} cores)" if device.is_cpu else f"{device.alias} ({device.name})"
    result = dict(device=device_name, load=os.getloadavg()[0], beam_set=args.beam_set, newton_version=newton.__version__, warp_version=wp.config.version,
                  scene=dict(size_m=SIZE, cells=CELLS, tets=mesh.num_tets, vertices=mesh.num_vertices, density=RHO,
                             gravity=G, duration_s=duration), time=TIME_KEY, beams=beams, seconds=time.perf_counter() - t_all)
    md = markdown(result)
    print(md)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(result, fh, indent=2)
    if args.markdown:
        with open(args.markdown, "w") as fh:
            fh.write(md)
    return result


def markdown(res):
    L = [f"### Peer comparison: warpfem vs newton {res['newton_version']} VBD ({res['device']}, load {res['load']:.1f})", "",
         f"Cantilever {res['scene']['tets']} tets, {res['scene']['duration_s']:g} s simulated, three materials. Error = RMS over "
         "frames (1/60 s) of the tip-displacement error / peak tip displacement of the reference. Time = seconds per "
         f"simulated second ({'CPU seconds of the process' if res['time'].startswith('cpu') else 'wall seconds'} in the "
         f"targets and frontiers; both in the tables). Whole run {res['seconds']:.0f} s wall.", "",
         "| beam | VBD default (dt 1/60, 10 it.): time, error | warpfem best within that time | its error | error ratio | "
         "10x? | 100x? | warpfem best within half that time | its error | ratio | 100x? | "
         "warpfem reaches every VBD error in no more time? |", "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for b in res["beams"]:
        t = b["targets"]
        e = f"{t['warpfem_best_within_error']:.2e}" if t["warpfem_best_within"] else "-"
        L.append(f"| {b['name']} (E {b['youngs_modulus']:g}, nu {b['poisson_ratio']:g}) | {t['vbd_default_time']:.2f} s, "
                 f"{t['vbd_default_error']:.2e} | {t['warpfem_best_within'] or 'none that fast'} ({t['warpfem_best_within_time'] or 0:.2f} s) | {e} | "
                 f"{t['error_ratio']:.3g} | {'yes' if t['target_10x'] else 'NO'} | {'yes' if t['aim_100x'] else 'no'} | "
                 f"{t['warpfem_best_within_half'] or 'none that fast'} ({t['warpfem_best_within_half_time'] or 0:.2f} s) | "
                 f"{(t['warpfem_best_within_half_error'] or float('nan')):.2e} | {t['error_ratio_half_time']:.3g} | "
                 f"{'yes' if t['target_100x_half_time'] else 'NO'} | "
                 f"{'yes' if t['frontier_reaches_every_vbd_error'] else 'NO'} |")
    for b in res["beams"]:
        ref = b["reference"]
        L += ["", f"#### {b['name']} beam: E = {b['youngs_modulus']:g} Pa, nu = {b['poisson_ratio']:g}", "",
              f"Reference: warpfem Newmark, float64, dt {ref['dt']:.3g} s, tol = cg_tol = {ref['tol']:g}, direct solves; peak tip "
              f"displacement {ref['peak_tip_m']:.4g} m; its estimated error (difference to the run at twice the step, / 3 for "
              f"second order) {ref['estimated_error']:.1e}.", "",
              "| code | configuration | wall s per simulated s | CPU s per simulated s | tip error | Newton/step | linear it./step |",
              "|---|---|---|---|---|---|---|"]
        for r in b["warpfem"] + b["vbd"]:
            nt = f"{r['newton_per_step']:.1f}" if "newton_per_step" in r else "-"
            cg = f"{r['cg_per_step']:.0f}" if "cg_per_step" in r else "-"
            L.append(f"| {r['code']} | {r['config']} | {r['wall_s_per_sim_s']:.2f} | {r['cpu_s_per_sim_s']:.2f} | {r['error']:.2e} | {nt} | {cg} |")
        L += ["", "Every VBD point against the fastest warpfem setting with at most its error:", "",
              "| VBD point | time | error | fastest warpfem at <= that error | time | met |", "|---|---|---|---|---|---|"]
        for r in b["targets"]["reach"]:
            wt = f"{r['warpfem_time']:.2f}" if r["warpfem_time"] is not None else "-"
            L.append(f"| {r['vbd']} | {r['vbd_time']:.2f} | {r['vbd_error']:.2e} | {r['warpfem'] or 'none'} | {wt} | "
                     f"{'yes' if r['met'] else 'NO'} |")
    return "\n".join(L) + "\n"


if __name__ == "__main__":
    sys.exit(0 if main() is not None else 1)
