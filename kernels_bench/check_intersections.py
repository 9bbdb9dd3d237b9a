"""Check every frame of a run for intersections with IPC Toolkit (``ipctk``, the test extra), an
independent judge of warpfem's contact: the scene is built again for its surface (the boundary
triangles of every body) and each frame of its ``[output] states`` file is tested with
``ipctk.has_intersections``. Also prints the smallest distance between surface primitives of
different bodies (or of one body with itself) over the run.

    python kernels_bench/check_intersections.py SCENE.toml [--states out/X.npz]

Exit code 1 when a frame intersects.
"""

from __future__ import annotations

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402


def main(argv=None):
    import ipctk

    from warpfem.scenes import load_scene

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene")
    p.add_argument("--states", default=None, help="default: the scene's [output] states (relative to the current folder)")
    a = p.parse_args(argv)
    scene = load_scene(a.scene)
    path = a.states or scene.spec.output["states"]
    run = scene.build()
    faces = np.asarray(run.model.mesh.boundary_faces(), dtype=np.int64)
    edges = np.unique(np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1), axis=0)
    rest = getattr(run.model, "vertex_rest_positions", run.model.rest_positions)  # every body's vertices
    cm = ipctk.CollisionMesh(np.asarray(rest, dtype=np.float64), edges, faces)
    frames = np.load(path)["positions"]
    bad = [k for k, x in enumerate(frames) if ipctk.has_intersections(cm, np.asarray(x, dtype=np.float64))]
    c = run.sim.surface_contact
    dmin = None
    if c is not None and getattr(run.model, "rigid", None) is None:  # (the states hold vertices, not the unknown)
        dmin = float("inf")
        for x in frames:
            run.sim.set_positions(x)
            dmin = min(dmin, c.min_distance())  # over the candidate pairs near dhat (inf: none)
    print(f"{os.path.basename(a.scene)}: {len(frames)} frames, {len(bad)} with intersections" + (f" (first {bad[0]})" if bad else "")
          + ("" if dmin is None else f"; smallest contact distance {dmin:.3g} m (dhat {c.dhat:.3g} m)"))
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
