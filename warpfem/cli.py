"""The ``warpfem`` command line: ``warpfem run SCENE``, ``warpfem describe SCENE``, ``warpfem compare A B``,
``--version``.

The subcommands are listed in one table, :data:`COMMANDS` (name -> ``"module:function"``). Each
function is ``register(subparsers)``: it adds its parser and must ``set_defaults(func=handler)``,
where ``handler(args) -> int`` returns the exit code. A module is imported only when the parser is
built, so a subcommand whose optional dependency is missing does not break the others, and a command
line naming a subcommand (``warpfem run ...``) imports that subcommand's module only. A new
subcommand is one module with a ``register`` function plus one line in :data:`COMMANDS`.

Subcommand modules use the public helpers here: :func:`error`, :func:`check_device`,
:func:`init_warp`, :func:`load` and the exit codes.

Exit codes: 0 success (``run``: non-converged steps are counted on the final line), 1 a step
diverged / failed to converge (with ``require_convergence`` or ``--require-convergence``) or
another runtime error, 2 invalid command line, scene or output path, 130 interrupted (Ctrl-C), 143
terminated (SIGTERM; ``run`` records it in the USD as it does Ctrl-C).
"""

from __future__ import annotations

import argparse
import logging
import sys

__all__ = ["main", "build_parser", "COMMANDS", "add_subcommand", "error", "check_device", "init_warp", "load",
           "EXIT_OK", "EXIT_FAILED", "EXIT_INVALID", "EXIT_INTERRUPTED", "EXIT_TERMINATED", "Terminated",
           "terminate_on_sigterm"]

EXIT_OK, EXIT_FAILED, EXIT_INVALID, EXIT_INTERRUPTED, EXIT_TERMINATED = 0, 1, 2, 130, 143


class Terminated(KeyboardInterrupt):
    """SIGTERM received: raised in the main thread so that outputs are closed marked incomplete
    with the reason, as on Ctrl-C (a KeyboardInterrupt, so code that cleans up on Ctrl-C does)."""


class terminate_on_sigterm:
    """Context manager: SIGTERM raises :class:`Terminated` inside it (main thread only; the previous
    handler is restored on exit)."""

    def __enter__(self):
        import signal
        import threading

        self._previous = None
        if threading.current_thread() is threading.main_thread() and hasattr(signal, "SIGTERM"):
            def _raise(signum, frame):
                raise Terminated("SIGTERM")

            self._previous = signal.signal(signal.SIGTERM, _raise)
        return self

    def __exit__(self, *exc):
        if self._previous is not None:
            import signal

            signal.signal(signal.SIGTERM, self._previous)
        return False


def _version():
    from warpfem import __version__  # the one definition (pyproject reads it too)

    return __version__


def error(msg):
    print(f"warpfem: error: {msg}", file=sys.stderr)


def note(msg):
    print(f"warpfem: note: {msg}", file=sys.stderr)


class _LogHandler(logging.Handler):
    """The library's log records on the current ``sys.stderr`` ("warning: ..." for warnings)."""

    def emit(self, record):
        try:
            msg = record.getMessage()
            if record.levelno >= logging.WARNING:
                msg = f"{record.levelname.lower()}: {msg}"
            elif record.levelno < logging.INFO:
                msg = f"debug: {record.name}: {msg}"
            print(msg, file=sys.stderr, flush=True)
        except Exception:  # noqa: BLE001 - logging must not raise
            self.handleError(record)


def _configure_logging(verbose: bool, quiet: bool = False) -> None:
    """The ``warpfem`` loggers: INFO and up on stderr, DEBUG too with ``--verbose``, only warnings
    and errors with ``--quiet`` (no "tetrahedralisation cache hit" line)."""
    log = logging.getLogger("warpfem")
    for h in [h for h in log.handlers if isinstance(h, _LogHandler)]:
        log.removeHandler(h)
    log.addHandler(_LogHandler())
    log.setLevel(logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO)


class _only_warnings:
    """Inside it, the ``warpfem`` loggers pass warnings and errors only (``describe`` prints the
    mesh's notes in its own text; the INFO lines would repeat them)."""

    def __enter__(self):
        self._log = logging.getLogger("warpfem")
        self._level = self._log.level
        if self._log.getEffectiveLevel() < logging.WARNING:
            self._log.setLevel(logging.WARNING)
        return self

    def __exit__(self, *exc):
        self._log.setLevel(self._level)
        return False


