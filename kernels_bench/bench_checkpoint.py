"""What checkpoints cost a scene run: the wall time per frame of ``SceneRun.run`` with
``checkpoint_every = 1`` (a checkpoint and a saved USD every frame, the default) against
``checkpoint_every = 0`` (none; the USD saved every 10 frames), measured in the same process, the two
alternating over ``--rounds`` rounds (best of each reported), with a USD and a states output; plus
one checkpoint alone (``Checkpoint.save``: the simulator's state and the run's record in one file, written and synced to
disk, then renamed over the previous one) and its size on disk; and one save of the USD (which a checkpointed frame also costs), with the
current value clip holding 1 and 100 frames of the scene's render surface.

    python kernels_bench/bench_checkpoint.py                     # cantilever (480 tets) and bunny_gravity
    python kernels_bench/bench_checkpoint.py --out kernels_bench/results/checkpoint.json
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import statistics
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENES = {"cantilever": ("examples/scenes/cantilever.toml", 24), "bunny_gravity": ("examples/scenes/bunny_gravity.toml", 6)}


def measure(name, path, frames, rounds, device):
    from warpfem.scenes import load_scene
    from warpfem.scenes.checkpoint import Checkpoint

    scene = load_scene(os.path.join(ROOT, path))
    per_frame = {0: [], 1: []}
    with tempfile.TemporaryDirectory() as tmp:
        scene.build(device=device).run(frames=1, usd=os.path.join(tmp, "w.usda"), checkpoint_every=1)  # warm
        for _ in range(rounds):
            for every in (0, 1):
                run = scene.build(device=device)
                out = os.path.join(tmp, f"e{every}")
                t0 = time.perf_counter()
                run.run(frames=frames, usd=os.path.join(out, "s.usda"), states=os.path.join(out, "s.npz"),
                        checkpoint_every=every)
                per_frame[every].append((time.perf_counter() - t0) / frames)
        ck = Checkpoint(os.path.join(tmp, "alone.checkpoint.npz"), run)
        saves = []
        for _ in range(5):
            t0 = time.perf_counter()
            ck.save(frames)
            saves.append(time.perf_counter() - t0)
        size = os.path.getsize(ck.path)
        # the USD's save of each checkpointed frame, at its dearest: the current clip (default 100 frames) full
        from warpfem.io import UsdMeshWriter

        w = UsdMeshWriter(os.path.join(tmp, "u.usda"), fps=24.0, save_every=10 ** 6, clip_frames=101)
        for pname, faces, count in run.usd_surfaces():
            w.add_mesh(pname, faces, count)
        pts = run.usd_surface_points()
        usd_saves = {}
        for f in range(100):
            w.write_frame(f, pts)
            if f in (0, 99):
                t0 = time.perf_counter()
                w.save()
                usd_saves[f + 1] = time.perf_counter() - t0
        w.close()
    off, on = min(per_frame[0]), min(per_frame[1])
    return {"scene": path, "vertices": int(run.model.num_vertices), "elements": int(scene.mesh().num_elements),
            "frames": frames, "rounds": rounds,
            "seconds_per_frame_without_checkpoints": off, "seconds_per_frame_checkpoint_every_frame": on,
            "overhead_seconds_per_frame": on - off, "overhead_percent": 100.0 * (on - off) / off,
            "checkpoint_save_seconds_median": statistics.median(saves), "checkpoint_bytes": size,
            "surface_points": int(run.num_surface_points),
            "usd_save_seconds_clip_with_1_frame": usd_saves[1], "usd_save_seconds_clip_with_100_frames": usd_saves[100]}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--scene", action="append", choices=sorted(SCENES), default=None)
    ap.add_argument("--out", default=None, help="results JSON")
    args = ap.parse_args(argv)
    sys.path.insert(0, ROOT)
    results = {"device": args.device, "processor": platform.processor() or platform.machine(),
               "note": "the machine's 2 cores were shared with other jobs; ratios within one run", "scenes": {}}
    for name in args.scene or list(SCENES):
        path, frames = SCENES[name]
        r = measure(name, path, frames, args.rounds, args.device)
        results["scenes"][name] = r
        print(f"{name}: {r['elements']} elements: {1e3 * r['seconds_per_frame_without_checkpoints']:.1f} ms/frame "
              f"without checkpoints, {1e3 * r['seconds_per_frame_checkpoint_every_frame']:.1f} ms/frame with one "
              f"every frame (+{1e3 * r['overhead_seconds_per_frame']:.1f} ms, {r['overhead_percent']:+.0f} %); "
              f"one checkpoint {1e3 * r['checkpoint_save_seconds_median']:.1f} ms, "
              f"{r['checkpoint_bytes'] / 1024:.0f} KiB; USD save {1e3 * r['usd_save_seconds_clip_with_1_frame']:.1f} ms "
              f"(clip of 1 frame) to {1e3 * r['usd_save_seconds_clip_with_100_frames']:.1f} ms (100 frames)", flush=True)
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            json.dump(results, f, indent=2)
            f.write("\n")


if __name__ == "__main__":
    main()
