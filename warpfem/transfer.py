"""Host <-> device crossings: the one place where the solvers, the contact code, the adjoint and the
multigrid read a device array to the host or upload host data into one.

* :func:`read` (a device array to a NumPy array, optionally only its first ``count`` entries),
  :func:`read_scalar` (one entry as a Python float), :func:`read_int`;
* :func:`upload` (host data into an existing device array, in place), :func:`to_device` (a new
  device array holding host data).

Each call counts one crossing in :data:`COUNTERS` (``reads``, ``uploads``, since start-up); per
step the simulators report the Newton loop's read-backs as ``SolveStats.newton_syncs`` and those
inside the linear solves as ``SolveStats.host_syncs``.

On the CPU Warp's arrays are host memory: a read is a view of the array (no copy) and an upload may
write straight into it. **Strict device mode** (``WARPFEM_STRICT_DEVICE=1`` in the environment, or
:func:`set_strict_device` / :func:`strict_device_mode`) makes the CPU behave like a discrete
device: a read returns a copy (writing to it changes nothing on the device), an upload goes
through Warp's device copy, and the CPU-only fast paths elsewhere ask :func:`strict_device` and
are off, so the code written for CUDA runs (docs/design.md, "Devices").
"""

from __future__ import annotations

import contextlib
import os

import numpy as np
import warp as wp

__all__ = ["COUNTERS", "strict_device", "set_strict_device", "strict_device_mode", "host_aliases", "read",
           "read_scalar", "read_int", "upload", "to_device"]

#: crossings made through this module since start-up (the simulators report per-step differences)
COUNTERS = {"reads": 0, "uploads": 0}

_ENV = "WARPFEM_STRICT_DEVICE"
_strict = None


def _env_strict() -> bool:
    value = os.environ.get(_ENV, "").strip().lower()
    if value in ("", "0", "false", "no", "off"):
        return False
    if value in ("1", "true", "yes", "on"):
        return True
    raise ValueError(f"{_ENV}={os.environ.get(_ENV)!r}: expected 1 or 0 (true/false, yes/no, on/off)")


def strict_device() -> bool:
    """Whether strict device mode is on (``WARPFEM_STRICT_DEVICE``, read once, or the last
    :func:`set_strict_device`). Objects built while it is on keep the CUDA code paths they chose."""
    global _strict
    if _strict is None:
        _strict = _env_strict()
    return _strict


def set_strict_device(on) -> bool:
    """Turn strict device mode on (True), off (False) or back to the environment's setting (None);
    returns the previous setting. Affects the simulators and solvers built afterwards (and every
    read and upload from now on)."""
    global _strict
    previous = strict_device()
    _strict = None if on is None else bool(on)
    return previous


@contextlib.contextmanager
def strict_device_mode(on: bool = True):
    """``with strict_device_mode():`` strict device mode inside the block, the previous setting after."""
    previous = set_strict_device(on)
    try:
        yield
    finally:
        set_strict_device(previous)


def host_aliases(device) -> bool:
    """Whether a host view of an array on ``device`` is its memory (the CPU outside strict mode):
    then a read is not a copy and writing into it changes the device array."""
    return bool(wp.get_device(device).is_cpu) and not strict_device()


def read(a, count: int | None = None) -> np.ndarray:
    """The device array ``a`` (or its first ``count`` entries) on the host. Outside strict mode on
    the CPU this is a view of ``a`` (do not keep it across a later write of ``a``); otherwise a copy."""
    COUNTERS["reads"] += 1
    if count is not None and count < a.shape[0]:
        a = a[: max(int(count), 0)]
    h = a.numpy()
    if a.device.is_cpu and strict_device():
        h = h.copy()
    return h


def read_scalar(a, index: int = 0) -> float:
    """Entry ``index`` of the 1-d device array ``a`` as a Python float (one crossing)."""
    COUNTERS["reads"] += 1
    if a.device.is_cpu and not strict_device():
        return float(a.numpy()[index])
    index = int(index) % a.shape[0]
    return float(a[index:index + 1].numpy()[0])


def read_int(a, index: int = 0) -> int:
    """Entry ``index`` of the 1-d integer device array ``a`` as a Python int (one crossing)."""
    COUNTERS["reads"] += 1
    if a.device.is_cpu and not strict_device():
        return int(a.numpy()[index])
    index = int(index) % a.shape[0]
    return int(a[index:index + 1].numpy()[0])


def _np_dtype(dtype):
    return wp.dtype_to_numpy(getattr(dtype, "_wp_scalar_type_", dtype))


def _host_shape(a):
    return tuple(a.shape) + tuple(getattr(a.dtype, "_shape_", ()))


def upload(dst, host):
    """Host data into the existing device array ``dst`` (same number of entries; cast to its
    scalar type), in place; returns ``dst``."""
    h = np.asarray(host)
    shape = _host_shape(dst)
    if h.size != int(np.prod(shape)):
        raise ValueError(f"upload: {h.size} values for a device array of shape {shape}")
    COUNTERS["uploads"] += 1
    if host_aliases(dst.device):  # the array is host memory: write into it (no temporary)
        np.copyto(dst.numpy().reshape(shape), h.reshape(shape), casting="unsafe")
    else:  # a device copy from a host staging array (what every discrete device needs)
        dst.assign(np.ascontiguousarray(h.reshape(shape), dtype=_np_dtype(dst.dtype)))
    return dst


def to_device(host, dtype, device, *, requires_grad: bool = False):
    """A new device array of ``dtype`` on ``device`` holding the host data ``host`` (one upload)."""
    COUNTERS["uploads"] += 1
    return wp.array(np.ascontiguousarray(host), dtype=dtype, device=device, requires_grad=requires_grad)