def check_device(args, err=None):
    """Validate ``args.device`` (before the scene is read) and replace it by the device's alias
    (``auto``: CUDA when present, else cpu). Returns None, or EXIT_INVALID after the message."""
    from warpfem.device import DeviceError, resolve_device

    if str(args.device).strip().lower() != "cpu":  # listing the devices initialises Warp
        init_warp(args.device, getattr(args, "verbose", False))
    try:
        args.device = resolve_device(args.device)
    except DeviceError as e:
        (err or error)(str(e))
        return EXIT_INVALID
    return None


def _configure_warp(verbose: bool) -> None:
    """Warp's start-up banner and module-load lines only with ``--verbose`` (warnings always);
    must run before Warp initialises (``warpfem.device.configure_warp``)."""
    from warpfem.device import configure_warp

    configure_warp(verbose or None)  # --verbose, or WARPFEM_VERBOSE in the environment


def init_warp(device: str, verbose: bool) -> None:
    """Initialise Warp now; on a CPU device without ``--verbose`` the native note that no CUDA
    driver was found is dropped (``warpfem.device.init_warp``)."""
    from warpfem.device import init_warp as _init

    _init(device, verbose or None)


def load(path):
    from warpfem.scenes import load_scene

    return load_scene(path)


# ----------------------------------------------------------------------------- describe
def _cmd_describe(args) -> int:
    from warpfem.scenes import SceneError

    try:
        with _only_warnings():  # the tetrahedralisation line is part of the description: once
            scene = load(args.scene)
            text = None if getattr(args, "json", False) else scene.describe(precision=args.precision)
            summary = scene.summary() if text is None else None
        if getattr(args, "json", False):
            import json

            print(json.dumps(summary, indent=2))
        else:
            print(text)
    except SceneError as e:
        error(str(e))
        return EXIT_INVALID
    return EXIT_OK


def _register_describe(subparsers):
    p = subparsers.add_parser("describe", help="print what a scene builds (counts, memory, estimated cost per frame) "
                                               "without running it (a surface file is meshed, with progress on stderr)")
    p.add_argument("scene", help="TOML scene file")
    p.add_argument("--precision", choices=("float32", "float64"), default="float64")
    p.add_argument("--json", action="store_true", help="print a JSON object instead of text")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr (meshing a surface file)")
    p.set_defaults(func=_cmd_describe)


# ----------------------------------------------------------------------------- run
def _cmd_run(args) -> int:
    from warpfem.scenes import SceneError

    if args.frames is not None and args.frames < 1:
        error(f"--frames must be >= 1, got {args.frames}")
        return EXIT_INVALID
    if args.out is not None and not args.out.lower().endswith((".usda", ".usd", ".usdc")):
        error(f"--out must end in .usda, .usd or .usdc, got {args.out!r}")
        return EXIT_INVALID
    if check_device(args) is not None:
        return EXIT_INVALID
    if getattr(args, "preview", None) is not None:
        if not args.preview.lower().endswith(".png"):
            error(f"--preview must end in .png, got {args.preview!r}")
            return EXIT_INVALID
        from warpfem.io.preview import require_matplotlib

        try:
            require_matplotlib()
        except ImportError as e:
            error(f"--preview: {e}")
            return EXIT_INVALID
    try:
        scene = load(args.scene)  # validation only: fails before anything is built or written
    except SceneError as e:
        error(str(e))
        return EXIT_INVALID
    paths = scene.output_paths(usd=args.out, stats="" if args.out is not None else None)
    usd, stats = paths["usd"], paths["stats"]
    from warpfem.io.outputs import OutputPathError, check_output_paths, checkpoint_path

    checkpoint = checkpoint_path(paths) if scene.spec.output["checkpoint_every"] or args.resume else None
    try:  # every output path before any work (a file named as a folder, a folder not writable)
        check_output_paths({"--out" if args.out is not None else "[output] usd": usd, "statistics log": stats,
                            "[output] states": paths["states"], "[output] vtu": paths["vtu"],
                            "checkpoint": checkpoint, "--preview": getattr(args, "preview", None)})
    except OutputPathError as e:
        error(f"{args.scene}: {e}")
        return EXIT_INVALID

    from warpfem.progress import COMPILING_NOTICE, CompileWatch

    shown = {"bar": None}  # the progress display once it exists

    def compiling():  # a kernel-cache miss ahead (Warp compiles on first use; ~15 s on a CPU)
        if args.quiet:
            return
        if shown["bar"] is not None:
            shown["bar"].note(COMPILING_NOTICE)
        else:
            print(COMPILING_NOTICE, flush=True)

    def compiled(seconds):  # compile time is not frame time: out of the ETA
        if shown["bar"] is not None:
            shown["bar"].exclude(seconds)

    with CompileWatch(on_start=compiling, on_compiled=compiled) as watch:
        return _run_scene(args, scene, usd, stats, watch, shown)


