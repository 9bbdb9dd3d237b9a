"""Declare the float32 and float64 overloads of generic kernels up front.

Warp recompiles a whole module each time a generic kernel meets a new argument type, so a module
whose kernels were instantiated lazily compiled once per new overload. Declaring both precisions
at import time makes each module compile once (per device) with every variant in it.
"""

from __future__ import annotations

import warp as wp

from warpfem.kernels.structs import STRUCT_TYPES
from warpfem.transfer import strict_device

PRECISION_TYPES = tuple({"s": s, "v": v, "m": m, "v4": v4, **STRUCT_TYPES[s]}
                        for s, v, m, v4 in ((wp.float32, wp.vec3, wp.mat33, wp.vec4), (wp.float64, wp.vec3d, wp.mat33d, wp.vec4d)))


def both_precisions(**roles):
    """Kernel decorator: ``roles`` maps each generic argument to "s" (scalar value), "s[]", "v[]",
    "m[]", "v4[]" (1-d arrays of scalar, vec3, mat33, vec4), "s[,]" or "v[,]" (2-d scalar / vec3 arrays), or a
    struct of :mod:`warpfem.kernels.structs`: "qp" (``QuadraturePoints32/64``), "mat"
    (``MaterialParams32/64``), "tets" (``WarpedTets32/64``)."""

    def decorate(kernel):
        for types in PRECISION_TYPES:
            arg_types = {}
            for arg in kernel.adj.args:
                role = roles.get(arg.label)
                if role is None:
                    arg_types[arg.label] = arg.type
                elif role in ("s", "qp", "mat", "tets"):
                    arg_types[arg.label] = types[role]
                elif role in ("s[,]", "v[,]"):
                    arg_types[arg.label] = wp.array2d(dtype=types[role[0]])
                else:
                    arg_types[arg.label] = wp.array(dtype=types[role[:-2]])
            wp.overload(kernel, arg_types)
        return kernel

    return decorate


_OVERLOAD_CACHE: dict = {}


def _type_key(a):
    dt = getattr(a, "dtype", None)
    if dt is not None and hasattr(a, "ndim"):
        return (dt, a.ndim)
    return type(a)


_LAUNCH_CACHE: dict = {}
_WARP_SCALARS = (wp.float32, wp.float64, wp.int32, wp.int64, wp.uint32, wp.uint64, wp.float16)
_IMMUTABLE = (int, float, bool)
_LAUNCH_CACHE_SIZE = 1024


#: launches made through :func:`launch` (and counted by solvers that replay recorded launches):
#: the simulators report the difference over a step as ``SolveStats.launches``
COUNTERS = {"launches": 0, "split": 0}


class _Split:
    """How :func:`launch` may split a kernel's range across CPU threads (:func:`splittable`)."""

    __slots__ = ("kind", "min_chunk", "acc", "slot", "n_add", "n_max", "n_min", "when", "written")

    def __init__(self, kind, min_chunk, acc, slot, n_add, n_max, n_min, when, written=None):
        self.kind, self.min_chunk, self.acc, self.slot, self.n_add, self.n_max = kind, min_chunk, acc, slot, n_add, n_max
        self.n_min, self.when, self.written = n_min, when, written


#: kernel -> _Split: the kernels whose launches :func:`launch` splits across CPU threads
SPLIT: dict = {}
#: a reduction's range is cut into at most this many blocks of partial sums (the block size depends
#: only on the range, so the sums do not depend on the thread count)
REDUCE_ROWS = 64
REDUCE_BLOCK_MIN = 1024
#: None: each kernel's own ``min_chunk``; an int: that for every kernel (tests split tiny ranges with it)
MIN_CHUNK = None
#: where a reduction's float64 sums are made in a fixed order from one row per index (``_ordered_reduce``):
#: "device" on devices other than the CPU (whose atomics add in no fixed order; the CPU's rows of
#: partial sums are already in a fixed order), "always" on the CPU too (tests), "never": atomics
ORDERED_SUMS = "device"
#: rows summed per thread and pass of the fixed-order tree
TREE_BLOCK = 256


