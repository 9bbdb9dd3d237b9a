"""``warpfem train SCENE``: precompute and cache a scene's subspace (basis + cubature).

Listed in the command table :data:`warpfem.cli.COMMANDS` (``register`` below).
Exit codes as in :mod:`warpfem.cli`: 0 trained (or up to date), 1 training failed (e.g. the
snapshot run diverged, a basis that cannot be built), 2 invalid scene or command line, 130
interrupted.
"""

from __future__ import annotations

from warpfem import cli as _cli


def _cmd_train(args) -> int:
    from warpfem.scenes import SceneError
    from warpfem.solvers.nonlinear import SolveFailed

    if _cli.check_device(args) is not None:  # a bad --device: before the scene is read
        return _cli.EXIT_INVALID
    try:
        scene = _cli.load(args.scene)
    except SceneError as e:
        _cli.error(str(e))
        return _cli.EXIT_INVALID
    if scene.spec.subspace is None:
        _cli.error(f"{args.scene}: no [subspace] section: nothing to train (add [subspace] with modes, "
                  "cubature_tolerance, ... to make the run reduced)")
        return _cli.EXIT_INVALID
    from warpfem.io.outputs import OutputPathError, check_output_paths
    from warpfem.reduced.scene import subspace_cache_path, train_scene
    from warpfem.reduced.subspace import format_report

    try:  # the cache file is written after the whole training: its folder is checked before it
        check_output_paths({"[subspace] cache": subspace_cache_path(scene)})
    except OutputPathError as e:
        _cli.error(f"{args.scene}: {e}")
        return _cli.EXIT_INVALID

    s = scene.spec.subspace
    if not args.quiet:
        snap = f"a full run of {s['training_frames'] or scene.spec.output['frames']} frames"
        how = {"snapshots": snap, "random": f"{s['training_poses']} random poses",
               "mixed": f"{s['training_poses']} random poses + {snap}"}[s["training"]]
        print(f"{scene.name}: training r = {s['modes']} subspace, cubature tolerance {s['cubature_tolerance']:g} "
              f"from {how} on {args.device} ({args.precision}) -> {subspace_cache_path(scene)}", flush=True)

    init = _cli.init_warp
    if init is not None:  # Warp's banner / "no CUDA driver" note only with --verbose (as `warpfem run`)
        init(args.device, args.verbose)

    import time

    from warpfem.progress import Progress

    bar, started = None, time.perf_counter()

    def progress(k, total):
        nonlocal bar
        if bar is None:
            bar = Progress(total, unit="training frame", enabled=not args.quiet, started=started)
        bar.update(k)

    def log(line):  # one line per error-budget attempt (after the training run's bar)
        nonlocal bar
        if args.quiet:
            return
        if bar is not None:
            bar.close()
            bar = None
        print(line, flush=True)

    try:
        try:
            sub = train_scene(scene, device=args.device, precision=args.precision, retrain=args.retrain, progress=progress,
                              log=log)
        finally:
            if bar is not None:
                bar.close()
    except SceneError as e:
        _cli.error(str(e))
        return _cli.EXIT_INVALID
    except SolveFailed as e:
        _cli.error(f"{args.scene}: the full training run failed: {e}")
        return _cli.EXIT_FAILED
    except (ValueError, RuntimeError, OSError) as e:
        _cli.error(f"{args.scene}: training failed: {e}")
        return _cli.EXIT_FAILED
    except KeyboardInterrupt:
        _cli.error("interrupted; the cache was not written")
        return _cli.EXIT_INTERRUPTED
    print(format_report(sub.report), flush=True)
    return _cli.EXIT_OK


def register(subparsers):
    p = subparsers.add_parser("train", help="train and cache a scene's reduced subspace (basis + cubature)")
    p.add_argument("scene", help="TOML scene file with a [subspace] section")
    p.add_argument("--retrain", action="store_true",
                   help="train even when the cache is up to date (default: reuse a cache that matches the scene)")
    p.add_argument("--device", default="cpu", help="Warp device for the training run: cpu, cuda, cuda:0, ... or auto (default cpu)")
    _cli.add_threads_option(p)
    p.add_argument("--precision", choices=("float32", "float64"), default="float64")
    p.add_argument("--quiet", action="store_true", help="only the final report")
    p.add_argument("--verbose", action="store_true", help="show Warp's initialisation and compile messages")
    p.set_defaults(func=_cmd_train)