def _run_scene(args, scene, usd, stats, watch, shown) -> int:
    from warpfem.scenes import SceneError
    from warpfem.solvers.nonlinear import SolveFailed

    try:
        init_warp(args.device, getattr(args, "verbose", False))
        run = scene.build(device=args.device, precision=args.precision)
    except SceneError as e:
        error(str(e))
        return EXIT_INVALID
    except (ValueError, RuntimeError) as e:  # e.g. an unknown device
        error(f"{args.scene}: cannot build the scene: {e}")
        return EXIT_FAILED
    frames = args.frames if args.frames is not None else run.frames
    if getattr(args, "require_convergence", False):  # as the scene's [integrator] require_convergence = true
        run.sim.require_convergence = True
    if not args.quiet:
        print(f"{scene.name}: {scene.mesh().num_elements} elements, {scene.mesh().num_vertices} vertices, "
              f"{frames} frames on {args.device} ({args.precision})", flush=True)

    from warpfem.progress import Progress

    bar = Progress(frames, unit="frame", enabled=not args.quiet)
    shown["bar"] = bar

    def progress(fs):  # a frame with non-converged steps also has its warning line (SceneRun.run's log)
        flag = "" if fs.converged else "  NOT CONVERGED"
        bar.update(fs.frame, f"t = {fs.time:.4f} s  newton {fs.newton_iterations}  cg {fs.cg_iterations}  "
                             f"{fs.step_seconds:.3f} s{flag}")

    on_frame, recorder = progress, None
    if getattr(args, "preview", None) is not None:  # keep the render surface at a few frames for the picture
        from warpfem.io.preview import PreviewRecorder

        recorder = PreviewRecorder(frames)
        recorder.add(0, 0.0, run.surface_points())

        def on_frame(fs, _report=progress):
            if recorder.wants(fs.frame):
                recorder.add(fs.frame, fs.time, run.surface_points())
            _report(fs)

    from warpfem.io.outputs import OutputPathError
    from warpfem.io.writers import OutputWriteError
    from warpfem.scenes.checkpoint import NothingToResume, ResumeError

    _StartupCollector.resume()  # start-up is over (a no-op unless main() owns the process)
    try:
        with bar, terminate_on_sigterm():
            history = run.run(frames=frames, usd=usd, stats=stats, progress=on_frame,
                              resume=getattr(args, "resume", False))
    except NothingToResume as e:
        if not e.complete:
            error(f"{args.scene}: {e}")
            return EXIT_INVALID
        print(f"{args.scene}: {e}", flush=True)  # already done: not an error (a resubmitted farm job)
        return EXIT_OK
    except (ResumeError, OutputPathError) as e:
        error(f"{args.scene}: {e}")
        return EXIT_INVALID
    except OutputWriteError as e:
        error(f"{args.scene}: {e}; the frames before it are kept")
        return EXIT_FAILED
    except SolveFailed as e:
        error(f"{args.scene}: frame {run.frame}: {e}" + (f"; frames 0..{run.frame - 1} are in {usd} (marked incomplete)" if usd else ""))
        return EXIT_FAILED
    except KeyboardInterrupt as e:
        how = "terminated (SIGTERM)" if isinstance(e, Terminated) else "interrupted"
        error(f"{how} at frame {run.frame}" + (f"; {usd} holds the frames done (marked incomplete)" if usd else ""))
        return EXIT_TERMINATED if isinstance(e, Terminated) else EXIT_INTERRUPTED
    if recorder is not None:
        from warpfem.io.preview import render_preview

        contact = getattr(run.sim, "contact", None)
        render_preview(args.preview, recorder.snapshots, run.surface_faces, up_axis=scene.spec.output["up_axis"],
                       title=scene.name, colliders=list(getattr(contact, "colliders", ())))
    if not args.quiet:
        outs = [p for p in (usd, stats, scene.spec.output["states"], scene.spec.output.get("vtu"),
                            getattr(args, "preview", None)) if p]
        built = f"; kernels compiled in {watch.seconds:.1f} s (cached for later runs)" if watch.modules else ""
        print(f"done: {frames} frames ({_convergence_report(run.convergence_summary(history, run.resumed_totals))})"
              + (f"; wrote {', '.join(outs)}" if outs else "") + built, flush=True)
    return EXIT_OK