def _min_chunk(spec) -> int:
    return max(1, spec.min_chunk if MIN_CHUNK is None else int(MIN_CHUNK))


def _chunk_bounds(n, threads, spec, rows=None, block=None):
    """The chunks' bounds [b_0 = 0, ..., b_parts = n] of a split launch over n items on ``threads``
    threads: contiguous ranges of at least the kernel's minimal chunk; a reduction (``rows`` partial
    rows of ``block`` items) splits on whole rows, so its partial sums do not depend on the split."""
    if rows is None:
        parts = max(1, min(threads, n // _min_chunk(spec)))
        return [n * c // parts for c in range(parts + 1)]
    parts = max(1, min(threads, rows, n // _min_chunk(spec)))
    return [min(n, block * (rows * c // parts)) for c in range(parts + 1)]


def splittable(kind: str, min_chunk: int = 4096, acc: int = -1, slot: int = -1, n_add: int = 0, n_max: int = 0,
               n_min: int = 0, when: int = -1, written=None):
    """Declare how :func:`launch` splits a kernel's 1-d range across CPU threads (CUDA launches are
    never split). ``kind``:

    - ``"start"``: the kernel's last argument is ``start: int``, added to ``wp.tid()``; every output
      is written by one index only (the gather kernels, the per-point slot kernels).
    - ``"reduce"``: the last three are ``start, row_block, row_stride``; the kernel adds its
      float64 sums into ``acc[slot + (i // row_block) * row_stride + j]`` (``acc``, ``slot``: the
      positions of those arguments), the first ``n_add`` of them sums, the next ``n_max`` maxima and
      the next ``n_min`` minima.
      On the CPU a range longer than ``REDUCE_BLOCK_MIN`` adds into rows of partial sums (one per
      block, the block size a function of the range only) that are then added in row order into
      ``acc``: the same numbers whatever the thread count.
    - ``"view"``: element-wise, every array argument indexed by the thread index only: each chunk
      is launched on views of the arrays.

    ``min_chunk``: the fewest indices worth a thread of their own (a chunk's launch costs some
    microseconds). ``when``: the position of an int argument that must be non-zero for a split (a
    kernel that scatters with atomics otherwise). ``written``: for a reduction that adds one sum
    into one entry of ``acc``, a function of the launch's arguments giving that entry; a
    :class:`RecordedLaunch` on the fixed-order path then gives each index one float64 of scratch
    instead of a row as long as ``acc``."""

    def decorate(kernel):
        SPLIT[kernel] = _Split(kind, int(min_chunk), acc, slot, n_add, n_max, n_min, when, written)
        return kernel

    return decorate


_SCRATCH: dict = {}
_VIEWS: dict = {}


def _scratch(device, size):
    key = (str(device), size)
    a = _SCRATCH.get(key)
    if a is None:
        if len(_SCRATCH) > 32:
            _SCRATCH.clear()
        a = _SCRATCH[key] = wp.zeros(size, dtype=wp.float64, device=device)
    return a


def _view(a, lo, hi):
    key = (id(a), lo, hi)
    v = _VIEWS.get(key)
    if v is None:
        if len(_VIEWS) > 4096:
            _VIEWS.clear()
        v = _VIEWS[key] = (a[lo:hi], a)  # the base kept alive with its view: its id is not reused
    return v[0]


_APIC_QUERY = []


def _cpu_capturing(device) -> bool:
    if not _APIC_QUERY:  # Warp's query, looked up once (an import per split launch cost microseconds)
        try:
            from warp._src.context import _get_apic_capture_for_device

            _APIC_QUERY.append(_get_apic_capture_for_device)
        except Exception:  # noqa: BLE001 -- a Warp without the query: assume not capturing
            _APIC_QUERY.append(None)
    query = _APIC_QUERY[0]
    if query is None:
        return False
    try:
        return query(device if isinstance(device, wp.Device) else wp.get_device(device)) is not None
    except Exception:  # noqa: BLE001
        return False


def cpu_capturing(device) -> bool:
    """Whether launches on ``device`` are being recorded into a CPU graph now (then no split)."""
    return _cpu_capturing(device)


def split_min_chunk(kernel) -> int:
    """The fewest indices a chunk of a split launch of ``kernel`` gets (its ``min_chunk``, or
    ``MIN_CHUNK`` where set): for callers that cut their own work in parts as :func:`launch` would."""
    return _min_chunk(SPLIT[kernel])


def launch(kernel, dim, inputs, device):
    """``wp.launch`` with less host overhead for the solver loops, split across CPU threads.

    The concrete overload of a generic kernel is looked up once per argument-type signature (Warp
    infers it on every launch of a generic kernel, about 4x the rest of the launch on the CPU), and
    the launch itself is a recorded :class:`warp.Launch` per (overload, dim, device) whose
    parameters are replaced (about half the cost of a fresh launch), only those that are not the
    same objects as in the previous launch of that entry (kernel structs, ``kernels.structs``,
    included: the same instance is not re-packed). Measured in
    kernels_bench/bench_solver_overhead.py.

    A kernel declared :func:`splittable` gets its trailing range arguments here (callers pass the
    others); on the CPU its range is cut into contiguous chunks run at once by the pool of
    :mod:`warpfem.threads` (``warpfem.set_threads``, ``WARPFEM_THREADS``), with results that do not
    depend on the thread count. Inside a CPU graph capture the chunks are recorded one after the
    other."""
    spec = SPLIT.get(kernel)
    if spec is None:
        _prepare(kernel, dim, inputs, device, None)()
        return
    n = int(dim)
    inputs = list(inputs)
    dev = wp.get_device(device)
    if spec.kind == "reduce" and n > 1 and _ordered(dev):
        _ordered_reduce(kernel, n, inputs, spec, dev, device)
        return
    if not dev.is_cpu or n <= 0:
        if spec.kind == "start":
            inputs.append(0)
        elif spec.kind == "reduce":
            inputs += [0, max(n, 1), 0]
        _prepare(kernel, dim, inputs, device, None)()
        return
    from warpfem.threads import get_threads, run_chunks

    threads = get_threads() if spec.when < 0 or inputs[spec.when] else 1
    kind = spec.kind
    if kind == "reduce":
        block = max(REDUCE_BLOCK_MIN, -(-n // REDUCE_ROWS))
        rows = -(-n // block)
        bounds = _chunk_bounds(n, threads, spec, rows=rows, block=block)
        width = spec.n_add + spec.n_max + spec.n_min
        if rows > 1:
            from warpfem.kernels import linalg as LK

            acc, slot = inputs[spec.acc], int(inputs[spec.slot])
            part = _scratch(dev, rows * width)
            if spec.n_max or spec.n_min:  # sums from 0, maxima from -inf, minima from +inf
                _prepare(LK.init_rows_kernel, rows * width, [part, width, spec.n_add, spec.n_max], device, None)()
            else:
                part.zero_()
            inputs[spec.acc], inputs[spec.slot] = part, 0
            tail = [block, width]
        else:
            tail = [max(n, 1), 0]
    else:
        bounds = _chunk_bounds(n, threads, spec)
    fns = []
    for c in range(len(bounds) - 1):
        lo, hi = bounds[c], bounds[c + 1]
        if hi <= lo:
            continue
        if kind == "view":
            args = [_view(v, lo, hi) if isinstance(v, wp.array) else v for v in inputs]
        elif kind == "start":
            args = inputs + [lo]
        else:
            args = inputs + [lo] + tail
        fns.append(_prepare(kernel, hi - lo, args, device, (lo, hi) if len(bounds) > 2 else None))
    if len(fns) > 1:
        COUNTERS["split"] += 1
        COUNTERS["launches"] -= len(fns) - 1  # counted as the one launch it stands for
        if _cpu_capturing(dev):
            for f in fns:
                f()
        else:
            run_chunks(fns)
    elif fns:
        fns[0]()
    if kind == "reduce" and rows > 1:
        _prepare(LK.reduce_rows_kernel, width, [part, rows, width, spec.n_add, spec.n_max, acc, slot], device, None)()


def launch_phases(phases, device):
    """Run sequences of CPU launches, each thread its own, with no barrier inside a phase.

    ``phases``: a list of phases, each a list (one entry per thread) of sequences of
    ``(kernel, dim, inputs)`` with every argument given (a splittable kernel's ``start`` included).
    The threads of a phase run their sequences at once, each in order; a phase starts when the
    previous one has ended. For work cut so that what a thread's later launch reads was written by
    its own earlier launches (``forms.ElasticForm``'s force: each thread computes the points its
    vertices gather), one dispatch replaces one per launch. Counted as one launch per position of
    the longest sequence of each phase (a split launch where more than one thread runs). Inside a
    CPU graph capture everything is recorded in order on this thread."""
    dev = wp.get_device(device)
    capturing = _cpu_capturing(dev)
    from warpfem.threads import run_chunks

    for p, phase in enumerate(phases):
        c0 = COUNTERS["launches"]
        fns = [[_prepare(k, dim, list(inputs), device, ("phase", p, t, j)) for j, (k, dim, inputs) in enumerate(seq)]
               for t, seq in enumerate(phase) if seq]
        COUNTERS["launches"] = c0 + max((len(f) for f in fns), default=0)
        if len(fns) > 1:
            COUNTERS["split"] += 1
        if capturing or len(fns) == 1:
            for seq in fns:
                for f in seq:
                    f()
        elif fns:
            run_chunks([_run_all(seq) for seq in fns])


def _run_all(seq):
    if len(seq) == 1:
        return seq[0]

    def run():
        for f in seq:
            f()

    return run


def _ordered(dev) -> bool:
    return ORDERED_SUMS == "always" or (ORDERED_SUMS == "device" and not dev.is_cpu)


def ordered_sums(device) -> bool:
    """Whether float64 sums on ``device`` are made in a fixed order from one row per index
    (``ORDERED_SUMS``: devices other than the CPU by default) rather than with atomics."""
    return _ordered(wp.get_device(device))


def ordered_sum_launches(rows, n, acc, slot, device):
    """Recorded launches (:class:`RecordedLaunch`, called in order) that add ``rows[0] + ... +
    rows[n - 1]`` into ``acc[slot]`` in a fixed order: the tree of :func:`_ordered_reduce` (passes
    of TREE_BLOCK rows, then the last rows in order), its scratch allocated here. For solvers whose
    kernels add one value per index into a row array of their own (``rows``, zeroed before: a
    view may start at the slot the kernel writes)."""
    from warpfem.kernels import linalg as LK

    steps, (passes, last), src = [], _tree_passes(n), rows
    for r in passes:
        groups = -(-r // TREE_BLOCK)
        dst = wp.zeros(groups, dtype=wp.float64, device=device)
        steps.append(RecordedLaunch(LK.reduce_tree_kernel, groups, [src, r, 1, 1, 0, TREE_BLOCK, dst], device,
                                    split=False))
        src = dst
    steps.append(RecordedLaunch(LK.reduce_rows_kernel, 1, [src, last, 1, 1, 0, acc, int(slot)], device, split=False))
    return steps


def _tree_passes(rows):
    """The row counts of the fixed-order tree's passes, from ``rows`` down to at most TREE_BLOCK."""
    out = []
    while rows > TREE_BLOCK:
        out.append(rows)
        rows = -(-rows // TREE_BLOCK)
    return out, rows


def _ordered_reduce(kernel, n, inputs, spec, dev, device):
    """A reduction with its float64 results in a fixed order on any device: index i adds into a row
    of its own (``row_block`` 1), then the rows are combined by a tree of passes, each thread
    summing TREE_BLOCK consecutive rows in order (``reduce_tree_kernel``), and the last rows are
    added into ``acc`` in row order (``reduce_rows_kernel``): the same bits run to run, whatever
    order the device's threads run in. Costs n x width float64 of scratch and a few launches."""
    from warpfem.kernels import linalg as LK

    width = spec.n_add + spec.n_max + spec.n_min
    acc, slot = inputs[spec.acc], int(inputs[spec.slot])
    part = _scratch(dev, n * width)
    if spec.n_max or spec.n_min:
        _prepare(LK.init_rows_kernel, n * width, [part, width, spec.n_add, spec.n_max], device, None)()
    else:
        part.zero_()
    inputs[spec.acc], inputs[spec.slot] = part, 0
    _prepare(kernel, n, inputs + [0, 1, width], device, None)()
    passes, rows = _tree_passes(n)
    src = part
    for r in passes:
        groups = -(-r // TREE_BLOCK)
        dst = _scratch(dev, groups * width)
        _prepare(LK.reduce_tree_kernel, groups * width, [src, r, width, spec.n_add, spec.n_max, TREE_BLOCK, dst],
                 device, None)()
        src = dst
    _prepare(LK.reduce_rows_kernel, width, [src, rows, width, spec.n_add, spec.n_max, acc, slot], device, None)()


def _prepare(kernel, dim, inputs, device, tag):
    """The recorded launch of ``kernel`` over ``inputs``, its parameters set, as a callable that
    runs it (see :func:`launch`); ``tag`` tells the chunks of one split launch apart."""
    COUNTERS["launches"] += 1
    if kernel.is_generic:
        key = (kernel, *map(_type_key, inputs))
        ovl = _OVERLOAD_CACHE.get(key)
        if ovl is None:
            try:
                ovl = kernel._add_normalized_overload(kernel.infer_argument_types(inputs))
            except AttributeError:  # a Warp without these internals: the plain (slower) launch
                ovl = kernel
            _OVERLOAD_CACHE[key] = ovl
        kernel = ovl
    # one entry per set of array arguments (by identity: an entry keeps its arrays alive, so their
    # ids are not reused while it exists): a kernel launched on alternating arrays (the two states,
    # the gradient and its trial buffer) finds its arrays already packed
    lkey = (kernel, dim if isinstance(dim, tuple) else (dim,), str(device), tag,
            *[id(v) for v in inputs if isinstance(v, wp.array)])
    entry = _LAUNCH_CACHE.get(lkey)
    if entry is not None:
        cmd, module, exec_key, last = entry
        # valid while the module was not modified (new overloads) or reloaded since it was recorded
        if module.hashers and module.execs.get(exec_key) is cmd.module_exec:
            # re-pack only the arguments that are not the very objects of the last launch: arrays
            # (the recorded launch holds them alive; what is packed is their pointer and shape),
            # immutable Python scalars, and struct instances whose packed parameter is their own
            # C buffer (Warp packs a struct as ``instance._ctype``, the buffer its field setters
            # write, so a field assigned in place is already what the launch reads). Anything else
            # (a Warp scalar, an unknown object) is re-packed.
            params = cmd.params
            for i, v in enumerate(inputs):
                lv = last[i]
                if v is lv and (isinstance(v, wp.array) or type(v) in _IMMUTABLE
                                or getattr(v, "_ctype", None) is params[i + 1]):
                    continue
                # a Warp scalar (a new object per launch, e.g. ``wp.float64(s)``) of the value packed last
                if type(v) is type(lv) and isinstance(v, _WARP_SCALARS) and v.value == lv.value:
                    continue
                cmd.set_param_at_index(i, v)
                last[i] = v
            return cmd.launch
    cmd = wp.launch(kernel, dim=dim, inputs=inputs, device=device, record_cmd=True)
    if cmd is None:  # nothing to launch (e.g. dim 0)
        return _nothing
    try:
        module = kernel.module
        exec_key = next(k for k, v in module.execs.items() if v is cmd.module_exec)
        if len(_LAUNCH_CACHE) >= _LAUNCH_CACHE_SIZE:  # a recorded launch keeps its last arrays alive
            _LAUNCH_CACHE.clear()
        _LAUNCH_CACHE[lkey] = (cmd, module, exec_key, list(inputs))
    except (AttributeError, StopIteration):  # a Warp without these internals: no caching
        pass
    return cmd.launch


def _nothing():
    pass


# Warp versions whose CPU kernel entry point (forward(bounds*, args*)) and launch internals the
# direct call of RecordedLaunch was checked against (tests/test_reduced_step.py compares it with
# Warp's own launch); any other version replays through Warp's public Launch.launch().
_DIRECT_CPU_CALL_WARP = {(1, 19)}


class RecordedLaunch:
    """One launch whose arguments never change, recorded once and replayed (``Launch.launch()``:
    about 4 us per call on the CPU against 10-20 us for :func:`launch`, which looks its entry up
    by the arguments' types every time; on the CPU the kernel's entry point is then called directly
    with its argument struct packed once, ~1.5 us). For the reduced simulator's per-iteration kernel.
    Re-recorded when the kernel's module was reloaded since (as :func:`launch` checks)."""

    def __init__(self, kernel, dim, inputs, device, split=True):
        spec = SPLIT.get(kernel) if split else None
        self._spec = spec if spec is not None and wp.get_device(device).is_cpu and isinstance(dim, int) else None
        inputs = list(inputs)
        self._reduce = None
        self._ordered = None
        if (spec is not None and spec.kind == "reduce" and isinstance(dim, int) and dim > 1
                and _ordered(wp.get_device(device)) and spec.written is not None):
            # one sum into one entry s of the accumulator: index i adds into part[s + i] (row_block
            # 1, row_stride 1), part[s:s + n] summed into acc[s] by the fixed-order tree
            n = int(dim)
            acc = inputs[spec.acc]
            s = int(spec.written(inputs))
            part = wp.zeros(n + acc.shape[0], dtype=wp.float64, device=device)
            inputs[spec.acc] = part
            inputs += [0, 1, 1]
            self._ordered = (part, ordered_sum_launches(part[s:s + n], n, acc, s, device))
            self._spec = None
        elif (spec is not None and spec.kind == "reduce" and isinstance(dim, int) and dim > 1
                and _ordered(wp.get_device(device))):
            # one row per index, combined by the fixed-order tree (``_ordered_reduce``): the whole
            # accumulator array per row, sums only (the recorded reductions are dot products)
            n = int(dim)
            acc = inputs[spec.acc]
            width = acc.shape[0]
            part = wp.zeros(n * width, dtype=wp.float64, device=device)
            inputs[spec.acc] = part
            inputs += [0, 1, width]
            steps, (passes, rows), src = [], _tree_passes(n), part
            from warpfem.kernels import linalg as LK

            for r in passes:
                groups = -(-r // TREE_BLOCK)
                dst = wp.zeros(groups * width, dtype=wp.float64, device=device)
                steps.append(RecordedLaunch(LK.reduce_tree_kernel, groups * width,
                                            [src, r, width, width, 0, TREE_BLOCK, dst], device, split=False))
                src = dst
            steps.append(RecordedLaunch(LK.reduce_rows_kernel, width, [src, rows, width, width, 0, acc, 0], device,
                                        split=False))
            self._ordered = (part, steps)
            self._spec = None
        elif spec is not None and spec.kind == "reduce":
            # the whole accumulator array in rows of partial sums (sums only), added in row order
            n = int(dim)
            block = max(REDUCE_BLOCK_MIN, -(-n // REDUCE_ROWS))
            rows = -(-n // block)
            if self._spec is None or rows <= 1:
                inputs += [0, max(n, 1), 0]  # not split: the whole range into the accumulator itself
                self._spec = None
            else:
                from warpfem.kernels import linalg as LK

                acc = inputs[spec.acc]
                width = acc.shape[0]
                part = wp.zeros(rows * width, dtype=wp.float64, device=device)
                self._reduce = (part, rows, block, width,
                                RecordedLaunch(LK.reduce_rows_kernel, width, [part, rows, width, width, 0, acc, 0],
                                               device, split=False))
        elif spec is not None and spec.kind == "start" and self._spec is None:
            inputs.append(0)  # not split (CUDA): the whole range from 0
        self._kernel, self._dim, self._inputs, self._device = kernel, dim, inputs, device
        self._cmd = self._module = self._key = self._direct = None
        self._parts, self._parts_for = None, None

    def _record(self):
        kernel = self._kernel
        if kernel.is_generic:
            try:
                kernel = kernel._add_normalized_overload(kernel.infer_argument_types(self._inputs))
            except AttributeError:  # a Warp without these internals: plain launches
                self._cmd = False
                return
        cmd = wp.launch(kernel, dim=self._dim, inputs=self._inputs, device=self._device, record_cmd=True)
        try:
            module = kernel.module
            key = next(k for k, v in module.execs.items() if v is cmd.module_exec)
        except (AttributeError, StopIteration):
            self._cmd = False
            return
        self._cmd, self._module, self._key = cmd, module, key

    @staticmethod
    def _cpu_call(cmd):
        """On the CPU, the kernel's forward entry point with its argument struct packed once
        (``Launch.launch`` packs a ctypes struct field by field on every call: ~6 us against
        ~1.5 us); None elsewhere, or when this Warp's internals differ (then ``cmd.launch()``)."""
        import ctypes

        if tuple(int(v) for v in wp.config.version.split(".")[:2]) not in _DIRECT_CPU_CALL_WARP:
            return None  # the entry point's C signature is Warp's internal: only versions checked here
        try:
            if not cmd.device.is_cpu or cmd.adjoint or getattr(cmd, "block_dim", 1) > 1 or strict_device():
                return None
            from warp._src.context import _get_apic_capture_for_device

            if _get_apic_capture_for_device(cmd.device) is not None:
                return None
            cached = cmd.kernel._invoke_cache.get((tuple(type(p) for p in cmd.params[1:]), False))
            if cached is None:
                return None
            Args, fields = cached
            args = Args()
            for i, f in enumerate(fields):
                setattr(args, f[0], cmd.params[1 + i])
            fwd, bounds = cmd.hooks.forward, ctypes.byref(cmd.params[0])
            pargs = ctypes.byref(args)
            return (fwd, bounds, pargs, args)  # args kept alive with its reference
        except Exception:  # noqa: BLE001 -- any mismatch of Warp internals: the public replay
            return None

    def _split_parts(self, threads):
        """The chunks of a split launch on the CPU (``splittable``): one RecordedLaunch each."""
        spec, n = self._spec, int(self._dim)
        if self._reduce is not None:
            part, rows, block, width, _ = self._reduce
            bounds = _chunk_bounds(n, threads, spec, rows=rows, block=block)
        else:
            bounds = _chunk_bounds(n, threads, spec)
        out = []
        for c in range(len(bounds) - 1):
            lo, hi = bounds[c], bounds[c + 1]
            if hi <= lo:
                continue
            if spec.kind == "view":
                args = [v[lo:hi] if isinstance(v, wp.array) else v for v in self._inputs]
            elif self._reduce is not None:
                args = list(self._inputs)
                args[spec.acc] = part
                args += [lo, block, width]
            else:
                args = self._inputs + [lo]
            out.append(RecordedLaunch(self._kernel, hi - lo, args, self._device, split=False))
        return out

    def __call__(self):
        if self._spec is not None:
            from warpfem.threads import get_threads, run_chunks

            threads = get_threads() if self._spec.when < 0 or self._inputs[self._spec.when] else 1
            fresh = self._parts_for != threads
            if fresh:  # (recorded here, in this thread, by their first runs below)
                self._parts, self._parts_for = self._split_parts(threads), threads
            if self._reduce is not None:
                self._reduce[0].zero_()
            if len(self._parts) > 1 and not fresh and not _cpu_capturing(self._device):
                run_chunks(self._parts)
            else:
                for part in self._parts:
                    part()
            if self._reduce is not None:
                self._reduce[4]()
            return
        if self._ordered is not None:
            part, steps = self._ordered
            part.zero_()
            self._ordered = None  # (the kernel's own launch below, then the tree)
            try:
                self()
            finally:
                self._ordered = (part, steps)
            for st in steps:
                st()
            return
        cmd = self._cmd
        if cmd is False:
            wp.launch(self._kernel, dim=self._dim, inputs=self._inputs, device=self._device)
            return
        if cmd is None or not (self._module.hashers and self._module.execs.get(self._key) is cmd.module_exec):
            self._record()
            cmd = self._cmd
            if cmd is False:
                return self()
            cmd.launch()  # the first replay packs Warp's own argument struct (cached by Warp)
            self._direct = self._cpu_call(cmd)
            return
        direct = self._direct
        if direct is not None:
            direct[0](direct[1], direct[2])
        else:
            cmd.launch()


#: capture and replay fixed sequences of device work (``CapturedSequences``); False turns it off everywhere
CAPTURE_SEQUENCES = True


class CapturedSequences:
    """Fixed sequences of device work (kernel launches, memsets, copies), each captured once per
    key as a Warp graph and replayed with ``wp.capture_launch``: a CUDA graph on CUDA, Warp's CPU
    operation stream (replayed in C++, no Python per launch) on the CPU.

    ``run(key, fn)``: ``fn()`` issues device work only (no read-back, no allocation) whose
    arguments are all determined by ``key`` (``None``: not capturable, run as is). A key seen for
    the first time runs ``fn`` as it is (it compiles and loads the kernels' modules); the second
    time it is captured, then replayed, and every later time only replayed. What ``fn`` returns
    is kept with the graph and returned by each replay. Launches are counted in ``COUNTERS`` as if
    they had been made. On CUDA only with the memory pool enabled (captures need it for
    allocations); never on CUDA without it. **The CUDA path has not been run** (no GPU was
    available when it was written); the CPU path is tested (tests/test_step_pipeline.py).
    """

    MAX_GRAPHS = 16

    def __init__(self, device):
        dev = wp.get_device(device)
        self.device = dev
        try:
            self.enabled = bool(dev.is_cpu or (dev.is_cuda and wp.is_mempool_enabled(dev)))
        except Exception:  # noqa: BLE001 -- a Warp without the query: only the CPU path
            self.enabled = bool(dev.is_cpu)
        self._graphs: dict = {}
        self._seen: set = set()
        self._split: set = set()  # keys whose sequence split launches across CPU threads (not captured)
        self._threads = None
        self.captures = 0
        self.replays = 0

    def clear(self):
        self._graphs.clear()
        self._seen.clear()
        self._split.clear()

    def run(self, key, fn):
        if key is None or not (self.enabled and CAPTURE_SEQUENCES) or getattr(self.device, "is_capturing", False):
            return fn()  # (inside a caller's own capture the launches go into that one)
        if self.device.is_cpu:
            from warpfem.threads import get_threads

            threads = get_threads()
            if self._threads != threads:  # the thread count changed: which sequences split may too
                self._threads = threads
                self.clear()
            if key in self._split:
                return fn()
        entry = self._graphs.get(key)
        if entry is None:
            if key not in self._seen:
                if len(self._seen) >= 16 * self.MAX_GRAPHS:
                    self._seen.clear()
                self._seen.add(key)
                s0 = COUNTERS["split"]
                out = fn()
                if self.device.is_cpu and COUNTERS["split"] != s0:
                    # launches split across CPU threads: a replayed graph would run them on one
                    # thread, so this sequence is run as is every time
                    self._split.add(key)
                return out
            if len(self._graphs) >= self.MAX_GRAPHS:
                self._graphs.clear()
            c0 = COUNTERS["launches"]
            with wp.ScopedCapture(device=self.device, force_module_load=False) as cap:
                out = fn()
            entry = (cap.graph, COUNTERS["launches"] - c0, out)
            COUNTERS["launches"] = c0
            self._graphs[key] = entry
            self.captures += 1
        graph, launches, out = entry
        wp.capture_launch(graph)
        COUNTERS["launches"] += launches
        self.replays += 1
        return out
