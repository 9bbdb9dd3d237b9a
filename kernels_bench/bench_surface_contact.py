"""What body-body contact costs per step: two soft boxes (one mesh, two components) of about
``--tets`` tetrahedra in all.

Phase 1 (far apart): the boxes 1 m apart falling side by side under gravity, stepped with
``set_contact()`` and again without it: seconds, Newton and linear iterations per step (the ratio
against the baseline measured in the same run). Phase 2 (in contact): the upper box dropped onto
the lower one (fixed at its base), Newmark; per step the seconds spent in the broad phase
(``SurfaceContact.update_pairs``: boxes, BVH refit, queries, pair read-back, pattern growth and
block positions), in the contact forms' energy / gradient / Hessian / CCD kernels, the pairs, and
the whole step.

    .venv/bin/python kernels_bench/bench_surface_contact.py [--tets 20000] [--steps 6] [--json PATH]
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

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, ROOT)
import warp as wp  # noqa: E402

from warpfem.materials import make_material  # noqa: E402
from warpfem.mesh import TetMesh, box_tet_mesh  # noqa: E402
from warpfem.model import Model  # noqa: E402
from warpfem.simulator import Simulator  # noqa: E402


def two_boxes(tets, *, apart):
    n = max(2, int(round((tets / 2 / 6) ** (1.0 / 3.0))))
    size = 0.2
    a = box_tet_mesh(size=(size, size, size), cells=(n, n, n), origin=(0.0, 0.0, 0.0))
    off = (1.0 + size, 0.0, 0.0) if apart else (0.03, size + 0.004, 0.02)
    b = box_tet_mesh(size=(size, size, size), cells=(n, n, n), origin=off)
    V = np.concatenate([a.vertices, b.vertices])
    T = np.concatenate([a.tets, b.tets + len(a.vertices)])
    return TetMesh(V, T), len(a.vertices)


def make(tets, *, apart, contact, device, precision):
    mesh, na = two_boxes(tets, apart=apart)
    m = Model(mesh, make_material("stable_neo_hookean", youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
              gravity=(0.0, -9.81, 0.0))
    if not apart:
        X = np.asarray(mesh.vertices)
        m.fix(np.flatnonzero((np.arange(len(X)) < na) & (X[:, 1] < 1e-9)))
    sim = Simulator(m, device=device, precision=precision, dt=1.0 / 120.0, integrator="newmark", max_iters=60)
    if contact:
        sim.set_contact()
    if not apart:
        v = np.zeros((m.num_vertices, 3))
        v[na:, 1] = -0.5
        sim.set_velocities(v)
    return sim


class Timers:
    """Wall seconds in the broad phase and in the contact form's methods (CPU launches are
    synchronous; on CUDA each timed call ends with a synchronize)."""

    def __init__(self, sim):
        self.t = {"broad_phase": 0.0, "pattern_growth": 0.0, "energy": 0.0, "gradient": 0.0, "hessian": 0.0, "ccd": 0.0}
        sc, form = sim.surface_contact, sim.surface_contact_form
        self._wrap(sim.system, "ensure_blocks", "pattern_growth", sim.device)
        self._wrap(sc, "update_pairs", "broad_phase", sim.device)
        for name, key in (("energy", "energy"), ("gradient", "gradient"), ("hessian", "hessian")):
            self._wrap(form, name, key, sim.device)
        run = sc.run

        def timed_run(mode, *a, **kw):
            t0 = time.perf_counter()
            out = run(mode, *a, **kw)
            if mode == 3:
                wp.synchronize_device(sim.device)
                self.t["ccd"] += time.perf_counter() - t0
            return out

        sc.run = timed_run

    def _wrap(self, obj, name, key, device):
        f = getattr(obj, name)

        def timed(*a, **kw):
            t0 = time.perf_counter()
            out = f(*a, **kw)
            wp.synchronize_device(device)
            self.t[key] += time.perf_counter() - t0
            return out

        setattr(obj, name, timed)

    def take(self):
        t, self.t = self.t, {k: 0.0 for k in self.t}
        return t


def steps(sim, n, timers=None):
    rows = []
    for _ in range(n):
        t0 = time.perf_counter()
        st = sim.step()
        row = {"seconds": time.perf_counter() - t0, "newton": st.newton_iterations, "linear": st.linear_iterations,
               "converged": st.converged}
        if timers is not None:
            row.update(timers.take())
            row["pairs"] = sim.surface_contact.num_pairs
        rows.append(row)
    return rows


def mean(rows, key):
    return float(np.mean([r[key] for r in rows]))


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--precision", default="float64")
    ap.add_argument("--tets", type=int, default=20000)
    ap.add_argument("--steps", type=int, default=6)
    ap.add_argument("--json", default=None)
    ap.add_argument("--phase", choices=("both", "far", "contact"), default="both")
    a = ap.parse_args()
    out = {"device": a.device, "machine": platform.machine(), "load_average": os.getloadavg(), "tets": None}
    # phase 1: far apart, with and without contact (alternated twice against drift of the machine's load)
    far = {True: [], False: []}
    for contact in (False, True, False, True) if a.phase != "contact" else ():
        sim = make(a.tets, apart=True, contact=contact, device=a.device, precision=a.precision)
        out["tets"] = sim.model.mesh.num_elements
        sim.step()  # warm-up
        far[contact] += steps(sim, a.steps)
    for c in (False, True) if a.phase != "contact" else ():
        print(f"far apart, contact={c}: {mean(far[c], 'seconds'):.3f} s/step, newton {mean(far[c], 'newton'):.1f}, "
              f"linear {mean(far[c], 'linear'):.1f}", flush=True)
    if a.phase != "contact":
        out["far_ratio"] = mean(far[True], "seconds") / mean(far[False], "seconds")
        out["far"] = {str(c): far[c] for c in far}
        print(f"time ratio with / without contact, far apart: {out['far_ratio']:.3f}", flush=True)
    if a.phase == "far":
        out["load_average_end"] = os.getloadavg()
        if a.json:
            with open(a.json, "w") as f:
                json.dump(out, f, indent=1)
        return
    # phase 2: in contact
    sim = make(a.tets, apart=False, contact=True, device=a.device, precision=a.precision)
    out["tets"] = sim.model.mesh.num_elements
    timers = Timers(sim)
    rows = steps(sim, a.steps + 2, timers)
    for r in rows:
        r["broad_phase"] -= r["pattern_growth"]  # (growth happens inside update_pairs)
        share = {k: r[k] / r["seconds"] for k in ("broad_phase", "pattern_growth", "energy", "gradient", "hessian", "ccd")}
        print(f"step: {r['seconds']:.2f} s, newton {r['newton']}, linear {r['linear']}, pairs {r['pairs']}, "
              + ", ".join(f"{k} {100 * v:.1f} %" for k, v in share.items()), flush=True)
    out["contact_rows"] = rows
    out["load_average_end"] = os.getloadavg()
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