def _convergence_report(summary, most=10) -> str:
    """``192 steps, all converged`` or ``192 steps, 3 not converged: frames 9, 17, 18; worst: frame
    17, relative gradient 3.10e-04`` (the first ``most`` frames, then how many more; the worst is
    the unconverged step with the largest relative gradient)."""
    n, bad, frames = summary["steps"], summary["unconverged_steps"], summary["unconverged_frames"]
    steps = f"{n} step{'s' if n != 1 else ''}"
    if not bad:
        return f"{steps}, all converged"
    shown = ", ".join(str(f) for f in frames[:most]) + (f" and {len(frames) - most} more" if len(frames) > most else "")
    worst = summary.get("worst")
    tail = f"; worst: frame {worst[0]}, relative gradient {worst[1]:.2e}" if worst else ""
    return f"{steps}, {bad} not converged: frame{'s' if len(frames) != 1 else ''} {shown}{tail}"


def _register_run(subparsers):
    p = subparsers.add_parser("run", help="simulate a scene and write its outputs")
    p.add_argument("scene", help="TOML scene file")
    p.add_argument("--device", default="cpu", help="Warp device: cpu, cuda, cuda:0, ... or auto (CUDA when present, else cpu; default cpu)")
    add_threads_option(p)
    p.add_argument("--precision", choices=("float32", "float64"), default="float64")
    p.add_argument("--frames", type=int, default=None, help="number of frames (default: the scene's [output].frames)")
    p.add_argument("--out", default=None, help="USD file (.usda/.usd/.usdc); default: the scene's [output].usd")
    p.add_argument("--preview", default=None, metavar="PNG",
                   help="after the run, draw 4 evenly spaced frames of the render surface and the colliders to this PNG, "
                        "one scale for all frames (needs the plot extra)")
    p.add_argument("--quiet", action="store_true", help="no progress lines (a bar with ETA on a terminal, else a line per frame)")
    p.add_argument("--verbose", action="store_true", help="show Warp's initialisation and compile messages (and debug logging)")
    p.add_argument("--require-convergence", action="store_true",
                   help="a step that does not converge is an error (exit 1, outputs kept marked incomplete), "
                        "as the scene's [integrator] require_convergence = true")
    p.add_argument("--resume", action="store_true",
                   help="continue a stopped run from its last checkpoint (next to its outputs), appending to its "
                        "outputs; refused when the scene's physics changed since")
    p.set_defaults(func=_cmd_run)


# ----------------------------------------------------------------------------- recover
def _cmd_recover(args) -> int:
    import os

    from warpfem.io.states import StatesError, recover_states, stream_directory

    paths = []
    for p in args.paths:
        if p.lower().endswith(".toml"):
            from warpfem.scenes import SceneError

            try:
                states = load(p).spec.output["states"]
            except SceneError as e:
                error(str(e))
                return EXIT_INVALID
            if not states:
                error(f"{p}: the scene writes no [output] states")
                return EXIT_INVALID
            paths.append(states)
        else:
            paths.append(p)
    code = EXIT_OK
    for p in paths:
        if not os.path.isdir(stream_directory(p)):
            print(f"{p}: nothing to recover (no {stream_directory(p)})" if os.path.exists(p) else
                  f"{p}: nothing to recover: neither it nor {stream_directory(p)} exists", flush=True)
            code = code if os.path.exists(p) else EXIT_INVALID
            continue
        try:
            k = recover_states(p)
        except (StatesError, OSError) as e:
            error(f"{p}: cannot recover it: {e}")
            return EXIT_FAILED
        print(f"{p}: recovered {k} frames from {stream_directory(p)}", flush=True)
    return code


