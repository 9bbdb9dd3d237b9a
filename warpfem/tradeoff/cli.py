"""``warpfem tradeoff SCENE``: run a scene over a grid of solver configurations, print the table,
write JSON / a Pareto plot; ``warpfem tune SCENE``. Listed in the command table :data:`warpfem.cli.COMMANDS` (``register``, ``register_tune``)."""

from __future__ import annotations

import os
import sys

from warpfem import cli as _cli

EXIT_OK, EXIT_FAILED, EXIT_INVALID, EXIT_INTERRUPTED = _cli.EXIT_OK, _cli.EXIT_FAILED, _cli.EXIT_INVALID, _cli.EXIT_INTERRUPTED


def _err(msg):
    print(f"warpfem tradeoff: error: {msg}", file=sys.stderr)


def _outputs_unwritable(named, err) -> bool:
    """Report the first output path that cannot be written (one line) and return True."""
    from warpfem.io.outputs import OutputPathError, check_output_paths

    try:
        check_output_paths(named)
    except OutputPathError as e:
        err(str(e))
        return True
    return False


def _cmd_tradeoff(args) -> int:
    from warpfem.scenes import SceneError, load_scene

    from .grid import GridError, builtin_grid, load_grid
    from .report import format_markdown, format_table, plot_pareto
    from .study import run_study

    if args.frames is not None and args.frames < 1:
        _err(f"--frames must be >= 1, got {args.frames}")
        return EXIT_INVALID
    if args.json is not None and not args.json.lower().endswith(".json"):
        _err(f"--json must end in .json, got {args.json!r}")
        return EXIT_INVALID
    if args.plot is not None and not args.plot.lower().endswith(".png"):
        _err(f"--plot must end in .png, got {args.plot!r}")
        return EXIT_INVALID
    if _cli.check_device(args, _err) is not None:  # a bad --device: before the scene is read
        return EXIT_INVALID
    if _outputs_unwritable({"--json": args.json, "--markdown": args.markdown, "--plot": args.plot}, _err):
        return EXIT_INVALID
    try:
        if load_scene(args.scene).spec.bodies:
            _err(f"{args.scene}: trade-off studies take a one-body scene; this one has [[body]] tables")
            return EXIT_INVALID
    except SceneError as e:
        _err(str(e))
        return EXIT_INVALID
    try:
        grid = builtin_grid(args.grid) if args.grid in ("quick", "full") else load_grid(args.grid)
        if args.skip:
            names = {c.name for c in grid.configs}
            unknown = [s for s in args.skip if s not in names]
            if unknown:
                raise GridError(f"--skip: no configuration named {unknown[0]!r}; names: {', '.join(sorted(names))}")
            grid.configs = [c for c in grid.configs if c.name not in set(args.skip)]
    except GridError as e:
        _err(str(e))
        return EXIT_INVALID
    if args.list:
        truth = "none (--no-truth)" if args.no_truth or grid.truth is None else str(grid.truth.as_dict())
        print("\n".join([f"reference: {grid.reference.as_dict()}", f"converged reference: {truth}"]
                        + [c.name for c in grid.configs]))
        return EXIT_OK
    if args.plot is not None:  # fail before an hour of runs, not after
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            _err("--plot needs matplotlib, which is not installed: pip install 'warpfem[plot]' (or drop --plot)")
            return EXIT_FAILED

    from warpfem.progress import Progress
    from warpfem.solvers.nonlinear import SolveFailed

    from .cluster import executor_from_args

    if getattr(args, "retries", 0) < 0:
        _err(f"--retries must be >= 0, got {args.retries}")
        return EXIT_INVALID
    if args.no_truth:
        grid.truth = None

    if not args.quiet:
        print(f"{args.scene}: {len(grid.configs)} configurations ({grid.name} grid) + reference runs on {args.device}",
              flush=True)
    init = _cli.init_warp
    if init is not None:  # Warp's banner / "no CUDA driver" note only with --verbose (as `warpfem run`)
        init(args.device, args.verbose)
    from .study import planned_runs

    bar = Progress(planned_runs(args.scene, grid), unit="run", enabled=not args.quiet)
    done = 0

    def log(line):  # after each configuration (the reference first)
        nonlocal done
        done += 1
        if bar.drawing_bar:
            bar.note(line)
            bar.update(done)
        else:
            bar.update(done, line)

    def progress(cfg, fs):  # after each frame: the bar shows which run it is in
        if bar.drawing_bar:
            bar.update(done, f"{getattr(cfg, 'name', '')} frame {fs.frame}")

    executor, code = executor_from_args(args, _err)
    if code is not None:
        return code
    try:
        with bar:
            study = run_study(args.scene, grid, device=args.device, frames=args.frames, quantity=args.quantity,
                              tip_point=tuple(args.tip_point) if args.tip_point else None, log=log, progress=progress,
                              executor=executor)
    except (SceneError, GridError) as e:
        _err(str(e))
        return EXIT_INVALID
    except SolveFailed as e:
        _err(str(e))
        return EXIT_FAILED
    except KeyboardInterrupt:
        _err("interrupted")
        return EXIT_INTERRUPTED
    finally:
        if executor is not None:
            executor.close()
    print(format_table(study))
    if args.json:
        study.to_json(args.json)
        print(f"wrote {args.json}")
    if args.markdown:
        os.makedirs(os.path.dirname(os.path.abspath(args.markdown)), exist_ok=True)
        with open(args.markdown, "w") as f:
            f.write(format_markdown(study) + "\n")
        print(f"wrote {args.markdown}")
    if args.plot:
        try:
            plot_pareto(study, args.plot)
        except ImportError as e:
            _err(str(e))
            return EXIT_FAILED
        print(f"wrote {args.plot}")
    return EXIT_OK


