"""Stiffness warping (corotational linear FEM, one linear solve per step) against Newton backward
Euler on the same beam, same material, same time step.

    python examples/stiffness_warping.py --device cpu --num-frames 30 --stage-path out/warping.usda --headless
    python examples/stiffness_warping.py --rotation qr

The beam of docs/stiffness_warping.md: 10 m x 1 m x 1 m, 20 x 2 x 2 cells (480 tets), E = 1e6 Pa,
nu = 0.3, rho = 1000 kg/m^3, clamped at x = 0, falling under gravity from rest; dt = 1/60 s, one
step per frame. ``wf.Simulator`` minimises the backward Euler incremental potential of the
corotated material with Newton; ``wf.StiffnessWarpingSimulator`` rotates each tet's rest stiffness
into its current frame and does one PCG solve per step. The script prints the wall time per step
of each and the trajectory difference (largest vertex distance between the two runs over all
frames, relative to the largest displacement), and writes both beams side by side (warping at
y + 1.5 m) to one USD stage.
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
from warpfem.skinning import mesh_boundary_surface  # noqa: E402

FPS = 60.0


class Example:
    """One step of both simulators per ``step()``; ``render()`` writes both beams."""

    def __init__(self, stage_path="out/warping.usda", *, cells=(20, 2, 2), rotation="polar", precision="float64",
                 device=None):
        self.mesh = wf.box_tet_mesh(size=(10.0, 1.0, 1.0), cells=cells)
        material = wf.Corotated(youngs_modulus=1e6, poisson_ratio=0.3, density=1000.0)
        clamp = wf.select_vertices_in_box(self.mesh, (-1, -1, -1), (1e-6, 2, 2))
        self.sims = {}
        for name in ("newton", "warping"):
            model = wf.Model(self.mesh, material, gravity=(0.0, 0.0, -9.81))
            model.fix(clamp)
            if name == "newton":
                self.sims[name] = wf.Simulator(model, device=device, precision=precision, dt=1.0 / FPS)
            else:
                self.sims[name] = wf.StiffnessWarpingSimulator(model, device=device, precision=precision, dt=1.0 / FPS,
                                                               rotation=rotation, cg_tol=1e-6)
        self.seconds = {name: [] for name in self.sims}
        self.cg = {name: 0 for name in self.sims}
        self.frame = 0
        self.max_difference = 0.0  # largest vertex distance newton vs warping so far (m)
        self.max_displacement = 0.0  # largest vertex displacement (Newton) so far (m)
        self.renderer = None
        if stage_path:
            self.surface_ids, faces = mesh_boundary_surface(self.mesh.vertices, self.mesh.tets)
            self.renderer = UsdMeshWriter(stage_path, fps=FPS, up_axis="Z")
            for name in self.sims:
                self.renderer.add_mesh(name, faces, len(self.surface_ids))

    def step(self):
        self.frame += 1
        for name, sim in self.sims.items():
            t0 = time.perf_counter()
            stats = sim.step()
            self.seconds[name].append(time.perf_counter() - t0)
            self.cg[name] += stats.cg_iterations
        x_newton, x_warping = self.sims["newton"].positions(), self.sims["warping"].positions()
        self.max_difference = max(self.max_difference, float(np.linalg.norm(x_warping - x_newton, axis=1).max()))
        self.max_displacement = max(self.max_displacement,
                                    float(np.linalg.norm(x_newton - self.mesh.vertices, axis=1).max()))

    def render(self):
        if self.renderer is not None:
            offset = {"newton": np.zeros(3), "warping": np.array([0.0, 1.5, 0.0])}
            self.renderer.write_frame(self.frame, {name: sim.positions()[self.surface_ids] + offset[name]
                                                   for name, sim in self.sims.items()})

    def close(self, complete=True, reason=None):
        if self.renderer is not None:
            self.renderer.close(complete=complete, reason=reason)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", type=str, default=None, help="Override the default Warp device.")
    parser.add_argument("--stage-path", type=lambda x: None if x == "None" else str(x), default="out/warping.usda",
                        help="Path to the output USD file (None: no output).")
    parser.add_argument("--num-frames", type=int, default=30, help="Total number of frames (one step each, 60 fps).")
    parser.add_argument("--rotation", choices=("polar", "qr"), default="polar",
                        help="How stiffness warping extracts each tet's rotation.")
    parser.add_argument("--cells", type=int, nargs=3, default=(20, 2, 2), metavar=("NX", "NY", "NZ"))
    parser.add_argument("--precision", choices=("float32", "float64"), default="float64")
    parser.add_argument("--headless", action="store_true", help="Run without an interactive viewer (USD output only).")
    args = parser.parse_known_args(argv)[0]

    init_warp(args.device or "cpu")  # quiet: no banner, no CUDA-driver note on a CPU (WARPFEM_VERBOSE=1 shows them)
    with wp.ScopedDevice(args.device):
        example = Example(stage_path=args.stage_path, cells=tuple(args.cells), rotation=args.rotation,
                          precision=args.precision, device=args.device)
        example.render()  # frame 0: rest state
        try:
            for _ in range(args.num_frames):
                example.step()
                example.render()
                print(f"frame {example.frame}/{args.num_frames}  newton {1e3 * example.seconds['newton'][-1]:6.1f} ms"
                      f"  warping {1e3 * example.seconds['warping'][-1]:6.1f} ms  difference "
                      f"{example.max_difference / max(example.max_displacement, 1e-300):.2e} of max displacement",
                      flush=True)
        except BaseException as e:
            example.close(complete=False, reason=f"{type(e).__name__}: {e}")
            raise
        example.close()

    # the first step of each includes Warp's first-use work (module loads): the median is the per-step cost
    ms = {name: 1e3 * float(np.median(s)) for name, s in example.seconds.items()}
    rel = example.max_difference / max(example.max_displacement, 1e-300)
    result = {"ms_per_step": ms, "cg_per_step": {k: v / args.num_frames for k, v in example.cg.items()},
              "speedup": ms["newton"] / ms["warping"], "max_difference": example.max_difference,
              "max_displacement": example.max_displacement, "relative_difference": rel,
              "rotation": args.rotation, "stage_path": args.stage_path}
    print(f"\n{args.num_frames} steps on {wp.get_device(args.device)}: Newton {ms['newton']:.1f} ms/step "
          f"({result['cg_per_step']['newton']:.0f} CG its), warping ({args.rotation}) {ms['warping']:.1f} ms/step "
          f"({result['cg_per_step']['warping']:.0f} CG its): {result['speedup']:.1f}x")
    print(f"trajectory difference: {example.max_difference:.3e} m = {rel:.2e} of the largest displacement "
          f"({example.max_displacement:.3f} m)")
    if args.stage_path:
        print(f"wrote {args.stage_path} ({args.num_frames + 1} frames: newton, and warping at y + 1.5 m)")
    return result


if __name__ == "__main__":
    main()
