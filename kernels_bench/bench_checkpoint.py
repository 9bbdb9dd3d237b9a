"""What checkpoints cost a scene run: the wall time per frame of ``SceneRun.run`` with
``checkpoint_every = 1`` (a checkpoint and a saved USD every frame, the default) against
``checkpoint_every = 0`` (none; the USD saved every 10 frames), measured in the same process, the two
alternating over ``--rounds`` rounds (best of each reported), with a USD and a states output; plus
one checkpoint alone (``Checkpoint.save``: the simulator's state file, written and synced to disk,
and the commit record) and its size on disk.

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
        ck = Checkpoint(os.path.join(tmp, "alone"), run)
        saves = []
        for _ in range(5):
            t0 = time.perf_counter()
            ck.save(frames)
            saves.append(time.perf_counter() - t0)
        size = sum(os.path.getsize(os.path.join(ck.folder, f)) for f in os.listdir(ck.folder))
        size //= 2 if os.path.exists(os.path.join(ck.folder, "state_1.npz")) else 1  # one state slot + record
    off, on = min(per_frame[0]), min(per_frame[1])
    return {"scene": path, "vertices": int(run.model.num_vertices), "elements": int(scene.mesh().num_elements),
            "frames": frames, "rounds": rounds,
            "seconds_per_frame_without_checkpoints": off, "seconds_per_frame_checkpoint_every_frame": on,
            "overhead_seconds_per_frame": on - off, "overhead_percent": 100.0 * (on - off) / off,
            "checkpoint_save_seconds_median": statistics.median(saves), "checkpoint_bytes": size}


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
              f"{r['checkpoint_bytes'] / 1024:.0f} KiB", flush=True)
    if args.out:
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out, "w") as f:
            json.dump(results, f, indent=2)
            f.write("\n")


if __name__ == "__main__":
    main()