def _register_recover(subparsers):
    p = subparsers.add_parser("recover", help="write the states .npz of a run that was killed, from its frame stream")
    p.add_argument("paths", nargs="+", metavar="OUT", help="a states .npz path (or a scene .toml: its [output] states)")
    p.set_defaults(func=_cmd_recover)


# ----------------------------------------------------------------------------- compare
def _cmd_compare(args) -> int:
    import json

    from warpfem.io.compare import CompareError, compare_runs, format_comparison

    if args.json is not None:
        from warpfem.io.outputs import OutputPathError, check_output_paths

        try:
            check_output_paths({"--json": args.json})
        except OutputPathError as e:
            error(str(e))
            return EXIT_INVALID
    try:
        result = compare_runs(args.a, args.b, prim=args.prim or None)
    except CompareError as e:
        error(str(e))
        return EXIT_INVALID
    print(format_comparison(result), flush=True)
    if args.json is not None:
        import os

        os.makedirs(os.path.dirname(os.path.abspath(args.json)), exist_ok=True)
        with open(args.json, "w") as f:
            json.dump(result, f, indent=2)
            f.write("\n")
    return EXIT_OK


def _register_compare(subparsers):
    p = subparsers.add_parser("compare", help="how far apart two runs are: RMS and max point distance over time")
    p.add_argument("a", metavar="A", help="reference run: a states .npz or a USD file (.usda/.usd/.usdc) written by run")
    p.add_argument("b", metavar="B", help="the other run, of the same kind as A")
    p.add_argument("--prim", action="append", default=None, metavar="PATH",
                   help="compare only this prim (USD path or name; states: positions or a body name); repeatable; "
                        "default: every animated prim both have, colliders excluded")
    p.add_argument("--json", default=None, metavar="OUT", help="also write the numbers to this JSON file")
    p.set_defaults(func=_cmd_compare)


# The command table: subcommand name -> "module:register function", in --help order.
COMMANDS = {
    "run": "warpfem.cli:_register_run",
    "describe": "warpfem.cli:_register_describe",
    "train": "warpfem.reduced.cli:register",
    "tradeoff": "warpfem.tradeoff.cli:register",
    "tune": "warpfem.tradeoff.cli:register_tune",
    "fit": "warpfem.diff.cli:register",
    "compare": "warpfem.cli:_register_compare",
    "recover": "warpfem.cli:_register_recover",
}

# Names kept for modules written against the earlier API (subcommands registered on import).
_check_device, _init_warp, _load, _err = check_device, init_warp, load, error
SUBCOMMANDS: list = []  # extra ``register`` functions added at run time with add_subcommand()


def add_subcommand(register) -> None:
    """Add a ``register(subparsers)`` that is not in :data:`COMMANDS` (for scripts and tests; a
    subcommand of the package belongs in the table). A function from a module of the table is ignored
    (it is registered through the table)."""
    module = getattr(register, "__module__", None)
    if any(spec.split(":")[0] == module for spec in COMMANDS.values()):
        return
    if register not in SUBCOMMANDS:
        SUBCOMMANDS.append(register)


def _resolve(spec: str):
    """``"module:function"`` -> the function; None when the module's optional dependency is missing."""
    import importlib

    module, _, func = spec.partition(":")
    try:
        mod = importlib.import_module(module)
    except ModuleNotFoundError as e:
        if e.name and module.startswith(e.name):  # the subcommand module itself is absent
            return None
        raise  # a real missing dependency inside it: report
    return getattr(mod, func)


