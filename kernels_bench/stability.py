"""Stability at the extremes (issue 7): every case x material x precision, as a table + JSON + markdown.

Each case function builds a small scene, drives the core Newton solver (``warpfem.Simulator``:
backward Euler or static solve) into an extreme, and returns a dict of measured numbers plus a
``verdict``:

- ``"recovers"`` / ``"ok"``: finite, converged where it had to, and the physics check passed;
- ``"reported"``: the solver did not converge but said so (``SolveStats.converged`` False or
  ``SolveFailed``), never accepting NaN;
- ``"fails"``: the documented failure of the method (e.g. linear elasticity under large rotation);
- ``"SILENT"``: a NaN/inf state accepted or an unreported wrong answer (a bug; must never appear).

The fast subset lives in ``tests/test_stability.py`` and imports these functions.

Usage::

    python kernels_bench/stability.py [--quick] [--json out/stability.json] [--markdown out/stability.md]
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import sys
import time
import warnings
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import warp as wp  # noqa: E402

import warpfem as wf  # noqa: E402

wp.config.quiet = True

MESHES = ROOT.parent / "shared" / "data" / "meshes"
MATERIALS = ("linear", "stvk", "corotated", "stable_neo_hookean")
PRECISIONS = ("float64", "float32")

E_SOFT, NU_SOFT, RHO = 1.0e5, 0.3, 1000.0


def material(name, *, youngs_modulus=E_SOFT, poisson_ratio=NU_SOFT, density=RHO):
    return wf.make_material(name, youngs_modulus=youngs_modulus, poisson_ratio=poisson_ratio, density=density)


# -- measurements ------------------------------------------------------------------------------
def tet_jacobians(x, mesh):
    """Volume ratio J = V(x) / V(X) of every tet."""
    from warpfem.mesh import tet_volumes

    return tet_volumes(x, mesh.tets) / mesh.rest_volumes()


def procrustes_rms(x, X):
    """RMS distance between x and the best rigid motion of X (rotation + translation, no
    reflection), relative to the bounding-box diagonal of X."""
    xc, Xc = x - x.mean(axis=0), X - X.mean(axis=0)
    U, _, Vt = np.linalg.svd(Xc.T @ xc)
    D = np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))])
    R = (U @ D @ Vt).T  # x ~ R X
    err = xc - Xc @ R.T
    diag = np.linalg.norm(X.max(axis=0) - X.min(axis=0))
    return float(np.sqrt((err ** 2).sum(axis=1).mean()) / diag)


class Run:
    """Steps a simulator, counting what each step reported; never lets NaN through unnoticed."""

    def __init__(self, sim):
        self.sim = sim
        self.steps = self.not_converged = self.failed = self.newton = self.cg = 0
        self.last_error = ""

    def step(self):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                st = self.sim.step()
        except wf.SolveFailed as exc:
            self.failed += 1
            self.last_error = str(exc)
            return None
        self.steps += 1
        self.newton += st.newton_iterations
        self.cg += st.cg_iterations
        if not st.converged:
            self.not_converged += 1
        return st

    def static(self, load_steps):
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", RuntimeWarning)
                st = self.sim.solve_static(load_steps=load_steps)
        except wf.SolveFailed as exc:
            self.failed += 1
            self.last_error = str(exc)
            return None
        self.steps += 1
        self.newton += st.newton_iterations
        self.cg += st.cg_iterations
        if not st.converged:
            self.not_converged += 1
        return st

    def summary(self):
        return dict(steps=self.steps, not_converged=self.not_converged, failed=self.failed,
                    newton_iterations=self.newton, cg_iterations=self.cg)


def _verdict(finite, reported, physics_ok):
    if not finite:
        return "SILENT"
    if physics_ok:
        return "recovers"
    return "reported" if reported else "fails"


# -- recovery cases (free body, no gravity, backward Euler with a large step) --------------------
def recover(mat_name, precision, start, *, squash=0.0, cells=(3, 3, 3), steps=20, dt=1.0, seed=0, **solver):
    """Start from a degenerate shape and let the free body relax (backward Euler, h = ``dt``).

    ``start``: "scrambled" (every vertex uniformly random in the bounding box), "plane", "line",
    "point" (squashed, plus 1e-6 relative jitter so the exact stationary point F = 0 is left),
    "mirrored" (reflected through the plane z = centre: every tet inverted).
    Recovery: Procrustes RMS < 1e-3 of the diagonal and every tet J in (0.9, 1.1).
    """
    mesh = wf.box_tet_mesh(size=(1.0, 1.0, 1.0), cells=cells)
    X = mesh.vertices
    sim = wf.Simulator(wf.Model(mesh, material(mat_name)), precision=precision, dt=dt, **solver)
    x = start_shape(X, start, seed, squash)
    sim.set_positions(x)
    run = Run(sim)
    t0 = time.perf_counter()
    energy_scale = E_SOFT * mesh.total_volume()
    for _ in range(steps):
        run.step()
        if run.failed > 2:
            break
        if sim.elastic_energy() < 1e-10 * energy_scale and run.steps > 2:
            break
    x = sim.positions()
    finite = bool(np.all(np.isfinite(x)))
    J = tet_jacobians(x, mesh) if finite else np.array([np.nan])
    rms = procrustes_rms(x, X) if finite else float("nan")
    ok = finite and rms < 1e-3 and J.min() > 0.9 and J.max() < 1.1
    reported = run.not_converged > 0 or run.failed > 0
    case = f"recover:{start}" + (f"@{squash:g}" if squash and start in ("plane", "line", "point") else "")
    return dict(case=case, material=mat_name, precision=precision, rms=rms,
                min_J=float(J.min()), max_J=float(J.max()), inverted=int((J <= 0).sum()),
                seconds=time.perf_counter() - t0, verdict=_verdict(finite, reported, ok), **run.summary())


def start_shape(X, start, seed=0, squash=0.0):
    rng = np.random.default_rng(seed)
    lo, hi = X.min(axis=0), X.max(axis=0)
    c = 0.5 * (lo + hi)
    x = X.copy()
    jitter = 1e-6 * np.linalg.norm(hi - lo) * rng.standard_normal(X.shape)
    if start == "scrambled":
        return rng.uniform(lo, hi, size=X.shape)
    axes = {"plane": [2], "line": [1, 2], "point": [0, 1, 2]}.get(start)
    if axes is not None:  # squashed: thickness ``squash`` times the rest size along ``axes``
        x[:, axes] = c[axes] + squash * (X[:, axes] - c[axes])
        return x + jitter
    if start == "mirrored":
        x[:, 2] = 2 * c[2] - x[:, 2]
        return x
    raise ValueError(f"unknown start shape {start!r}")


# -- nearly incompressible: uniaxial stretch of a unit cube, volume vs closed form --------------
def uniaxial_closed_form_J(mat_name, a, mu, lam):
    """Volume ratio J = a b^2 of a homogeneous uniaxial stress state at axial stretch a, with the
    Lame values mu, lambda (the *small-strain* ones; stable neo-Hookean reparametrised inside)."""
    from scipy.optimize import brentq

    if mat_name == "linear":  # lateral strain -nu eps, nu = lam / (2 (lam + mu)); J measured on positions
        b = 1.0 - lam / (2.0 * (lam + mu)) * (a - 1.0)
    elif mat_name == "stvk":
        b = math.sqrt(1.0 - lam * (a * a - 1.0) / (2.0 * (lam + mu)))
    elif mat_name == "stable_neo_hookean":
        m, l = mu, lam + mu
        alpha = 1.0 + m / l
        b = math.sqrt((alpha * l * a - m) / (l * a * a))
    elif mat_name == "corotated":
        b = brentq(lambda b: 4 * mu * (b - 1) + 2 * lam * (a * b * b - 1) * a * b, 1e-3, 2.0)
    else:
        raise ValueError(mat_name)
    return a * b * b


def incompressible(mat_name, precision, nu, *, a=1.5, cells=(2, 2, 2), load_steps=4, **solver):
    """Uniaxial stress (faces x = 0 and x = 1 held at x1 = a X1, normal component only) at Poisson
    ratio ``nu``: Newton must converge and the volume ratio must match the closed form."""
    mesh = wf.box_tet_mesh(size=(1.0, 1.0, 1.0), cells=cells)
    X = mesh.vertices
    mat = material(mat_name, poisson_ratio=nu)
    model = wf.Model(mesh, mat)
    left = np.flatnonzero(np.abs(X[:, 0]) < 1e-9)
    right = np.flatnonzero(np.abs(X[:, 0] - 1) < 1e-9)
    origin = np.flatnonzero(np.linalg.norm(X, axis=1) < 1e-9)
    ey = np.flatnonzero(np.linalg.norm(X - [0, 1, 0], axis=1) < 1e-9)
    model.fix(np.concatenate([left, right]), "x")
    model.fix(origin, "yz")
    model.fix(ey, "z")
    opts = dict(tol=1e-9 if precision == "float64" else 1e-5, cg_tol=1e-10 if precision == "float64" else 1e-6, max_iters=80)
    opts.update(solver)
    sim = wf.Simulator(model, precision=precision, **opts)
    targets = X.copy()
    targets[right, 0] = a
    moved = np.concatenate([left, right, origin, ey])
    sim.set_targets(moved, targets[moved])
    run = Run(sim)
    t0 = time.perf_counter()
    st = run.static(load_steps)
    x = sim.positions()
    finite = bool(np.all(np.isfinite(x)))
    mu_l = mat.youngs_modulus / (2 * (1 + nu))
    lam_l = mat.youngs_modulus * nu / ((1 + nu) * (1 - 2 * nu))
    J_closed = uniaxial_closed_form_J(mat_name, a, mu_l, lam_l)
    from warpfem.mesh import tet_volumes

    J = float(tet_volumes(x, mesh.tets).sum() / mesh.total_volume()) if finite else float("nan")
    rel = abs(J - J_closed) / J_closed if finite else float("nan")
    ok = finite and st is not None and st.converged and rel < (1e-6 if precision == "float64" else 1e-3)
    return dict(case=f"poisson:{nu}", material=mat_name, precision=precision, a=a, J=J, J_closed_form=J_closed,
                J_rel_error=rel, residual=(st.residual if st else float("nan")), seconds=time.perf_counter() - t0,
                verdict=_verdict(finite, run.not_converged + run.failed > 0, ok), **run.summary())


# -- large time steps and stiff materials: cantilever under gravity ------------------------------
def cantilever_dynamics(mat_name, precision, *, dt, youngs_modulus, steps=10, cells=(6, 2, 2), **solver):
    """A 3 x 0.5 x 0.5 m bar clamped at x = 0 falling under gravity from rest (backward Euler).

    Backward Euler is dissipative: the total energy (kinetic + elastic - x^T f_ext) must never grow
    beyond the solver tolerance. Returns the largest relative growth over any step.
    """
    mesh = wf.box_tet_mesh(size=(3.0, 0.5, 0.5), cells=cells)
    model = wf.Model(mesh, material(mat_name, youngs_modulus=youngs_modulus), gravity=(0.0, 0.0, -9.81))
    model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (1e-6, 2, 2)))
    sim = wf.Simulator(model, precision=precision, dt=dt, **solver)
    run = Run(sim)
    t0 = time.perf_counter()
    # energy scale: the gravitational work of a tip-size drop, rho g V L
    scale = RHO * 9.81 * mesh.total_volume() * 3.0
    energies = [sim.total_energy()]
    growth = 0.0
    for _ in range(steps):
        st = run.step()
        if st is None:
            if run.failed > 2:
                break
            continue
        energies.append(sim.total_energy())
        growth = max(growth, (energies[-1] - energies[-2]) / scale)
    x = sim.positions()
    finite = bool(np.all(np.isfinite(x))) and bool(np.all(np.isfinite(energies)))
    ok = finite and growth < 1e-6 and run.not_converged == 0 and run.failed == 0
    return dict(case=f"dt={dt:.4g},E={youngs_modulus:.0e}", material=mat_name, precision=precision,
                max_energy_growth=float(growth), final_energy=float(energies[-1] / scale),
                tip_z=float(x[:, 2].min()) if finite else float("nan"), seconds=time.perf_counter() - t0,
                verdict=_verdict(finite, run.not_converged + run.failed > 0, ok), **run.summary())


# -- extreme stretch and twist of a bar clamped at both ends ------------------------------------
def clamped_bar(mat_name, precision, mode, *, cells=(16, 2, 2), load_steps=None, **solver):
    """Bar 2 x 0.5 x 0.5 m, both end faces prescribed (static solve with ``set_targets``):
    ``mode`` "stretch" pulls the right face to x = 6 (3x), "twist" turns it by two full turns
    (720 degrees) about the bar's axis. Checks: converged, no inverted tet, and for the stretch the
    mid cross-section area ratio vs the homogeneous uniaxial value (end effects aside), for the
    twist the angle of the section at L/4 (reported, not judged: 720 degrees over 4 widths is beyond
    what a 2 x 2 cross-section resolves, and the bar may shed a turn)."""
    L = 2.0
    mesh = wf.box_tet_mesh(size=(L, 0.5, 0.5), cells=cells)
    X = mesh.vertices
    model = wf.Model(mesh, material(mat_name))
    left = np.flatnonzero(X[:, 0] < 1e-9)
    right = np.flatnonzero(X[:, 0] > L - 1e-9)
    model.fix(np.concatenate([left, right]))
    opts = dict(tol=1e-8 if precision == "float64" else 1e-5, max_iters=60)
    opts.update(solver)
    sim = wf.Simulator(model, precision=precision, **opts)
    c = np.array([0.0, 0.25, 0.25])
    tgt = X[right].copy()
    if mode == "stretch":
        tgt[:, 0] = 3 * L
        load_steps = load_steps or 8
    elif mode == "twist":
        load_steps = load_steps or 32
    else:
        raise ValueError(mode)
    run = Run(sim)
    t0 = time.perf_counter()
    if mode == "twist":  # ramp the angle (a linear ramp of positions would pass the axis)
        ok_steps = True
        for k in range(1, load_steps + 1):
            th = 4 * math.pi * k / load_steps
            R = np.array([[1, 0, 0], [0, math.cos(th), -math.sin(th)], [0, math.sin(th), math.cos(th)]])
            sim.set_targets(right, (X[right] - c) @ R.T + c)
            st = run.static(1)
            if st is None or not st.converged:
                ok_steps = False
                break
    else:
        sim.set_targets(right, tgt)
        st = run.static(load_steps)
        ok_steps = st is not None and st.converged
    x = sim.positions()
    finite = bool(np.all(np.isfinite(x)))
    J = tet_jacobians(x, mesh) if finite else np.array([np.nan])
    out = dict(case=f"bar:{mode}", material=mat_name, precision=precision, min_J=float(J.min()),
               max_J=float(J.max()), inverted=int((J <= 0).sum()))
    ok = finite and ok_steps and J.min() > 0
    if finite and mode == "stretch":
        mid = np.flatnonzero(np.abs(X[:, 0] - L / 2) < 1e-9)
        w = np.ptp(x[mid, 1]) * np.ptp(x[mid, 2]) / 0.25
        out["mid_area_ratio"] = float(w)
    if finite and mode == "twist":
        q = np.flatnonzero(np.abs(X[:, 0] - L / 4) < 1e-9)
        d0, d1 = X[q, 1:] - c[1:], x[q, 1:] - c[1:]
        ang = np.angle(np.sum((d1[:, 0] + 1j * d1[:, 1]) * np.conj(d0[:, 0] + 1j * d0[:, 1])))
        # 180 for a uniform twist; a coarse bar may shed a whole turn through a snap (then ~90)
        out["quarter_angle_deg"] = float(np.degrees(ang) % 360.0)
        # untwisted inside (linear elasticity: two turns of the end are the identity) is a failure
        ok = ok and 45.0 < out["quarter_angle_deg"] < 315.0
    out.update(seconds=time.perf_counter() - t0, verdict=_verdict(finite, run.not_converged + run.failed > 0, ok),
               **run.summary())
    return out


# -- real meshes -----------------------------------------------------------------------------
def load_real(name):
    path = MESHES / name
    return wf.load_mesh(path, inside_surface=True) if name.startswith("bunny") else wf.load_mesh(path)


def real_mesh(mat_name, precision, name, *, steps=2, dt=1.0 / 60.0, youngs_modulus=E_SOFT, **solver):
    """A couple of backward Euler steps under gravity with the lowest 10 % (in z) fixed."""
    mesh = load_real(name)
    X = mesh.vertices
    lo, hi = mesh.bounds()
    model = wf.Model(mesh, material(mat_name, youngs_modulus=youngs_modulus), gravity=(0.0, 0.0, -9.81))
    model.fix(np.flatnonzero(X[:, 2] < lo[2] + 0.1 * (hi[2] - lo[2])))
    sim = wf.Simulator(model, precision=precision, dt=dt, **solver)
    run = Run(sim)
    t0 = time.perf_counter()
    for _ in range(steps):
        run.step()
    x = sim.positions()
    finite = bool(np.all(np.isfinite(x)))
    J = tet_jacobians(x, mesh) if finite else np.array([np.nan])
    vol = mesh.rest_volumes()
    ok = finite and run.not_converged == 0 and run.failed == 0 and J.min() > 0
    return dict(case=f"mesh:{name}", material=mat_name, precision=precision, tets=mesh.num_tets,
                rest_volume_ratio=float(vol.max() / vol.min()), min_J=float(J.min()), max_J=float(J.max()),
                displacement=float(np.abs(x - X).max()) if finite else float("nan"),
                seconds=time.perf_counter() - t0, verdict=_verdict(finite, not ok, ok), **run.summary())


# -- documented failures -------------------------------------------------------------------------
def spinning(mat_name, precision, *, omega=2.0, steps=12, dt=1.0 / 24.0, cells=(3, 3, 3)):
    """A free unit cube spinning about z at ``omega`` rad/s (no gravity) for a quarter turn-ish.

    Rotation-invariant materials keep the volume (|J - 1| tiny); linear elasticity sees the
    rotation as strain ("ghost forces") and the volume grows: the documented failure.
    """
    mesh = wf.box_tet_mesh(size=(1.0, 1.0, 1.0), cells=cells)
    X = mesh.vertices
    sim = wf.Simulator(wf.Model(mesh, material(mat_name)), precision=precision, dt=dt)
    c = X.mean(axis=0)
    v = np.cross([0.0, 0.0, omega], X - c)
    sim.set_velocities(v)
    run = Run(sim)
    t0 = time.perf_counter()
    for _ in range(steps):
        run.step()
    x = sim.positions()
    from warpfem.mesh import tet_volumes

    finite = bool(np.all(np.isfinite(x)))
    J = float(tet_volumes(x, mesh.tets).sum() / mesh.total_volume()) if finite else float("nan")
    rms = procrustes_rms(x, X) if finite else float("nan")
    ok = finite and abs(J - 1) < 1e-2 and rms < 1e-2  # centrifugal dilation ~0.35 % is physical
    return dict(case="spin", material=mat_name, precision=precision, turned_deg=float(np.degrees(omega * dt * steps)),
                volume_ratio=J, rms=rms, seconds=time.perf_counter() - t0,
                verdict=_verdict(finite, run.not_converged + run.failed > 0, ok), **run.summary())


def locking(precision="float64", *, nu=0.4999, cells=(10, 2, 2)):
    """Tet4 volumetric locking: cantilever (10 x 1 x 1, E = 1e4, rho g = 1) tip deflection at ``nu``
    relative to nu = 0.3 (beam theory: nearly the same, Timoshenko shear term changes it < 1 %)."""
    def tip(n):
        mesh = wf.box_tet_mesh(size=(10, 1, 1), cells=cells)
        model = wf.Model(mesh, wf.LinearElastic(youngs_modulus=1e4, poisson_ratio=n, density=1.0), gravity=(0, 0, -1.0))
        model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (0, 2, 2)))
        sim = wf.Simulator(model, precision=precision, tol=1e-8 if precision == "float64" else 1e-5,
                           cg_tol=1e-10 if precision == "float64" else 1e-6, max_cg_iters=20000)
        st = sim.solve_static()
        tipv = np.abs(mesh.vertices[:, 0] - 10) < 1e-9
        return -(sim.positions() - mesh.vertices)[tipv, 2].mean(), st

    t0 = time.perf_counter()
    d_ref, st_ref = tip(0.3)
    d, st = tip(nu)
    ratio = d / d_ref
    return dict(case=f"locking:{nu}", material="linear", precision=precision, tip=float(d), tip_nu03=float(d_ref),
                ratio=float(ratio), converged=bool(st.converged and st_ref.converged), seconds=time.perf_counter() - t0,
                verdict="fails" if ratio < 0.5 else "recovers")


# -- driver --------------------------------------------------------------------------------------
def all_cases(quick=False):
    """(label, callable) for every case x material x precision."""
    cases = []
    for prec in PRECISIONS:
        for m in MATERIALS:
            for start in ("scrambled", "plane", "line", "point", "mirrored"):
                cases.append(lambda m=m, p=prec, s=start: recover(m, p, s))
            for nu in (0.49, 0.499, 0.4999):
                cases.append(lambda m=m, p=prec, nu=nu: incompressible(m, p, nu))
            for dt in (1 / 24, 1 / 10):
                for E in (E_SOFT, 1e9):
                    cases.append(lambda m=m, p=prec, dt=dt, E=E: cantilever_dynamics(m, p, dt=dt, youngs_modulus=E))
            for mode in ("stretch", "twist"):
                cases.append(lambda m=m, p=prec, mode=mode: clamped_bar(m, p, mode))
            cases.append(lambda m=m, p=prec: spinning(m, p))
            meshes = ("octopus-low.mesh",) if quick else ("octopus-low.mesh", "bunny.mesh")
            for name in meshes:
                cases.append(lambda m=m, p=prec, name=name: real_mesh(m, p, name))
        cases.append(lambda p=prec: locking(p))
    return cases


def _fmt(v):
    if isinstance(v, float):
        return f"{v:.3g}"
    return str(v)


KEYS = ("rms", "min_J", "J_rel_error", "max_energy_growth", "mid_area_ratio", "quarter_angle_deg", "volume_ratio",
        "ratio", "rest_volume_ratio")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="skip the bunny (22874 tets)")
    ap.add_argument("--device", default="cpu", help="Warp device (results are device-independent; timing is not)")
    ap.add_argument("--json", default="out/stability.json")
    ap.add_argument("--markdown", default="out/stability.md")
    ap.add_argument("--only", default="", help="substring filter on case/material/precision")
    args = ap.parse_args(argv)
    wp.init()
    wp.set_device(args.device)
    dev = wp.get_device(args.device)
    devname = f"{dev.name} ({platform.processor() or platform.machine()}, {os.cpu_count()} cores)" if dev.is_cpu else dev.name
    rows = []
    hdr = f"{'case':<26}{'material':<20}{'prec':<9}{'verdict':<10}{'steps':>6}{'!conv':>6}{'fail':>5}{'newton':>7}{'sec':>7}  numbers"
    print(hdr)
    for fn in all_cases(args.quick):
        r = fn()
        if args.only and not any(args.only in str(r[k]) for k in ("case", "material", "precision")):
            continue
        rows.append(r)
        nums = ", ".join(f"{k}={_fmt(r[k])}" for k in KEYS if k in r)
        print(f"{r['case']:<26}{r['material']:<20}{r['precision']:<9}{r['verdict']:<10}{r.get('steps', 0):>6}"
              f"{r.get('not_converged', 0):>6}{r.get('failed', 0):>5}{r.get('newton_iterations', 0):>7}{r['seconds']:>7.2f}  {nums}",
              flush=True)
        _write(args, rows, devname)  # after every run, so an interrupted sweep still leaves its table
    silent = [r for r in rows if r["verdict"] == "SILENT"]
    _write(args, rows, devname)
    print(f"\n{len(rows)} runs, {len(silent)} SILENT; wrote {args.json} and {args.markdown}")
    return 1 if silent else 0


def _write(args, rows, devname):
    for path in (args.json, args.markdown):
        Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(dict(device=devname, rows=rows), indent=1, default=float))
    Path(args.markdown).write_text(envelope_markdown(rows, devname))


def envelope_markdown(rows, devname):
    """Envelope table: one row per case, one column per material x precision, cell = verdict."""
    cols = [(m, p) for m in MATERIALS for p in PRECISIONS]
    cases = []
    for r in rows:
        if r["case"] not in cases:
            cases.append(r["case"])
    lines = [f"Measured on {devname} with `python kernels_bench/stability.py`.", "",
             "| case | " + " | ".join(f"{m} {p[-2:]}" for m, p in cols) + " |",
             "|---" * (len(cols) + 1) + "|"]
    for c in cases:
        cells = []
        for m, p in cols:
            hit = [r for r in rows if r["case"] == c and r["material"] == m and r["precision"] == p]
            cells.append(hit[0]["verdict"] if hit else "")
        lines.append(f"| {c} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    sys.exit(main())
