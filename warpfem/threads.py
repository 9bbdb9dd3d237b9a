"""How many CPU threads warpfem's kernel launches use, and the pool that runs them.

Warp runs a CPU kernel launch on one thread. warpfem splits the range of an element, vertex or
block kernel into contiguous chunks and launches them from a pool of Python threads (a Warp CPU
launch releases the GIL while the kernel runs), so a CPU simulation uses every core the process may
use. Results do not depend on the thread count: each output is written by exactly one chunk
(forces and Hessian blocks are gathered per vertex and per block in a fixed order), and sums are
made of partial sums over blocks whose size depends only on the range, added in a fixed order.

The count is, in order of precedence: :func:`set_threads` (the CLI's ``--threads N``), the
``WARPFEM_THREADS`` environment variable, the number of cores the process may run on
(``os.sched_getaffinity``). A count above that core count is clamped to it with a warning; zero,
negative or non-integer counts are an error. CUDA launches are not split.
"""

from __future__ import annotations

import os
import threading
import warnings

__all__ = ["ThreadsError", "available_cores", "get_threads", "set_threads", "parse_threads", "run_chunks"]

ENV = "WARPFEM_THREADS"


class ThreadsError(ValueError):
    """A thread count that is not a positive integer."""


def available_cores() -> int:
    """The number of CPU cores this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # platforms without affinity (macOS, Windows)
        return max(1, os.cpu_count() or 1)


def parse_threads(value, source: str = ENV) -> int:
    """A thread count from ``value`` (int or text), checked: a positive integer, clamped with a warning
    to :func:`available_cores`. ``source`` names where it came from in the one-line error."""
    text = str(value).strip()
    try:
        n = int(text)  # "2.5", "two", "" and True are refused
    except (TypeError, ValueError):
        raise ThreadsError(f"{source}={text!r}: the thread count must be a positive integer") from None
    if n < 1:
        raise ThreadsError(f"{source}={n}: the thread count must be a positive integer (at least 1)")
    cores = available_cores()
    if n > cores:
        warnings.warn(f"{source}={n} is more than the {cores} cores this process may use: using {cores} threads",
                      RuntimeWarning, stacklevel=3)
        n = cores
    return n


_state = {"set": None, "env": None, "env_value": None}
_lock = threading.Lock()


def set_threads(n=None) -> int:
    """Use ``n`` CPU threads for kernel launches from now on (None: back to ``WARPFEM_THREADS`` or
    the core count). Returns the count in use. Raises :class:`ThreadsError` for a count that is not a
    positive integer; a count above the core count is clamped with a warning."""
    _state["set"] = None if n is None else parse_threads(n, "threads")
    _pool_resize()
    return get_threads()


def get_threads() -> int:
    """The number of CPU threads kernel launches use now."""
    n = _state["set"]
    if n is not None:
        return n
    env = os.environ.get(ENV)
    if env is None or env.strip() == "":
        return available_cores()
    if env != _state["env_value"]:  # parsed (and warned about) once per value
        _state["env"], _state["env_value"] = parse_threads(env, ENV), env
    return _state["env"]


# -- the pool ---------------------------------------------------------------------------------------
class _Worker:
    """One pool thread: runs the functions handed to it, one at a time.

    Signalled through two plain locks used as binary semaphores (``go`` released by the launching
    thread to start a function, ``done`` released by the worker when it has run): a lock's acquire
    and release are single C calls, where a ``threading.Event``'s set and wait run a condition
    variable's Python code (some microseconds per dispatch, thousands of dispatches per step)."""

    def __init__(self):
        self.go = threading.Lock()
        self.done = threading.Lock()
        self.go.acquire()
        self.done.acquire()
        self.fn = None
        self.error = None
        self.thread = threading.Thread(target=self._loop, daemon=True, name="warpfem-launch")
        self.thread.start()

    def start(self, fn):
        self.fn, self.error = fn, None
        self.go.release()

    def _loop(self):
        go, done = self.go, self.done
        while True:
            go.acquire()
            fn = self.fn
            if fn is None:
                return
            try:
                fn()
            except BaseException as e:  # noqa: BLE001 -- re-raised in the launching thread
                self.error = e
            done.release()


_workers: list = []


def _after_fork_in_child():
    """A forked process has none of its parent's pool threads: start from an empty pool."""
    global _lock
    _workers.clear()
    _lock = threading.Lock()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_after_fork_in_child)


def _pool_resize():
    with _lock:
        try:
            want = max(0, get_threads() - 1) if _workers else 0
        except ThreadsError:  # a bad WARPFEM_THREADS: said at the next launch
            want = 0
        while len(_workers) > want:
            _workers.pop().start(None)


def run_chunks(fns) -> None:
    """Run the callables ``fns`` at once, the first in this thread and each other in a pool thread;
    return when all are done (the first exception raised by one is raised here)."""
    if len(fns) == 1:
        fns[0]()
        return
    with _lock:
        while len(_workers) < len(fns) - 1:
            _workers.append(_Worker())
        used = _workers[:len(fns) - 1]
        for w, fn in zip(used, fns[1:]):
            w.start(fn)
        first = None
        try:
            fns[0]()
        except BaseException as e:  # noqa: BLE001
            first = e
        for w in used:
            w.done.acquire()
        errors = [first] + [w.error for w in used]
        for e in errors:
            if e is not None:
                raise e
