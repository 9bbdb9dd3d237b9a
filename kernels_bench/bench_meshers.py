"""Which tetrahedraliser for ``[mesh] path = "surface.off"``: time, size, quality, robustness.

Runs each candidate mesher on the shipped surfaces and on constructed bad surfaces, each in its
own subprocess (a crash or a hang is a result, not the end of the run), single-threaded so that
the machine load hits every candidate alike:

* ``tetgen``       TetGen 1.6 through the ``tetgen`` wheel (pyvista's wrapper), ``quality=True``
                   (radius-edge <= 2, TetGen's default ``-pq``); and the same with a minimum
                   dihedral angle of 10 degrees (``-pq2/10``).
* ``wildmeshing``  TetWild (Hu et al., "Tetrahedral Meshing in the Wild") through the
                   ``wildmeshing`` wheel, default options (ideal edge = bbox diagonal / 20).
* ``pytetwild``    fTetWild (Hu et al., "Fast Tetrahedral Meshing in the Wild") through the
                   ``pytetwild`` wheel, default options (ideal edge = bbox diagonal / 20).
                   Its 0.4 wheels import pyvista unconditionally; a stub module stands in here.

Inputs: ``bunny.off``, ``decimated-knight.off`` (closed, manifold), two unit cubes sharing an
edge (non-manifold edge), a cube with one face duplicated, two interpenetrating cubes
(self-intersecting), a cube with one face missing (open).

For each: wall seconds, vertices, tets, minimum dihedral angle (degrees), minimum mean-ratio
quality (1 for a regular tet, 0 degenerate), tets with volume <= 0, and the relative difference
between the tet volume and the volume enclosed by the input surface (divergence theorem; for the
bad inputs that figure means little).

    .venv/bin/python kernels_bench/bench_meshers.py [--only NAME ...] [--timeout 300]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
MESHES = os.path.join(ROOT, "examples", "meshes")

CUBE_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                   [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype=np.float64)
CUBE_F = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                   [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]], dtype=np.int64)


def surfaces():
    import meshio

    out = {}
    for name in ("bunny.off", "decimated-knight.off"):
        m = meshio.read(os.path.join(MESHES, name))
        out[name] = (np.asarray(m.points, float), np.concatenate([c.data for c in m.cells if c.type == "triangle"]))
    # two cubes sharing the edge x = 1, y = 1 (second cube shifted by (1, 1, 0)); vertices merged
    V2 = np.vstack([CUBE_V, CUBE_V + [1.0, 1.0, 0.0]])
    F2 = np.vstack([CUBE_F, CUBE_F + 8])
    V2u, inv = np.unique(V2, axis=0, return_inverse=True)
    out["two cubes sharing an edge"] = (V2u, inv.ravel()[F2])
    out["cube with a duplicated face"] = (CUBE_V, np.vstack([CUBE_F, CUBE_F[:1]]))
    out["interpenetrating cubes"] = (np.vstack([CUBE_V, CUBE_V + 0.5]), np.vstack([CUBE_F, CUBE_F + 8]))
    out["open cube (one face missing)"] = (CUBE_V, CUBE_F[2:])
    return out


def enclosed_volume(V, F):
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def quality(V, T):
    """(min dihedral angle deg, min mean ratio, count of volume <= 0, total volume)."""
    x = V[T]
    d1, d2, d3 = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]
    vol = np.einsum("ij,ij->i", d1, np.cross(d2, d3)) / 6.0
    if (vol < 0).all():  # a mesher with the opposite orientation convention: swap two vertices
        x = x[:, [0, 2, 1, 3]]
        vol = -vol
    edges = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    l2 = sum(((x[:, j] - x[:, i]) ** 2).sum(1) for i, j in edges)
    mean_ratio = 12.0 * np.cbrt(3.0 * np.abs(vol)) ** 2 / l2 * np.sign(vol)
    faces = [(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)]
    n = [np.cross(x[:, b] - x[:, a], x[:, c] - x[:, a]) for a, b, c in faces]
    n = [v / np.maximum(np.linalg.norm(v, axis=1, keepdims=True), 1e-300) for v in n]
    dihedral = []
    for i in range(4):
        for j in range(i + 1, 4):
            dihedral.append(np.degrees(np.pi - np.arccos(np.clip((n[i] * n[j]).sum(1), -1, 1))))
    return float(np.min(dihedral)), float(mean_ratio.min()), int((vol <= 0).sum()), float(vol.sum())


def run_one(mesher, V, F):
    F32 = np.ascontiguousarray(F, dtype=np.int32)
    V = np.ascontiguousarray(V, dtype=np.float64)
    if mesher.startswith("tetgen"):
        import tetgen

        kw = {"quality": True, "minratio": 2.0}
        if mesher == "tetgen-dihedral10":
            kw["mindihedral"] = 10.0
        tg = tetgen.TetGen(V, F32)
        nodes, elems = tg.tetrahedralize(**kw)[:2]
        return np.asarray(nodes), np.asarray(elems)
    if mesher == "wildmeshing":
        import wildmeshing as wm

        t = wm.Tetrahedralizer(max_threads=1)
        t.set_log_level(6)
        t.set_mesh(V, F32)
        t.tetrahedralize()
        nodes, elems = t.get_tet_mesh()[:2]
        return np.asarray(nodes), np.asarray(elems)
    if mesher == "pytetwild":
        import types

        sys.modules.setdefault("pyvista", types.ModuleType("pyvista"))  # 0.4 imports it unconditionally
        from pytetwild import pytetwild as ptw

        nodes, elems = ptw.tetrahedralize(V, F32, num_threads=1, quiet=True)
        return np.asarray(nodes), np.asarray(elems)
    raise ValueError(mesher)


def child(mesher, case):
    V, F = surfaces()[case]
    t0 = time.perf_counter()
    nodes, elems = run_one(mesher, V, F)
    dt = time.perf_counter() - t0
    if len(elems) == 0:
        print(json.dumps({"status": "no tets", "seconds": dt}))
        return
    dmin, qmin, nneg, vol = quality(nodes, elems)
    ref = enclosed_volume(V, F)
    print(json.dumps({"status": "ok", "seconds": dt, "vertices": len(nodes), "tets": len(elems),
                      "min_dihedral": dmin, "min_mean_ratio": qmin, "nonpositive": nneg,
                      "volume_error": (vol - ref) / abs(ref) if ref else float("nan")}))


MESHERS = ("tetgen", "tetgen-dihedral10", "wildmeshing", "pytetwild")


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--child", nargs=2)
    ap.add_argument("--only", nargs="*", default=None)
    ap.add_argument("--cases", nargs="*", default=None)
    ap.add_argument("--timeout", type=float, default=300.0)
    args = ap.parse_args()
    if args.child:
        child(*args.child)
        return
    env = dict(os.environ, OMP_NUM_THREADS="1", TBB_NUM_THREADS="1")
    cases = args.cases or list(surfaces())
    rows = []
    for case in cases:
        for mesher in args.only or MESHERS:
            try:
                p = subprocess.run([sys.executable, __file__, "--child", mesher, case], capture_output=True,
                                   text=True, timeout=args.timeout, env=env)
                last = [ln for ln in p.stdout.splitlines() if ln.startswith("{")]
                if p.returncode == 0 and last:
                    r = json.loads(last[-1])
                else:
                    err = (p.stderr.strip().splitlines() or [f"exit code {p.returncode}"])[-1]
                    r = {"status": f"failed (rc {p.returncode}): {err[:120]}"}
            except subprocess.TimeoutExpired:
                r = {"status": f"timeout > {args.timeout:g} s"}
            r.update(mesher=mesher, case=case)
            rows.append(r)
            print(json.dumps(r), flush=True)
    print()
    print("| input | mesher | result | s | vertices | tets | min dihedral (deg) | min mean ratio | vol <= 0 | volume error |")
    print("| --- | --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for r in rows:
        if r["status"] == "ok":
            print(f"| {r['case']} | {r['mesher']} | ok | {r['seconds']:.2f} | {r['vertices']} | {r['tets']} | "
                  f"{r['min_dihedral']:.2f} | {r['min_mean_ratio']:.3f} | {r['nonpositive']} | {r['volume_error']:+.2e} |")
        else:
            print(f"| {r['case']} | {r['mesher']} | {r['status']} | | | | | | | |")


if __name__ == "__main__":
    main()
