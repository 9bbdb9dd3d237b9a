"""A small speed/accuracy trade-off study driven from Python, then a run of the configuration it picks.

    python examples/tradeoff.py --device cpu --num-frames 8 --stage-path out/tradeoff.usda --headless
    python examples/tradeoff.py --scene examples/scenes/cantilever_hex8.toml --with-reduced --error-budget 0.02

``warpfem.tradeoff.run_study`` runs the scene (default: the cantilever of ``make demo``) once per
``TradeoffConfig`` (each overrides a few scene settings: precision, Newton/CG tolerances, substeps,
integrator, subspace) and compares every run with a converged reference (float64, tolerances 1e-9,
4 substeps). It returns the wall time per simulated second, iterations and errors of each, and the
Pareto frontier of time vs tip error (no configuration both faster and more accurate). The script
prints that table and the frontier, picks the fastest frontier configuration whose tip error is
within ``--error-budget`` (of the peak tip displacement), builds it with
``warpfem.tradeoff.variant_scene`` and writes its animation to the USD stage. The whole CLI
version is ``warpfem tradeoff SCENE --grid quick|full|FILE.toml`` (docs/tradeoff.md).
"""

from __future__ import annotations

import argparse
import os
import sys

import warp as wp

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from warpfem.device import init_warp  # noqa: E402
from warpfem.tradeoff import (TradeoffConfig, TradeoffGrid, format_table, run_study, scene_document,  # noqa: E402
                              variant_scene)

SCENE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "scenes", "cantilever.toml")


def make_grid(with_reduced=False):
    """The configurations to compare (None = keep the scene's value) and the reference."""
    configs = [
        TradeoffConfig(name="scene settings"),
        TradeoffConfig(name="float32, tol 1e-3, cg_tol 1e-2", precision="float32", tol=1e-3, cg_tol=1e-2),
        TradeoffConfig(name="2 substeps", substeps=2),
        TradeoffConfig(name="stiffness warping", integrator="stiffness_warping"),
        TradeoffConfig(name="stiffness warping, 4 substeps", integrator="stiffness_warping", substeps=4),
    ]
    if with_reduced:  # trains a subspace first (reported separately, not in the time per simulated second)
        configs.append(TradeoffConfig(name="reduced r = 20", subspace=(("cubature_tolerance", 0.01), ("modes", 20))))
    reference = TradeoffConfig(name="reference", precision="float64", tol=1e-9, max_iters=100, cg_tol=1e-9,
                               max_cg_iters=20000, substeps=4)
    return TradeoffGrid(configs=configs, reference=reference, name="example")


class Example:
    """``study()`` runs the grid; then one frame of the chosen configuration per ``step()``."""

    def __init__(self, stage_path="out/tradeoff.usda", *, scene_path=SCENE, num_frames=8, device="cpu",
                 with_reduced=False):
        self.scene_path, self.stage_path, self.num_frames, self.device = scene_path, stage_path, num_frames, device
        self.grid = make_grid(with_reduced)
        self.result = None
        self.run = None
        self.renderer = None
        self.frame = 0

    def study(self):
        self.result = run_study(self.scene_path, self.grid, device=self.device, frames=self.num_frames, quantity="tip",
                                log=lambda line: print("  " + line, flush=True))
        return self.result

    def choose(self, error_budget):
        """The fastest frontier configuration within the budget (else the most accurate one)."""
        front = [r for r in self.result.ok_results() if r.on_frontier]  # sorted by time below
        front.sort(key=lambda r: r.seconds_per_sim_second)
        within = [r for r in front if r.tip_error <= error_budget]
        return within[0] if within else min(front, key=lambda r: r.tip_error)

    def start(self, chosen):
        from warpfem.io import UsdMeshWriter

        cfg = {c.name: c for c in self.grid.configs}[chosen.name]
        out_dir = os.path.dirname(os.path.abspath(self.stage_path or "out/tradeoff.usda"))
        scene = variant_scene(scene_document(self.scene_path), self.scene_path, cfg, cache_dir=out_dir)
        if scene.spec.subspace is not None:  # a reduced choice needs its training first
            from warpfem.reduced.scene import train_scene

            train_scene(scene, device=self.device)
        self.run = scene.build(device=self.device, precision=cfg.precision)
        if self.stage_path:
            self.renderer = UsdMeshWriter(self.stage_path, fps=self.run.fps)
            self.renderer.add_mesh(self.run.surface_name, self.run.surface_faces, self.run.num_surface_points)

    def step(self):
        stats = self.run.step_frame(total_frames=self.num_frames)
        self.frame = stats.frame
        return stats

    def render(self):
        if self.renderer is not None:
            self.renderer.write_frame(self.frame, {self.run.surface_name: self.run.surface_points()})

    def close(self, complete=True, reason=None):
        if self.renderer is not None:
            self.renderer.close(complete=complete, reason=reason)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", type=str, default=None, help="Override the default Warp device.")
    parser.add_argument("--stage-path", type=lambda x: None if x == "None" else str(x), default="out/tradeoff.usda",
                        help="USD file for the chosen configuration's run (None: study only).")
    parser.add_argument("--num-frames", type=int, default=8, help="Frames of every run of the study (and the final run).")
    parser.add_argument("--scene", default=SCENE, help="Scene file (default: examples/scenes/cantilever.toml).")
    parser.add_argument("--error-budget", type=float, default=0.05,
                        help="Largest acceptable tip error / peak tip displacement for the final run.")
    parser.add_argument("--with-reduced", action="store_true", help="Add a reduced (r = 20) configuration (trains first).")
    parser.add_argument("--headless", action="store_true", help="Run without an interactive viewer (USD output only).")
    args = parser.parse_known_args(argv)[0]

    init_warp(args.device or "cpu")  # quiet: no banner, no CUDA-driver note on a CPU (WARPFEM_VERBOSE=1 shows them)
    device = str(wp.get_device(args.device))
    with wp.ScopedDevice(device):
        example = Example(stage_path=args.stage_path, scene_path=args.scene, num_frames=args.num_frames, device=device,
                          with_reduced=args.with_reduced)
        print(f"study: {len(example.grid.configs)} configurations + reference, {args.num_frames} frames each", flush=True)
        study = example.study()
        print()
        print(format_table(study))
        front = sorted((r for r in study.ok_results() if r.on_frontier), key=lambda r: r.seconds_per_sim_second)
        print("\nPareto frontier (faster first; each is more accurate than every faster one):")
        for r in front:
            print(f"  {r.name:34s} {r.seconds_per_sim_second:8.3g} s per simulated s   tip error {r.tip_error:.2e}")
        chosen = example.choose(args.error_budget)
        print(f"chosen (fastest within tip error {args.error_budget:g}): {chosen.name}", flush=True)

        if args.stage_path:
            example.start(chosen)
            example.render()  # frame 0: rest state
            try:
                for _ in range(args.num_frames):
                    example.step()
                    example.render()
            except BaseException as e:
                example.close(complete=False, reason=f"{type(e).__name__}: {e}")
                raise
            example.close()
            print(f"wrote {args.stage_path} ({args.num_frames + 1} frames of '{chosen.name}')")

    return {"study": study, "frontier": [r.name for r in front], "chosen": chosen.name,
            "results": {r.name: r for r in study.ok_results()}, "reference": study.reference,
            "stage_path": args.stage_path, "surface_points": example.run.num_surface_points if example.run else None}


if __name__ == "__main__":
    main()
