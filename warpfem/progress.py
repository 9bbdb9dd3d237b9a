"""Progress of the long command-line jobs (frames of ``run``, training frames, ``tradeoff``
configurations) with elapsed time and an ETA.

On a terminal (stderr is a TTY) a live bar is drawn on stderr with ``rich``; otherwise (CI, pipes,
files) one plain line per unit is written (to stdout by default)::

    [######..................] frame 3/12  t = 0.1500 s  newton 3  cg 41  0.012 s  elapsed 0:00:01  ETA 0:00:03

The ETA is (units left) x (mean time per unit after the first): the first unit usually includes
Warp's kernel compilation and would inflate it. Time spent compiling (:class:`CompileWatch`, given to
:meth:`Progress.exclude`) is left out of the ETA too, so the estimate after the first unit is not
inflated either.
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
import time

__all__ = ["Progress", "format_duration", "CompileWatch", "COMPILING_NOTICE", "Stages", "set_stage_writer"]

COMPILING_NOTICE = "compiling kernels (first run only) ..."


def format_duration(seconds) -> str:
    """``H:MM:SS`` (``--:--:--`` for an unknown / infinite time)."""
    if seconds is None or seconds != seconds or seconds == float("inf"):
        return "-:--:--"
    s = int(round(max(seconds, 0.0)))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"


class Progress:
    """``update(done, detail)`` after each of ``total`` units; ``note(line)`` for a line that must stay
    visible (a warning about a unit); ``close()`` (or use as a context manager) at the end.

    Args:
        total: number of units.
        unit: what a unit is called in the plain lines ("frame", "configuration", ...).
        enabled: False: nothing is shown (``--quiet``).
        bar: draw a live bar (default: when stderr is a terminal).
        write: where plain lines go (default: print to stdout, flushed).
        clock: time source (seconds), for tests.
        started: ``clock()`` value at which the work began (default: now).
    """

    WIDTH = 24

    def __init__(self, total, *, unit="frame", enabled=True, bar=None, write=None, clock=time.perf_counter,
                 started=None):
        self.total = max(int(total), 0)
        self.unit = unit
        self.enabled = enabled
        self._clock = clock
        self._write = write or (lambda line: print(line, flush=True))
        self._t0 = clock() if started is None else started
        self._t_first = None  # time at which the first unit finished
        self._excluded = 0.0  # seconds not spent on the units themselves (kernel compilation)
        self._excluded_at_first = 0.0
        self._live = None
        if enabled and (sys.stderr.isatty() if bar is None else bar):
            self._live = self._start_bar()

    @property
    def drawing_bar(self) -> bool:
        """True while a live bar is drawn (plain lines otherwise)."""
        return self._live is not None

    # -- time ---------------------------------------------------------------------------------------
    def elapsed(self) -> float:
        return self._clock() - self._t0

    def eta(self, done) -> float:
        """Seconds left after ``done`` units (inf when unknown)."""
        left = self.total - done
        if left <= 0:
            return 0.0
        now = self._clock()
        if done >= 2 and self._t_first is not None:
            per = (now - self._t_first - (self._excluded - self._excluded_at_first)) / (done - 1)
        elif done >= 1:
            per = (now - self._t0 - self._excluded) / done
        else:
            return float("inf")
        return max(per, 0.0) * left

    def exclude(self, seconds) -> None:
        """Leave ``seconds`` (already elapsed, e.g. compiling kernels) out of the ETA."""
        self._excluded += max(float(seconds), 0.0)

    # -- output -------------------------------------------------------------------------------------
    def _start_bar(self):
        try:
            from rich.console import Console
            from rich.progress import (BarColumn, MofNCompleteColumn, Progress as RichProgress, TextColumn,
                                       TimeElapsedColumn, TimeRemainingColumn)
        except ImportError:  # rich is a declared dependency; plain lines if it is broken or missing
            return None
        live = RichProgress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                            TimeElapsedColumn(), TextColumn("ETA"), TimeRemainingColumn(),
                            TextColumn("{task.fields[detail]}"), console=Console(file=sys.stderr),
                            transient=False)
        live.start()
        self._task = live.add_task(self.unit + "s", total=self.total or None, detail="")
        return live

    def line(self, done, detail="") -> str:
        """The plain line for ``done`` units."""
        n = self.WIDTH * done // self.total if self.total else self.WIDTH
        bar = "#" * n + "." * (self.WIDTH - n)
        mid = f"  {detail}" if detail else ""
        return (f"[{bar}] {self.unit} {done}/{self.total}{mid}  elapsed {format_duration(self.elapsed())}  "
                f"ETA {format_duration(self.eta(done))}")

    def update(self, done, detail="") -> None:
        if done >= 1 and self._t_first is None:
            self._t_first = self._clock()
            self._excluded_at_first = self._excluded
        if not self.enabled:
            return
        if self._live is not None:
            self._live.update(self._task, completed=done, detail=detail)
        else:
            self._write(self.line(done, detail))

    def note(self, text) -> None:
        """A line that stays (above the bar on a terminal; a plain line otherwise)."""
        if not self.enabled:
            return
        if self._live is not None:
            self._live.console.print(text, markup=False, highlight=False)
        else:
            self._write(text)

    def close(self) -> None:
        if self._live is not None:
            self._live.stop()
            self._live = None

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


class CompileWatch:
    """Context manager that notices Warp compiling a module (a kernel-cache miss) while it is active.

    ``on_start()`` is called once, before the first compilation (say "compiling kernels (first run
    only)"); ``on_compiled(seconds)`` after each module load that compiled, with the whole load's
    time (code generation, compiler, hashing, loading the binary; e.g. :meth:`Progress.exclude`).
    ``seconds`` and ``modules`` total them. It wraps Warp's ``Module.load`` and ``Module._compile``
    for the duration (process-wide hooks, restored on exit); with a Warp that has no such methods it
    notices nothing.
    """

    def __init__(self, on_start=None, on_compiled=None):
        self.on_start, self.on_compiled = on_start, on_compiled
        self.seconds = 0.0
        self.modules = 0
        self._started = False
        self._saved = []  # (class, name, original function)
        self._depth = 0
        self._compiled_in_load = False

    @staticmethod
    def _module_class():
        try:
            from warp._src.context import Module
        except ImportError:
            return None
        ok = all(callable(getattr(Module, name, None)) for name in ("_compile", "load"))
        return Module if ok else None

    @staticmethod
    def _will_compile(args, kwargs) -> bool:
        """A cache miss ahead: the binary ``output_dir/output_name`` the load asks for is absent
        (False when the call does not say: the call's result decides then)."""
        out_dir = kwargs.get("output_dir", args[1] if len(args) > 1 else None)
        name = kwargs.get("output_name", args[2] if len(args) > 2 else None)
        if out_dir is None or name is None:
            return False
        return not os.path.exists(os.path.join(os.fspath(out_dir), name))

    def _notice_start(self):
        if not self._started:
            self._started = True
            if self.on_start is not None:
                self.on_start()

    def _finished(self, seconds):
        self.seconds += seconds
        self.modules += 1
        if self.on_compiled is not None:
            self.on_compiled(seconds)

    def __enter__(self):
        cls = self._module_class()
        if cls is None:
            return self
        compile_, load = cls.__dict__["_compile"], cls.__dict__["load"]

        def _compile(module, *args, **kwargs):
            if self._will_compile(args, kwargs):
                self._notice_start()
            compiled = compile_(module, *args, **kwargs)
            if compiled:
                self._notice_start()
                self._compiled_in_load = True
            return compiled

        def _load(module, *args, **kwargs):
            outer = self._depth == 0
            if outer:
                self._compiled_in_load = False
            self._depth += 1
            t0 = time.perf_counter()
            try:
                return load(module, *args, **kwargs)
            finally:
                self._depth -= 1
                if outer and self._compiled_in_load:
                    self._compiled_in_load = False
                    self._finished(time.perf_counter() - t0)

        self._saved = [(cls, "_compile", compile_), (cls, "load", load)]
        cls._compile, cls.load = _compile, _load
        return self

    def __exit__(self, *exc):
        for cls, name, fn in self._saved:
            setattr(cls, name, fn)
        self._saved = []
        return False


# ------------------------------------------------------------------------------------- stages
_stage_writer = None


def set_stage_writer(write):
    """Where the stage lines of long preparations (meshing a surface file) go: a callable taking one
    line, or None: silent, the default (library use, tests). The command line sets it to stderr
    unless ``--quiet``. Returns the previous writer."""
    global _stage_writer
    previous, _stage_writer = _stage_writer, write
    return previous


class Stages:
    """One line per stage of a job that has no unit count (meshing a surface file)::

        meshing scan.obj [0:00:00] checking the 111456-triangle surface
        meshing scan.obj [0:00:03] decimating to 1776 triangles (fast-simplification)
        meshing scan.obj [0:00:04] TetGen: filling it, edge bound 0.0087 (try 1 of 4)
        meshing scan.obj [0:00:05] 19740 tets (target 20000, -1.3 %)

    The bracket is the time since the job began. A stage still running after ``heartbeat`` seconds
    gets a "still ..." line every ``heartbeat`` seconds (a mesher is one long native call). Lines go to
    ``write`` (default: the writer of :func:`set_stage_writer`, silent when none).
    """

    def __init__(self, job, *, write=None, clock=time.perf_counter, heartbeat=15.0):
        self.job = job
        self._write = write if write is not None else _stage_writer
        self._clock = clock
        self._t0 = clock()
        self.heartbeat = heartbeat

    @property
    def enabled(self) -> bool:
        return self._write is not None

    def elapsed(self) -> float:
        return self._clock() - self._t0

    def note(self, text) -> None:
        if self._write is not None:
            self._write(f"{self.job} [{format_duration(self.elapsed())}] {text}")

    @contextlib.contextmanager
    def stage(self, text):
        """``with stages.stage("TetGen: ..."):`` a line now; "still <text>" lines while it runs."""
        self.note(text)
        timer = None
        if self._write is not None and self.heartbeat:
            started = self._clock()
            stop = threading.Event()

            def beat():
                while not stop.wait(self.heartbeat):
                    self.note(f"still {text} ({format_duration(self._clock() - started)} in this stage)")

            timer = threading.Thread(target=beat, daemon=True)
            timer.start()
        try:
            yield
        finally:
            if timer is not None:
                stop.set()
                timer.join()