def register(subparsers):
    from .grid import QUANTITIES

    p = subparsers.add_parser("tradeoff", help="speed/accuracy study of a scene over solver configurations")
    p.add_argument("scene", help="TOML scene file")
    p.add_argument("--grid", default="quick",
                   help="'quick' (one knob at a time, default), 'full' (products) or a grid .toml file")
    p.add_argument("--frames", type=int, default=None, help="output frames per run (default: grid's, else the scene's)")
    p.add_argument("--device", default="cpu", help="Warp device: cpu, cuda, cuda:0, ... or auto (default cpu)")
    _cli.add_threads_option(p)
    p.add_argument("--json", default=None, metavar="OUT.json", help="write every measurement as JSON")
    p.add_argument("--markdown", default=None, metavar="OUT.md", help="write the table as markdown")
    p.add_argument("--plot", default=None, metavar="OUT.png", help="Pareto plot, error vs time (needs matplotlib)")
    p.add_argument("--quantity", choices=tuple(QUANTITIES), default="tip",
                   help="error measure of the frontier: tip displacement (default), rms vertex, surface, energy")
    p.add_argument("--tip-point", type=float, nargs=3, metavar=("X", "Y", "Z"), default=None,
                   help="rest position (m) whose displacement is the named quantity (default: free vertex of max displacement)")
    p.add_argument("--skip", action="append", default=[], metavar="NAME", help="drop a configuration by name (repeatable)")
    p.add_argument("--no-truth", action="store_true",
                   help="compare with the grid's reference on the scene's own mesh (solver / time-step error only) "
                        "instead of the converged reference (refined higher-order mesh, time-step ladder)")
    from .cluster import add_cluster_args

    add_cluster_args(p)
    p.add_argument("--list", action="store_true", help="list the configurations and exit")
    p.add_argument("--quiet", action="store_true", help="no per-configuration lines")
    p.add_argument("--verbose", action="store_true", help="show Warp's messages")
    p.set_defaults(func=_cmd_tradeoff)




# ----------------------------------------------------------------------------- warpfem tune
def _tune_err(msg):
    print(f"warpfem tune: error: {msg}", file=sys.stderr)


