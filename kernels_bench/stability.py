"""Stability at the extremes: every case x material x precision, as a table + JSON + markdown.

Each case function builds a small scene, drives an integrator into an extreme and returns a dict
of measured numbers plus a ``verdict``. Integrators: the core Newton solver (``warpfem.Simulator``:
backward Euler or static solve; Tet4, Tet10, Hex8, Hex27), stiffness warping
(``warpfem.StiffnessWarpingSimulator``, polar and qr rotations) and reduced mode
(``warpfem.reduced.ReducedSimulator``). ``twist_study`` is the two-turn twist investigation of
docs/stability.md. Verdicts:

- ``"recovers"`` / ``"ok"``: finite, converged where it had to, and the physics check passed;
- ``"reported"``: the solver did not converge but said so (``SolveStats.converged`` False or
  ``SolveFailed``), never accepting NaN;
- ``"fails"``: the documented failure of the method (e.g. linear elasticity under large rotation);
- ``"SILENT"``: a NaN/inf state accepted or an unreported wrong answer (a bug; must never appear).

The case functions are in ``kernels_bench/stability_cases.py`` (importable; the fast subset in
``tests/test_stability.py`` uses them); this script is the driver and the report.

Usage::

    python kernels_bench/stability.py [--quick] [--only WORDS] [--json out/stability.json] [--markdown out/stability.md]

``--only warping-qr,float32`` runs only the cases whose tag (group material precision integrator
element) holds every listed word; groups: recover poisson dt bar spin mesh locking amplitude
twist-study.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:  # run as a script: make the repository importable
    sys.path.insert(0, str(ROOT))

import warp as wp  # noqa: E402

from kernels_bench import stability_cases as cases  # noqa: E402
from kernels_bench.stability_cases import (E_SOFT, MATERIALS, PRECISIONS, cantilever_any, cantilever_dynamics,  # noqa: E402
                                           clamped_bar, element_incompressible, element_locking, incompressible,
                                           locking, real_mesh, recover, recover_any, reduced_dynamics,
                                           reduced_large_amplitude, spinning, twist_study, warping_bar,
                                           warping_uniaxial)


# -- driver --------------------------------------------------------------------------------------
def all_cases(quick=False):
    """(tag, callable) for every case x material x integrator x element x precision; ``tag``
    ("group material precision integrator element") is what ``--only`` filters on before running."""
    cases = []

    def add(tag, fn):
        cases.append((tag, fn))

    for prec in PRECISIONS:
        # core Newton solver, Tet4, every material
        for m in MATERIALS:
            for start in ("scrambled", "plane", "line", "point", "mirrored"):
                add(f"recover {m} {prec} newton tet4", lambda m=m, p=prec, s=start: recover(m, p, s))
            for nu in (0.49, 0.499, 0.4999):
                add(f"poisson {m} {prec} newton tet4", lambda m=m, p=prec, nu=nu: incompressible(m, p, nu))
            for dt in (1 / 24, 1 / 10):
                for E in (E_SOFT, 1e9):
                    add(f"dt {m} {prec} newton tet4",
                        lambda m=m, p=prec, dt=dt, E=E: cantilever_dynamics(m, p, dt=dt, youngs_modulus=E))
            for mode in ("stretch", "twist"):
                add(f"bar {m} {prec} newton tet4", lambda m=m, p=prec, mode=mode: clamped_bar(m, p, mode))
            add(f"spin {m} {prec} newton tet4", lambda m=m, p=prec: spinning(m, p))
            meshes = ("octopus-low.mesh",) if quick else ("octopus-low.mesh", "bunny.mesh")
            for name in meshes:
                add(f"mesh {m} {prec} newton tet4", lambda m=m, p=prec, name=name: real_mesh(m, p, name))
        add(f"locking linear {prec} newton tet4", lambda p=prec: locking(p))
        # second-order time integrators of the core solver (docs/integrators.md), stable neo-Hookean Tet4
        for integ in ("newton-bdf2", "newton-newmark"):
            tag = f"stable_neo_hookean {prec} {integ} tet4"
            for start in ("scrambled", "mirrored"):
                add(f"recover {tag}", lambda p=prec, i=integ, s=start: recover_any("stable_neo_hookean", p, s, integrator=i))
            for dt in (1 / 24, 1 / 10):
                for E in (E_SOFT, 1e9):
                    add(f"dt {tag}", lambda p=prec, i=integ, dt=dt, E=E: cantilever_any(
                        "stable_neo_hookean", p, dt=dt, youngs_modulus=E, integrator=i, steps=10))
        # stiffness warping (material kind ignored: corotated E, nu), Tet4
        for integ in ("warping-polar", "warping-qr"):
            tag = f"corotated {prec} {integ} tet4"
            for start in ("scrambled", "plane", "line", "point", "mirrored"):
                add(f"recover {tag}", lambda p=prec, i=integ, s=start: recover_any("corotated", p, s, integrator=i, steps=40,
                                                                                     damping_mass=2.0))
            add(f"recover {tag}", lambda p=prec, i=integ: dict(recover_any("corotated", p, "scrambled", integrator=i),
                                                              case=f"recover:scrambled,undamped[{i}]"))
            for dt in (1 / 24, 1 / 10):
                for E in (E_SOFT, 1e9):
                    add(f"dt {tag}", lambda p=prec, i=integ, dt=dt, E=E: cantilever_any("corotated", p, dt=dt, youngs_modulus=E,
                                                                                         integrator=i, cells=(6, 2, 2), steps=10))
            for nu in (0.49, 0.499, 0.4999):
                add(f"poisson {tag}", lambda p=prec, i=integ, nu=nu: warping_uniaxial(p, nu, rotation=i.split("-")[1]))
            add(f"bar {tag}", lambda p=prec, i=integ: dict(warping_bar(p, "stretch", rotation=i.split("-")[1], dt=0.5),
                                                          case=f"bar:stretch,h=0.5[{i}]"))
            add(f"bar {tag}", lambda p=prec, i=integ: dict(warping_bar(p, "stretch", rotation=i.split("-")[1], dt=0.1,
                                                                       damping_mass=2.0), case=f"bar:stretch,h=0.1[{i}]"))
            add(f"bar {tag}", lambda p=prec, i=integ: warping_bar(p, "twist", rotation=i.split("-")[1], dt=0.1,
                                                                 damping_mass=2.0, settle=60))
            for name in ("octopus-low.mesh",) if quick else ("octopus-low.mesh", "bunny.mesh"):
                add(f"mesh {tag}", lambda p=prec, i=integ, name=name: real_mesh("corotated", p, name, integrator=i))
        # element types, core Newton solver, stable neo-Hookean (+ linear for locking)
        for el, cells in (("tet10", (3, 1, 1)), ("hex8", (3, 1, 1)), ("hex27", (3, 1, 1))):
            tag = f"stable_neo_hookean {prec} newton {el}"
            for dt in (1 / 24, 1 / 10):
                for E in (E_SOFT, 1e9):
                    add(f"dt {tag}", lambda p=prec, el=el, c=cells, dt=dt, E=E: cantilever_any(
                        "stable_neo_hookean", p, dt=dt, youngs_modulus=E, element=el, cells=c))
            for nu in (0.49, 0.4999):
                add(f"poisson {tag}", lambda p=prec, el=el, nu=nu: element_incompressible(el, "stable_neo_hookean", p, nu))
            rc = (2, 2, 2) if el == "hex8" else (1, 1, 1)
            for start in ("mirrored", "scrambled", "plane"):
                add(f"recover {tag}", lambda p=prec, el=el, s=start, rc=rc: recover_any("stable_neo_hookean", p, s, element=el,
                                                                                          cells=rc))
        for el, vi in (("tet4", "full"), ("tet10", "full"), ("hex8", "full"), ("hex8", "reduced"), ("hex27", "full")):
            add(f"locking linear {prec} newton {el}", lambda p=prec, el=el, vi=vi: element_locking(el, p, volumetric_integration=vi))
        # reduced mode (stable neo-Hookean, r = 8, modal derivatives, cubature tol 0.05)
        tag = f"stable_neo_hookean {prec} reduced tet4"
        for dt in (1 / 24, 1 / 10):
            for E in (E_SOFT, 1e9):
                add(f"dt {tag}", lambda p=prec, dt=dt, E=E: reduced_dynamics(p, dt=dt, youngs_modulus=E))
        for a in (0.1, 1.0, 3.0, 10.0):
            add(f"amplitude {tag}", lambda p=prec, a=a: reduced_large_amplitude(p, amplitude=a))
        for name in ("octopus-low.mesh",) if quick else ("octopus-low.mesh", "bunny.mesh"):
            add(f"mesh {tag}", lambda p=prec, name=name: real_mesh("stable_neo_hookean", p, name, integrator="reduced"))
    # the two-turn twist study (float64, stable neo-Hookean; docs/stability.md)
    for cells, hess, pred, inc in (((16, 2, 2), "projected", False, 32), ((16, 2, 2), "exact", False, 32),
                                   ((16, 2, 2), "hybrid", False, 32), ((16, 2, 2), "exact", True, 32),
                                   ((16, 2, 2), "exact", False, 128), ((16, 3, 3), "exact", False, 32),
                                   ((16, 4, 4), "exact", False, 32), ((32, 4, 4), "exact", False, 32)):
        add("twist-study stable_neo_hookean float64 newton tet4",
            lambda c=cells, h=hess, pr=pred, n=inc: twist_study(cells=c, hessian=h, predictor=pr, increments=n))
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
    ap.add_argument("--only", default="", help="comma-separated words that must all be in a case's tag "
                    "(group material precision integrator element), e.g. 'warping-polar,float64' or 'reduced'")
    args = ap.parse_args(argv)
    wp.init()
    wp.set_device(args.device)
    cases.DEVICE = args.device
    dev = wp.get_device(args.device)
    devname = f"{dev.name} ({platform.processor() or platform.machine()}, {os.cpu_count()} cores)" if dev.is_cpu else dev.name
    rows = []
    hdr = f"{'case':<26}{'material':<20}{'prec':<9}{'verdict':<10}{'steps':>6}{'!conv':>6}{'fail':>5}{'newton':>7}{'sec':>7}  numbers"
    print(hdr)
    for tag, fn in all_cases(args.quick):
        if args.only and not all(word in tag.split() for word in args.only.split(",")):
            continue
        r = fn()
        r.setdefault("integrator", "newton")
        r.setdefault("element", "tet4")
        if r["case"].startswith("twist-study"):
            r["case"] += f",{r['hessian']}{',predictor' if r['predictor'] else ''},{r['increments']}inc"
            r["verdict"] = "reported" if r["stopped_at"] else "recovers"
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
