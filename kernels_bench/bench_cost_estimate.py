"""``warpfem describe``'s cost estimate against the measured cost per frame.

For each scene: :meth:`Scene.cost_estimate` (seconds per frame, Newton iterations per frame), then
the scene built on the CPU in float64 and run for ``--frames`` frames; measured: the median wall
seconds of a frame's steps and the mean Newton iterations per frame, frame 1 left out (kernel
compilation, the solver's first analysis). Ratios measured / estimated; the estimate claims
``warpfem.scenes.cost.STATED_FACTOR`` either way.

Scenes: the command-line tests' 4-cell beam (tiny), the shipped knight (TetGen mesh of a surface),
cantilever, twisted bar, bunny drop (contact) and ball in a bowl (contact).

    .venv/bin/python kernels_bench/bench_cost_estimate.py [--frames 5] [--out PATH]
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "tests"))

SCENES = ["knight.toml", "cantilever.toml", "twisted_bar.toml", "bunny_drop.toml", "ball_bowl.toml"]


def measure(path, frames):
    import numpy as np

    from warpfem.scenes import load_scene

    scene = load_scene(path)
    est = scene.cost_estimate()
    run = scene.build(device="cpu", precision="float64")
    rows = []
    run.run(frames=frames, progress=rows.append)
    later = rows[1:] or rows
    secs = float(np.median([r.step_seconds for r in later]))
    newton = float(np.mean([r.newton_iterations for r in later]))
    return dict(scene=os.path.basename(path), vertices=int(scene.mesh().num_vertices), frames=frames,
                estimated_s_per_frame=est["seconds_per_frame"], measured_s_per_frame=secs,
                time_ratio=secs / est["seconds_per_frame"], estimated_newton_per_frame=est["newton_per_frame"],
                measured_newton_per_frame=newton, newton_ratio=newton / est["newton_per_frame"],
                contact=est["contact_factor"] > 1, basis=est["basis"])


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=10)
    ap.add_argument("--out", default=str(ROOT / "kernels_bench" / "results" / "cost_estimate"))
    args = ap.parse_args()
    import warp as wp

    wp.config.quiet = True
    from tiny_scenes import cli_beam_toml
    from warpfem.scenes.cost import STATED_FACTOR

    load0 = os.getloadavg()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        beam = os.path.join(tmp, "tiny_beam.toml")
        with open(beam, "w") as f:
            f.write(cli_beam_toml(frames=args.frames))
        for path in [beam] + [str(ROOT / "examples" / "scenes" / s) for s in SCENES]:
            r = measure(path, args.frames)
            print(r, flush=True)
            rows.append(r)
    meta = dict(device="cpu", precision="float64", cpu=platform.processor() or platform.machine(), cores=os.cpu_count(),
                stated_factor=STATED_FACTOR, load_average_start=load0, load_average_end=os.getloadavg())
    with open(args.out + ".json", "w") as f:
        json.dump(dict(meta=meta, rows=rows), f, indent=1)
    lines = ["| scene | vertices | contact | estimated s / frame | measured | measured / estimated | Newton / frame est. | measured |",
             "| --- | ---: | --- | ---: | ---: | ---: | ---: | ---: |"]
    for r in rows:
        lines.append(f"| {r['scene']} | {r['vertices']} | {'yes' if r['contact'] else 'no'} | {r['estimated_s_per_frame']:.3g} | "
                     f"{r['measured_s_per_frame']:.3g} | {r['time_ratio']:.2f} | {r['estimated_newton_per_frame']:g} | "
                     f"{r['measured_newton_per_frame']:.1f} |")
    from kernels_bench.report import write_markdown

    write_markdown(args.out + ".md", lines, meta)


if __name__ == "__main__":
    main()