def _cmd_tune(args) -> int:
    from warpfem.scenes import SceneError, load_scene
    from warpfem.solvers.nonlinear import SolveFailed

    from .cluster import executor_from_args
    from .grid import GridError, TruthSpec
    from .tune import SPACES, format_tune, load_space, tune, write_scene

    if not args.max_error > 0:
        _tune_err(f"--max-error must be > 0, got {args.max_error}")
        return EXIT_INVALID
    if args.frames is not None and args.frames < 1:
        _tune_err(f"--frames must be >= 1, got {args.frames}")
        return EXIT_INVALID
    for opt, val, ext in (("--out", args.out, ".toml"), ("--report", args.report, ".json")):
        if val is not None and not val.lower().endswith(ext):
            _tune_err(f"{opt} must end in {ext}, got {val!r}")
            return EXIT_INVALID
    if args.space is not None and args.space not in SPACES and not args.space.lower().endswith(".toml"):
        _tune_err(f"--space must be {' or '.join(SPACES)} or a search-space .toml file, got {args.space!r}")
        return EXIT_INVALID
    if _cli.check_device(args, _tune_err) is not None:
        return EXIT_INVALID
    try:
        scene = load_scene(args.scene)
    except SceneError as e:
        _tune_err(str(e))
        return EXIT_INVALID
    if scene.spec.bodies:
        _tune_err(f"{args.scene}: tune takes a one-body scene; this one has [[body]] tables")
        return EXIT_INVALID
    try:
        space = args.space if args.space in SPACES else "default"
        axes = load_space(args.space) if args.space and args.space not in SPACES else {}
        if args.subspace:
            axes["subspace"] = list(args.subspace)
        truth = None if args.no_truth else TruthSpec.from_dict(
            {k: v for k, v in (("refine", args.truth_refine), ("substeps", args.truth_substeps),
                               ("element", args.truth_element)) if v is not None}, where="--truth-*")
    except GridError as e:
        _tune_err(str(e))
        return EXIT_INVALID
    stem = os.path.splitext(os.path.basename(args.scene))[0]
    out = args.out or os.path.join("out", "tune", f"{stem}.tuned.toml")
    report = args.report or os.path.splitext(out)[0] + ".json"
    if _outputs_unwritable({"--out": out, "--report": report}, _tune_err):  # before minutes of runs
        return EXIT_INVALID
    init = _cli.init_warp
    if init is not None:
        init(args.device, args.verbose)
    executor, code = executor_from_args(args, _tune_err)
    if code is not None:
        return code
    log = (lambda s: None) if args.quiet else (lambda s: print(s, flush=True))
    try:
        result = tune(args.scene, args.max_error, quantity=args.quantity, frames=args.frames, device=args.device,
                      axes=axes, truth=truth, cost=args.cost, executor=executor, log=log,
                      tip_point=tuple(args.tip_point) if args.tip_point else None, space=space)
    except (SceneError, GridError) as e:
        _tune_err(str(e))
        return EXIT_INVALID
    except SolveFailed as e:
        _tune_err(str(e))
        return EXIT_FAILED
    except KeyboardInterrupt:
        _tune_err("interrupted")
        return EXIT_INTERRUPTED
    finally:
        if executor is not None:
            executor.close()
    if result.winner is not None:
        write_scene(result, out)
    result.to_json(report)
    print(format_tune(result))
    print(f"wrote {report}")
    del scene
    return EXIT_OK if result.winner is not None else EXIT_FAILED


def register_tune(subparsers):
    from .cluster import add_cluster_args

    p = subparsers.add_parser("tune", help="cheapest configuration of a scene within an error budget")
    p.add_argument("scene", help="TOML scene file")
    p.add_argument("--max-error", type=float, required=True, metavar="E",
                   help="error budget against the converged reference (e.g. 0.01 = 1 %% of the peak tip displacement)")
    p.add_argument("--quantity", choices=("tip", "rms"), default="tip",
                   help="tip: tip displacement error / its peak (default); rms: RMS vertex error / object size")
    p.add_argument("--cost", choices=("time", "work"), default="time",
                   help="what 'cheapest' means: measured wall time (default) or the deterministic work proxy")
    p.add_argument("--frames", type=int, default=None, help="frames of the full run (default: the scene's)")
    p.add_argument("--out", default=None, metavar="TUNED.toml", help="scene file to write (default out/tune/<scene>.tuned.toml)")
    p.add_argument("--report", default=None, metavar="REPORT.json", help="search report (default next to --out)")
    p.add_argument("--space", default=None, metavar="default|full|SPACE.toml",
                   help="search space: default (the registered dynamic integrators on the scene's element and its "
                        "higher-order partner, 1/2/4 substeps, float64; a surface-file scene also 1/4, 1/2, 1 x its target_tets "
                        "and float32: minutes), full (every element, 1-8 substeps, "
                        "two tolerances each, both precisions, every linear solver: hours), or a file of axes (arrays) "
                        "replacing those of the default space")
    p.add_argument("--subspace", type=int, nargs="+", default=None, metavar="R",
                   help="also search reduced runs with these subspace sizes (trains each once: minutes)")
    p.add_argument("--truth-refine", type=int, default=None,
                   help="reference mesh: cells x this (default 2); a surface-file scene: target_tets x this cubed")
    p.add_argument("--truth-substeps", type=int, default=None, help="reference: finest substeps per frame (default 8)")
    p.add_argument("--truth-element", default=None, help="reference element (default tet10 / hex27)")
    p.add_argument("--no-truth", action="store_true",
                   help="measure against the tight run on the scene's own mesh (solver / time-step error only)")
    p.add_argument("--tip-point", type=float, nargs=3, metavar=("X", "Y", "Z"), default=None,
                   help="rest position (m) of the tip (default: free vertex of max displacement)")
    p.add_argument("--device", default="cpu", help="Warp device: cpu, cuda, cuda:0, ... or auto (default cpu)")
    _cli.add_threads_option(p)
    add_cluster_args(p)
    p.add_argument("--quiet", action="store_true", help="no progress lines")
    p.add_argument("--verbose", action="store_true", help="show Warp's messages")
    p.set_defaults(func=_cmd_tune)


