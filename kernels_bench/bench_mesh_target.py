"""Meshing a surface to ``target_tets``: the count reached, the seconds and where they go.

For each surface and target: ``tetrahedralize(V, F, target_tets=N)`` in this process (no cache),
its stage lines (``warpfem.progress.Stages``, time-stamped) kept to show where the time goes, the
tet count and its deviation from the target, the mesher that made it and how many meshes it took.

Surfaces: the scanned-surface stand-in of ``scan_surface.py`` (the bunny split twice, 111,456
triangles, noise 0.01 and 0.05 of the mean edge along the normals; at 0.05 it crosses itself), the
shipped bunny and knight, and surfaces the meshing code was not tuned on: the knight split twice
(16,000 triangles) and three times (64,000) with 0.03 / 0.05 noise. ``--fallback`` also runs the scan
stand-in with every decimation refused, which forces the TetWild path (TetWild on the decimated
surface, TetGen re-meshing its boundary).

    .venv/bin/python kernels_bench/bench_mesh_target.py [--targets 5000 20000] [--fallback] [--out PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import time
from pathlib import Path

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from kernels_bench.scan_surface import make_scan, midpoint_subdivide, vertex_normals  # noqa: E402


def knight(subdivisions, noise, seed=1):
    from warpfem.mesh.tetrahedralization import read_surface

    V, F = read_surface(ROOT / "examples" / "meshes" / "decimated-knight.off")
    for _ in range(subdivisions):
        V, F = midpoint_subdivide(V, F)
    h = float(np.mean(np.linalg.norm(V[F[:, 1]] - V[F[:, 0]], axis=1)))
    rng = np.random.default_rng(seed)
    return V + vertex_normals(V, F) * (noise * h * rng.standard_normal(len(V)))[:, None], F


def surfaces():
    from warpfem.mesh.tetrahedralization import read_surface

    yield "scan stand-in, noise 0.01", *make_scan(2, 0.01)[:2]
    yield "scan stand-in, noise 0.05", *make_scan(2, 0.05)[:2]
    yield "bunny.off", *read_surface(ROOT / "examples" / "meshes" / "bunny.off")
    yield "knight split twice, noise 0.03", *knight(2, 0.03)
    yield "knight split 3 times, noise 0.05", *knight(3, 0.05)


def mesh_once(V, F, target, name, refuse_decimation=False):
    import warnings

    import warpfem.mesh.tetrahedralization as T
    from warpfem.progress import set_stage_writer

    lines = []
    t0 = time.perf_counter()
    previous = set_stage_writer(lambda line: lines.append((round(time.perf_counter() - t0, 2), line)))
    saved = T._simplified
    if refuse_decimation:  # no decimation of the input is clean (TetWild's boundary may still be decimated)
        T._simplified = lambda V_, F_, *a, **k: None if len(F_) == len(F) else saved(V_, F_, *a, **k)
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            mesh = T.tetrahedralize(V, F, target_tets=target, name=name)
    finally:
        set_stage_writer(previous)
        T._simplified = saved
    secs = time.perf_counter() - t0
    info = mesh.tetrahedralization
    return dict(target_tets=target, tets=mesh.num_elements, off=mesh.num_elements / target - 1.0, seconds=secs,
                mesher=info.mesher, meshes=info.extra.get("meshes"), coarsened="edge_length" in info.extra,
                remeshed_from=info.extra.get("remeshed_from"), dirty=bool(info.extra.get("dirty")),
                volume_change=info.extra.get("volume_change"), warnings=[str(w.message)[:160] for w in caught],
                stages=lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--targets", type=int, nargs="+", default=[5000, 20000])
    ap.add_argument("--fallback", action="store_true")
    ap.add_argument("--out", default=str(ROOT / "kernels_bench" / "results" / "mesh_target"))
    args = ap.parse_args()
    load0 = os.getloadavg()
    rows = []
    for label, V, F in surfaces():
        for target in args.targets:
            r = dict(surface=label, surface_triangles=int(len(F)), **mesh_once(V, F, target, "surface.obj"))
            print({k: v for k, v in r.items() if k != "stages"}, flush=True)
            rows.append(r)
    if args.fallback:
        V, F = make_scan(2, 0.05)[:2]
        for target in args.targets:
            r = dict(surface="scan stand-in, noise 0.05, every decimation refused", surface_triangles=int(len(F)),
                     **mesh_once(V, F, target, "surface.obj", refuse_decimation=True))
            print({k: v for k, v in r.items() if k != "stages"}, flush=True)
            rows.append(r)
    meta = dict(cpu=platform.processor() or platform.machine(), cores=os.cpu_count(), python=platform.python_version(),
                load_average_start=load0, load_average_end=os.getloadavg())
    with open(args.out + ".json", "w") as f:
        json.dump(dict(meta=meta, rows=rows), f, indent=1)
    lines = ["| surface | triangles | target_tets | tets | off | mesher | meshes | s |",
             "| --- | ---: | ---: | ---: | ---: | --- | ---: | ---: |"]
    for r in rows:
        how = r["mesher"] + (" (TetWild's boundary)" if r["remeshed_from"] else "") + (", dirty input" if r["dirty"] else "")
        lines.append(f"| {r['surface']} | {r['surface_triangles']} | {r['target_tets']} | {r['tets']} | "
                     f"{100 * r['off']:+.1f} % | {how} | {r['meshes'] or 1} | {r['seconds']:.1f} |")
    from kernels_bench.report import write_markdown

    write_markdown(args.out + ".md", lines, meta)


if __name__ == "__main__":
    main()