def build_parser(argv=None) -> argparse.ArgumentParser:
    """The ``warpfem`` parser with every subcommand; given the command line ``argv`` whose first
    word is a subcommand of :data:`COMMANDS`, with that one only (the other subcommands' modules
    are not imported: ``warpfem run`` does not load the training, trade-off or fitting code)."""
    parser = argparse.ArgumentParser(prog="warpfem", description="Deformable-body FEM with NVIDIA Warp (CPU and CUDA).")
    parser.add_argument("--version", action="version", version=f"warpfem {_version()}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    specs = list(COMMANDS.values())
    if argv and argv[0] in COMMANDS:
        specs = [COMMANDS[argv[0]]]
    registers = [_resolve(spec) for spec in specs]
    for register in [r for r in registers if r is not None] + SUBCOMMANDS:
        register(sub)
    return parser


def add_threads_option(p) -> None:
    """The ``--threads N`` option of a subcommand that simulates (applied by :func:`main`)."""
    p.add_argument("--threads", default=None, metavar="N",
                   help="CPU threads for the kernels (default: WARPFEM_THREADS, else every core this process may use; "
                        "ignored on CUDA)")


def apply_threads(args) -> int | None:
    """Check ``WARPFEM_THREADS`` and apply ``--threads`` (a note and nothing else on a CUDA device).
    Returns None, or EXIT_INVALID after a one-line error."""
    import warnings

    from warpfem.threads import ThreadsError, get_threads, set_threads

    n = getattr(args, "threads", None)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            if n is not None and str(getattr(args, "device", "cpu")).strip().lower().startswith("cuda"):
                note(f"--threads {n} ignored: the kernels run on {args.device}, not on CPU threads")
                get_threads()
            elif n is not None:
                import os

                os.environ["WARPFEM_THREADS"] = str(set_threads(n))  # processes it starts use the same count
            else:
                get_threads()
        except ThreadsError as e:
            error(str(e).replace("threads=", "--threads ", 1) if n is not None else str(e))
            return EXIT_INVALID
    for w in caught:
        note(str(w.message).replace("threads=", "--threads ", 1))
    return None


class _StartupCollector:
    """The cyclic garbage collector during a command-line program's start-up (``main()`` with no
    ``argv``: the ``warpfem`` command, ``python -m warpfem``).

    Start-up makes ~200,000 long-lived objects (Warp's built-ins and kernels, the modules) and
    almost no cyclic garbage (~2,000 objects on the example scenes), so collecting them is wasted
    time: :meth:`pause` switches the collector off at the start, :meth:`resume` (before the first
    step, or before any other command's work) moves every object made so far to the permanent
    generation (``gc.freeze``: later collections skip them) and switches it on again, and
    :meth:`at_exit` freezes again so that the interpreter's last collections skip them too.
    ``main(argv)`` called from Python (tests, scripts) leaves the collector alone."""

    active = False

    @classmethod
    def pause(cls) -> None:
        import gc

        if gc.isenabled():
            gc.disable()
            cls.active = True

    @classmethod
    def resume(cls) -> None:
        if cls.active:
            import gc

            cls.active = False
            gc.freeze()
            gc.enable()

    @classmethod
    def at_exit(cls) -> None:
        import gc

        cls.resume()
        gc.freeze()


def main(argv=None) -> int:
    program = argv is None  # the command itself, not a call from Python: owns the process
    argv = sys.argv[1:] if argv is None else list(argv)
    if program:
        _StartupCollector.pause()
    try:
        # before anything (subcommand modules included) can initialise Warp: banner / module-load lines only with --verbose
        _configure_warp("--verbose" in argv)
        parser = build_parser(argv)
        args = parser.parse_args(argv)
        _configure_logging(getattr(args, "verbose", False), quiet=getattr(args, "quiet", False))
        if getattr(args, "func", None) is None:
            parser.print_help(sys.stderr)
            return EXIT_INVALID
        if apply_threads(args) is not None:
            return EXIT_INVALID
        if args.func is not _cmd_run:  # run resumes it itself, once the scene is built
            _StartupCollector.resume()
        from warpfem.progress import set_stage_writer

        # the stages of long preparations (meshing a surface file: which mesher, decimation, elapsed) on stderr
        previous = set_stage_writer(None if getattr(args, "quiet", False) else _stage_line)
        try:
            return int(args.func(args))
        finally:
            set_stage_writer(previous)
    finally:
        if program:
            _StartupCollector.at_exit()


def _stage_line(line) -> None:
    print(line, file=sys.stderr, flush=True)


if __name__ == "__main__":  # pragma: no cover
    # `python -m warpfem.cli`: the imported module's main, so the table resolves "warpfem.cli:..." to one module
    from warpfem.cli import main as _main

    sys.exit(_main())
