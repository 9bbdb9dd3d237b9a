"""Reduced (subspace + cubature) simulation: train once, then step in r coordinates, checked
against a full Newton run of the same beam.

    python examples/reduced.py --device cpu --num-frames 24 --stage-path out/reduced.usda --headless
    python examples/reduced.py --modes 40 --training mixed --cache out/beam.subspace.npz

The beam of the default scene (examples/scenes/cantilever.toml): 1 m x 0.2 m x 0.2 m, 20 x 2 x 2
cells (480 tets), stable neo-Hookean E = 1e6 Pa, nu = 0.3, rho = 1000 kg/m^3, clamped at x = 0,
falling under gravity from rest, dt = 1/48 s (one step per frame), Newton tol 1e-5, CG tol 1e-3.

0. Training poses: a full run of ``--training-frames`` frames under a *different* load (gravity
   x 1.3), so the trajectory compared below is not in the training set (``--training random``
   skips it and samples random poses only: cheaper to train, several times less accurate).
1. ``warpfem.reduced.train_subspace`` builds x = X + U q: r linear modes plus modal derivatives
   (mass-PCA'd back to r columns) with the linear static response to gravity as one column, and
   trains a cubature (a few weighted tets, greedy non-negative least squares over the training
   poses) that reproduces the reduced internal forces to ``--cubature-tolerance``. ``--cache FILE``
   stores it (reloaded next time when the mesh, material and settings match).
2. ``warpfem.reduced.ReducedSimulator`` runs backward Euler in the subspace (an r x r Newton
   system per iteration, forces from the cubature tets only).
3. A full ``wf.Simulator`` run of the same frames is the reference: the script prints time per
   step of both, the speed-up, and the errors (tip: largest distance between the two runs' tip
   centres over the run / the full run's peak tip displacement; RMS: largest RMS vertex distance
   / the beam's bounding-box diagonal). Both beams go to one USD stage (reduced at y + 0.4 m).
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
from warpfem.reduced import ReducedSimulator, format_report, train_subspace  # noqa: E402
from warpfem.skinning import mesh_boundary_surface  # noqa: E402

FPS = 48.0
SOLVER = dict(tol=1e-5, cg_tol=1e-3)  # the scene's Newton settings (cg_tol is unused by the reduced solve)
POSE_SOURCES = {"snapshots": "snapshots", "mixed": "random+snapshots", "random": "random"}


def beam_model(gravity_scale=1.0):
    mesh = wf.box_tet_mesh(size=(1.0, 0.2, 0.2), cells=(20, 2, 2))
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=1e6, poisson_ratio=0.3, density=1000.0),
                     gravity=(0.0, 0.0, -9.81 * gravity_scale))
    model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (1e-6, 1, 1)))  # clamp the x = 0 face
    return mesh, model


class Example:
    """Training in ``__init__``; one step of the full and the reduced simulator per ``step()``."""

    def __init__(self, stage_path="out/reduced.usda", *, modes=20, cubature_tolerance=0.01, training="snapshots",
                 training_frames=24, cache=None, precision="float64", device=None):
        self.mesh, self.model = beam_model()
        self.tip = np.flatnonzero(self.mesh.vertices[:, 0] > 1.0 - 1e-6)

        t0 = time.perf_counter()
        snapshots = None
        if training != "random":  # full run under gravity x 1.3: its frames are the training poses
            _, heavier = beam_model(gravity_scale=1.3)
            sim = wf.Simulator(heavier, device=device, precision="float64", dt=1.0 / FPS, **SOLVER)
            snapshots = []
            for _ in range(training_frames):
                sim.step()
                snapshots.append(sim.positions())
        self.snapshot_seconds = time.perf_counter() - t0
        t0 = time.perf_counter()
        self.subspace = train_subspace(self.model, modes=modes, modal_derivatives=True, load_response=True,
                                       cubature_tolerance=cubature_tolerance, max_cubature_points=300, seed=0,
                                       snapshots=snapshots, pose_source=POSE_SOURCES[training], cache=cache)
        self.train_seconds = time.perf_counter() - t0

        self.sims = {"full": wf.Simulator(self.model, device=device, precision=precision, dt=1.0 / FPS, **SOLVER),
                     "reduced": ReducedSimulator(self.model, self.subspace, device=device, precision=precision,
                                                 dt=1.0 / FPS, tol=SOLVER["tol"])}
        self.seconds = {name: [] for name in self.sims}
        self.frame = 0
        self.tip_error = 0.0  # max over frames of |tip_reduced - tip_full| (m)
        self.tip_peak = 0.0  # max over frames of |tip_full - tip_rest| (m)
        self.rms_error = 0.0  # max over frames of the RMS vertex distance (m)
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
            sim.step()
            self.seconds[name].append(time.perf_counter() - t0)
        x_full, x_red = self.sims["full"].positions(), self.sims["reduced"].positions()
        tip_rest = self.mesh.vertices[self.tip].mean(axis=0)
        self.tip_error = max(self.tip_error, float(np.linalg.norm(x_red[self.tip].mean(0) - x_full[self.tip].mean(0))))
        self.tip_peak = max(self.tip_peak, float(np.linalg.norm(x_full[self.tip].mean(0) - tip_rest)))
        self.rms_error = max(self.rms_error, float(np.sqrt(np.mean(np.sum((x_red - x_full) ** 2, axis=1)))))

    def render(self):
        if self.renderer is not None:
            offset = {"full": np.zeros(3), "reduced": np.array([0.0, 0.4, 0.0])}
            self.renderer.write_frame(self.frame, {name: sim.positions()[self.surface_ids] + offset[name]
                                                   for name, sim in self.sims.items()})

    def close(self, complete=True, reason=None):
        if self.renderer is not None:
            self.renderer.close(complete=complete, reason=reason)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", type=str, default=None, help="Override the default Warp device.")
    parser.add_argument("--stage-path", type=lambda x: None if x == "None" else str(x), default="out/reduced.usda",
                        help="Path to the output USD file (None: no output).")
    parser.add_argument("--num-frames", type=int, default=24, help="Total number of frames (one step each, 48 fps).")
    parser.add_argument("--modes", type=int, default=20, help="Subspace dimension r.")
    parser.add_argument("--cubature-tolerance", type=float, default=0.01, help="Target relative cubature force error.")
    parser.add_argument("--training", choices=tuple(POSE_SOURCES), default="snapshots",
                        help="Cubature training poses: frames of a full run under gravity x 1.3 ('snapshots'), those "
                             "plus random poses ('mixed', the scenes' default), or random poses only ('random').")
    parser.add_argument("--training-frames", type=int, default=24, help="Frames of the full training run.")
    parser.add_argument("--cache", default=None, help="npz file for the trained subspace (reused when it matches).")
    parser.add_argument("--precision", choices=("float32", "float64"), default="float64")
    parser.add_argument("--headless", action="store_true", help="Run without an interactive viewer (USD output only).")
    args = parser.parse_known_args(argv)[0]

    init_warp(args.device or "cpu")  # quiet: no banner, no CUDA-driver note on a CPU (WARPFEM_VERBOSE=1 shows them)
    with wp.ScopedDevice(args.device):
        example = Example(stage_path=args.stage_path, modes=args.modes, cubature_tolerance=args.cubature_tolerance,
                          training=args.training, training_frames=args.training_frames, cache=args.cache, precision=args.precision, device=args.device)
        print(format_report(example.subspace.report))
        print(f"training run {example.snapshot_seconds:.1f} s, basis + cubature {example.train_seconds:.1f} s", flush=True)
        example.render()  # frame 0: rest state
        try:
            for _ in range(args.num_frames):
                example.step()
                example.render()
                print(f"frame {example.frame}/{args.num_frames}  full {1e3 * example.seconds['full'][-1]:7.1f} ms  "
                      f"reduced {1e3 * example.seconds['reduced'][-1]:6.1f} ms  tip error {example.tip_error:.2e} m",
                      flush=True)
        except BaseException as e:
            example.close(complete=False, reason=f"{type(e).__name__}: {e}")
            raise
        example.close()

    # medians: the first step of each includes Warp's first-use work
    ms = {name: 1e3 * float(np.median(s)) for name, s in example.seconds.items()}
    size = float(np.linalg.norm(np.ptp(example.mesh.vertices, axis=0)))
    result = {"modes": example.subspace.U.shape[1], "cubature_points": len(example.subspace.cubature.elements),
              "train_seconds": example.train_seconds,
              "training_run_seconds": example.snapshot_seconds, "ms_per_step": ms, "speedup": ms["full"] / ms["reduced"],
              "tip_error": example.tip_error / max(example.tip_peak, 1e-300), "tip_peak": example.tip_peak,
              "rms_error": example.rms_error / size, "stage_path": args.stage_path}
    print(f"\nr = {result['modes']}, {result['cubature_points']} cubature tets, trained in {example.train_seconds:.1f} s; "
          f"{args.num_frames} steps on {wp.get_device(args.device)}: full {ms['full']:.1f} ms/step, reduced "
          f"{ms['reduced']:.2f} ms/step, speed-up {result['speedup']:.0f}x")
    print(f"error vs full: tip {100 * result['tip_error']:.2f} % of the peak tip displacement "
          f"({example.tip_peak:.3f} m), RMS {100 * result['rms_error']:.3f} % of the beam's size")
    if args.stage_path:
        print(f"wrote {args.stage_path} ({args.num_frames + 1} frames: full, and reduced at y + 0.4 m)")
    return result


if __name__ == "__main__":
    main()
