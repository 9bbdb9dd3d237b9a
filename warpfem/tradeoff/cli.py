"""``warpfem tradeoff SCENE``: run a scene over a grid of solver configurations, print the table,
write JSON / a Pareto plot. Listed in the command table :data:`warpfem.cli.COMMANDS` (``register`` below)."""

from __future__ import annotations

import os
import sys

from warpfem import cli as _cli

EXIT_OK, EXIT_FAILED, EXIT_INVALID, EXIT_INTERRUPTED = _cli.EXIT_OK, _cli.EXIT_FAILED, _cli.EXIT_INVALID, _cli.EXIT_INTERRUPTED


def _err(msg):
    print(f"warpfem tradeoff: error: {msg}", file=sys.stderr)


def _cmd_tradeoff(args) -> int:
    from warpfem.scenes import SceneError, load_scene

    from .study import GridError, builtin_grid, format_markdown, format_table, load_grid, plot_pareto, run_study

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
    try:
        load_scene(args.scene)
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
        print("\n".join([f"reference: {grid.reference.as_dict()}"] + [c.name for c in grid.configs]))
        return EXIT_OK
    if args.plot is not None:  # fail before an hour of runs, not after
        try:
            import matplotlib  # noqa: F401
        except ImportError:
            _err("--plot needs matplotlib, which is not installed: pip install 'warpfem[plot]' (or drop --plot)")
            return EXIT_FAILED

    from warpfem.progress import Progress
    from warpfem.solvers.nonlinear import SolveFailed

    if not args.quiet:
        print(f"{args.scene}: reference + {len(grid.configs)} configurations ({grid.name} grid) on {args.device}", flush=True)
    init = _cli.init_warp
    if init is not None:  # Warp's banner / "no CUDA driver" note only with --verbose (as `warpfem run`)
        init(args.device, args.verbose)
    bar = Progress(1 + len(grid.configs), unit="configuration", enabled=not args.quiet)
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

    try:
        with bar:
            study = run_study(args.scene, grid, device=args.device, frames=args.frames, quantity=args.quantity,
                              tip_point=tuple(args.tip_point) if args.tip_point else None, log=log, progress=progress)
    except (SceneError, GridError) as e:
        _err(str(e))
        return EXIT_INVALID
    except SolveFailed as e:
        _err(str(e))
        return EXIT_FAILED
    except KeyboardInterrupt:
        _err("interrupted")
        return EXIT_INTERRUPTED
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
    from .study import QUANTITIES

    p = subparsers.add_parser("tradeoff", help="speed/accuracy study of a scene over solver configurations")
    p.add_argument("scene", help="TOML scene file")
    p.add_argument("--grid", default="quick",
                   help="'quick' (one knob at a time, default), 'full' (products) or a grid .toml file")
    p.add_argument("--frames", type=int, default=None, help="output frames per run (default: grid's, else the scene's)")
    p.add_argument("--device", default="cpu", help="Warp device: cpu, cuda, cuda:0, ... or auto (default cpu)")
    p.add_argument("--json", default=None, metavar="OUT.json", help="write every measurement as JSON")
    p.add_argument("--markdown", default=None, metavar="OUT.md", help="write the table as markdown")
    p.add_argument("--plot", default=None, metavar="OUT.png", help="Pareto plot, error vs time (needs matplotlib)")
    p.add_argument("--quantity", choices=tuple(QUANTITIES), default="tip",
                   help="error measure of the frontier: tip displacement (default), rms vertex, surface, energy")
    p.add_argument("--tip-point", type=float, nargs=3, metavar=("X", "Y", "Z"), default=None,
                   help="rest position (m) whose displacement is the named quantity (default: free vertex of max displacement)")
    p.add_argument("--skip", action="append", default=[], metavar="NAME", help="drop a configuration by name (repeatable)")
    p.add_argument("--list", action="store_true", help="list the configurations and exit")
    p.add_argument("--quiet", action="store_true", help="no per-configuration lines")
    p.add_argument("--verbose", action="store_true", help="show Warp's messages")
    p.set_defaults(func=_cmd_tradeoff)


