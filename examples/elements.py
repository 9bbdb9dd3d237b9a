"""The four element types (Tet4, Tet10, Hex8, Hex27) on one cantilever, against beam theory.

    python examples/elements.py --device cpu --num-frames 4 --stage-path out/elements.usda --headless
    python examples/elements.py --cells 10 1 1          # coarser: Tet10/Hex27 still within 0.2 %

The benchmark cantilever of docs/elements.md: 10 m x 1 m x 1 m, clamped at x = 0, linear elastic
(E = 1e4 Pa, nu = 0), loaded by its own weight (rho g = 1 N/m^3 along -z), so the Timoshenko beam
deflection of the tip is 1.512 m. Each frame is one quasi-static load step (gravity ramped to its
full value on the last frame); each beam is solved with the same Newton/PCG simulator, only the
mesh differs. The four beams go side by side (1.5 m apart in y) into one USD stage, each as its
boundary surface (curved element faces triangulated through their mid-nodes).

Linear tets lock in bending: on the same cells Tet4 and Hex8 are far too stiff, Tet10 and Hex27
hit the reference.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np
import warp as wp

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

import warpfem as wf  # noqa: E402
from warpfem.device import init_warp  # noqa: E402
from warpfem.io import UsdMeshWriter  # noqa: E402

LENGTH = 10.0  # m; cross-section 1 m x 1 m
TIMOSHENKO_TIP = 1.512  # m: tip deflection of this beam under its own weight (Timoshenko beam theory)
ELEMENTS = ("tet4", "tet10", "hex8", "hex27")


def beam_mesh(element, cells):
    """The beam in ``element`` (every type is the same ``VolumeMesh`` class)."""
    size = (LENGTH, 1.0, 1.0)
    if element in ("tet4", "tet10"):
        tets = wf.box_tet_mesh(size=size, cells=cells)
        if element == "tet10":
            return wf.tet10_from_tet4(tets)
        return tets
    return wf.box_hex_mesh(size=size, cells=cells, order=1 if element == "hex8" else 2)


class Example:
    """One quasi-static load step of every beam per ``step()``; ``render()`` writes the four surfaces."""

    def __init__(self, stage_path="out/elements.usda", *, cells=(20, 2, 2), num_frames=4, precision="float64",
                 device=None, elements=ELEMENTS):
        self.num_frames = num_frames
        self.frame = 0
        self.beams = {}
        for i, element in enumerate(elements):
            mesh = beam_mesh(element, cells)
            model = wf.Model(mesh, wf.LinearElastic(youngs_modulus=1e4, poisson_ratio=0.0, density=1.0),
                             gravity=(0.0, 0.0, 0.0))
            model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (0, 2, 2)))  # clamp the x = 0 face
            sim = wf.Simulator(model, device=device, precision=precision, tol=1e-8, cg_tol=1e-10, max_cg_iters=20000)
            faces = mesh.boundary_faces()
            tip = np.flatnonzero(np.abs(mesh.vertices[:, 0] - LENGTH) < 1e-9)
            self.beams[element] = dict(mesh=mesh, model=model, sim=sim, faces=faces, tip=tip,
                                       offset=np.array([0.0, 1.5 * i, 0.0]), seconds=0.0, newton=0, cg=0)
        self.renderer = None
        if stage_path:
            self.renderer = UsdMeshWriter(stage_path, fps=24.0, up_axis="Z")
            for element, b in self.beams.items():
                self.renderer.add_mesh(element, b["faces"], b["mesh"].num_vertices)

    def step(self):
        self.frame += 1
        load = self.frame / self.num_frames
        for b in self.beams.values():
            b["model"].gravity = np.array([0.0, 0.0, -1.0 * load])
            b["sim"].sync_model()  # upload the new external forces
            t0 = time.perf_counter()
            stats = b["sim"].solve_static()
            b["seconds"] += time.perf_counter() - t0
            b["newton"] += stats.newton_iterations
            b["cg"] += stats.cg_iterations

    def tip_deflection(self, element):
        b = self.beams[element]
        u = b["sim"].positions() - b["mesh"].vertices
        return float(-u[b["tip"], 2].mean())

    def render(self):
        if self.renderer is not None:
            self.renderer.write_frame(self.frame, {e: b["sim"].positions() + b["offset"] for e, b in self.beams.items()})

    def close(self, complete=True, reason=None):
        if self.renderer is not None:
            self.renderer.close(complete=complete, reason=reason)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", type=str, default=None, help="Override the default Warp device.")
    parser.add_argument("--stage-path", type=lambda x: None if x == "None" else str(x), default="out/elements.usda",
                        help="Path to the output USD file (None: no output).")
    parser.add_argument("--num-frames", type=int, default=4, help="Load steps (gravity reaches full value on the last).")
    parser.add_argument("--cells", type=int, nargs=3, default=(20, 2, 2), metavar=("NX", "NY", "NZ"),
                        help="Cells along the beam and across it (same for every element type).")
    parser.add_argument("--precision", choices=("float32", "float64"), default="float64")
    parser.add_argument("--headless", action="store_true", help="Run without an interactive viewer (USD output only).")
    args = parser.parse_known_args(argv)[0]

    init_warp(args.device or "cpu")  # quiet: no banner, no CUDA-driver note on a CPU (WARPFEM_VERBOSE=1 shows them)
    with wp.ScopedDevice(args.device):
        example = Example(stage_path=args.stage_path, cells=tuple(args.cells), num_frames=args.num_frames,
                          precision=args.precision, device=args.device)
        example.render()  # frame 0: unloaded
        try:
            for _ in range(args.num_frames):
                example.step()
                example.render()
                tips = "  ".join(f"{e} {example.tip_deflection(e):.4f}" for e in example.beams)
                print(f"load step {example.frame}/{args.num_frames}  tip deflection (m): {tips}", flush=True)
        except BaseException as e:
            example.close(complete=False, reason=f"{type(e).__name__}: {e}")
            raise
        example.close()

    result = {"cells": tuple(args.cells), "reference": TIMOSHENKO_TIP, "stage_path": args.stage_path}
    cells = "x".join(map(str, args.cells))
    print(f"\ncantilever {cells} cells, tip deflection vs Timoshenko {TIMOSHENKO_TIP} m:")
    print(f"{'element':8s} {'DOFs':>6s} {'tip (m)':>8s} {'error':>8s} {'newton':>6s} {'cg':>6s} {'solve s':>8s}")
    for element, b in example.beams.items():
        tip = example.tip_deflection(element)
        dofs = int((~b["model"].fixed).sum())  # free displacement components
        err = tip / TIMOSHENKO_TIP - 1.0
        result[element] = {"tip": tip, "error": err, "dofs": dofs, "newton": b["newton"], "cg": b["cg"],
                           "seconds": b["seconds"]}
        print(f"{element:8s} {dofs:6d} {tip:8.5f} {100 * err:+7.2f}% {b['newton']:6d} {b['cg']:6d} {b['seconds']:8.2f}")
    if args.stage_path:
        print(f"wrote {args.stage_path} ({args.num_frames + 1} frames, one mesh per element type)")
    return result


if __name__ == "__main__":
    main()
