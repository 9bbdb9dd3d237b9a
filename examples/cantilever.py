"""Cantilever beam sagging under gravity (the default scene), Warp-example style.

    python examples/cantilever.py --device cpu --num-frames 48 --stage-path out/cantilever.usda --headless
    python examples/cantilever.py --scene examples/scenes/cantilever_hex8.toml --stage-path out/beam_hex8.usda

Loads examples/scenes/cantilever.toml (Tet4; ``--scene`` picks another, e.g. the Hex8 beam)
through ``warpfem.scenes``, steps it frame by frame and writes the beam's boundary surface to an
animated USD (open it in usdview or Omniverse; the frames live in value clips next to it, in
``<stage>.clips/``).
"""

from __future__ import annotations

import argparse
import os
import sys

import warp as wp

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from warpfem.device import init_warp  # noqa: E402
from warpfem.io import UsdMeshWriter  # noqa: E402
from warpfem.progress import COMPILING_NOTICE, CompileWatch  # noqa: E402
from warpfem.scenes import load_scene  # noqa: E402

SCENE = os.path.join(os.path.dirname(os.path.abspath(__file__)), "scenes", "cantilever.toml")


class Example:
    """One frame per ``step()``; ``render()`` writes the current frame to the USD stage."""

    def __init__(self, stage_path="out/cantilever.usda", *, num_frames=None, precision="float64", device=None,
                 scene_path=SCENE):
        self.scene = load_scene(scene_path)
        self.run = self.scene.build(device=device or wp.get_device(), precision=precision)
        self.num_frames = num_frames or self.run.frames
        self.frame = 0
        self.sim_time = 0.0
        self.renderer = None
        if stage_path:
            self.renderer = UsdMeshWriter(stage_path, fps=self.run.fps)
            self.renderer.add_mesh(self.run.surface_name, self.run.surface_faces, self.run.num_surface_points)

    def step(self):
        stats = self.run.step_frame(total_frames=self.num_frames)
        self.frame = stats.frame
        self.sim_time = stats.time
        return stats

    def render(self):
        if self.renderer is not None:
            self.renderer.write_frame(self.frame, {self.run.surface_name: self.run.surface_points()})

    def close(self, complete=True, reason=None):
        if self.renderer is not None:
            self.renderer.close(complete=complete, reason=reason)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", type=str, default=None, help="Override the default Warp device (cpu, cuda:0, ... or auto).")
    parser.add_argument("--stage-path", type=lambda x: None if x == "None" else str(x), default="out/cantilever.usda",
                        help="Path to the output USD file (None: no output).")
    parser.add_argument("--num-frames", type=int, default=48, help="Total number of frames.")
    parser.add_argument("--precision", choices=("float32", "float64"), default="float64")
    parser.add_argument("--scene", default=SCENE, help="Scene file (default: examples/scenes/cantilever.toml).")
    parser.add_argument("--headless", action="store_true", help="Run without an interactive viewer (USD output only).")
    args = parser.parse_known_args(argv)[0]
    if args.device is not None:  # "auto", and a clear error for an unknown name (lists the devices)
        from warpfem.device import DeviceError, resolve_device

        try:
            args.device = resolve_device(args.device)
        except DeviceError as e:
            parser.error(str(e))

    init_warp(args.device or "cpu")  # quiet: no banner, no CUDA-driver note on a CPU (WARPFEM_VERBOSE=1 shows them)
    # a kernel-cache miss (the first run) is announced, as `warpfem run` does
    watch = CompileWatch(on_start=lambda: print(COMPILING_NOTICE, flush=True))
    with watch, wp.ScopedDevice(args.device):
        example = Example(stage_path=args.stage_path, num_frames=args.num_frames, precision=args.precision,
                          device=args.device, scene_path=args.scene)
        example.render()  # frame 0: rest state
        try:
            for _ in range(args.num_frames):
                stats = example.step()
                example.render()
                print(f"frame {stats.frame}/{args.num_frames}  t = {stats.time:.4f} s  newton {stats.newton_iterations}"
                      f"  cg {stats.cg_iterations}", flush=True)
        except BaseException as e:
            example.close(complete=False, reason=f"{type(e).__name__}: {e}")
            raise
        example.close()
    built = f"; kernels compiled in {watch.seconds:.1f} s (cached for later runs)" if watch.modules else ""
    if args.stage_path:
        print(f"wrote {args.stage_path} ({args.num_frames + 1} frames at {example.run.fps:g} fps){built}")
    elif built:
        print(built[2:])


if __name__ == "__main__":
    main()
