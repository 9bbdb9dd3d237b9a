"""Device names: one place that checks a Warp device name and says which devices exist.

``resolve_device(name)`` turns ``"cpu"``, ``"cuda"``, ``"cuda:N"``, any other alias Warp lists
(``wp.get_devices()``) or ``"auto"`` (CUDA when a CUDA device is present, else the CPU) into the
alias of an existing Warp device, and raises :class:`DeviceError` naming the available devices
otherwise. The simulators call :func:`get_device`, so ``Simulator(model, device="auto")`` works
and ``device="gpu"`` fails at once with that list instead of deep inside Warp.

Quiet by default: importing warpfem calls :func:`configure_warp`, so Warp's start-up banner and its
``Module ... load`` lines are not printed (warnings still are), and :func:`init_warp` (run by
:func:`get_device` when Warp is not initialised yet) drops the native library's note that no CUDA
driver was found (a CUDA device asked for on a machine without one gets a one-line error instead). ``WARPFEM_VERBOSE=1`` in the environment (or
``configure_warp(verbose=True)`` before Warp initialises) shows them, as ``warpfem --verbose`` does.
"""

from __future__ import annotations

import os
import sys

__all__ = ["DeviceError", "available_devices", "resolve_device", "get_device", "configure_warp", "init_warp",
           "warp_initialized"]

_NO_DRIVER = "Could not find or load the NVIDIA CUDA driver"


def _env_verbose() -> bool:
    return os.environ.get("WARPFEM_VERBOSE", "").strip().lower() not in ("", "0", "false", "no")


def configure_warp(verbose: bool | None = None) -> None:
    """Warp's banner and module-load lines only when ``verbose`` (default: ``WARPFEM_VERBOSE``);
    warnings always. Takes effect for messages printed after it (the banner: before Warp
    initialises). Warp 1.19 reads ``wp.config.log_level``; older versions ``quiet``."""
    import warp as wp

    verbose = _env_verbose() if verbose is None else bool(verbose)
    wp.config.quiet = not verbose
    if hasattr(wp, "LOG_INFO"):
        wp.config.log_level = wp.LOG_INFO if verbose else wp.LOG_WARNING


def warp_initialized() -> bool:
    """True once Warp's runtime exists (``wp.init()`` ran, explicitly or by a first use)."""
    try:
        from warp._src import context
    except ImportError:  # another Warp layout: assume it is (nothing is filtered then)
        return True
    return getattr(context, "runtime", True) is not None


def init_warp(device="cpu", verbose: bool | None = None) -> None:
    """Initialise Warp now (nothing when it already is). Unless ``verbose`` (default:
    ``WARPFEM_VERBOSE``), the native library's note that no CUDA driver was found (printed by C
    code straight to file descriptor 2, not through Warp's log level) is dropped, also when a CUDA
    device is asked for: :func:`resolve_device` then says in one line that there is none (no
    NVIDIA driver or GPU); anything else it prints is passed on to stderr."""
    import warp as wp

    if warp_initialized():
        return
    verbose = _env_verbose() if verbose is None else bool(verbose)
    if verbose:
        wp.init()
        return
    import tempfile

    sys.stderr.flush()
    try:
        saved = os.dup(2)
    except OSError:  # no usable fd 2: nothing to filter
        wp.init()
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        tmp.seek(0)
        text = tmp.read().decode("utf-8", errors="replace")
    rest = [line for line in text.splitlines() if _NO_DRIVER not in line]
    if rest:  # Warp's own output, passed on as it was (not a message of warpfem's: no logging)
        sys.stderr.write("\n".join(rest) + "\n")
        sys.stderr.flush()


class DeviceError(ValueError):
    """An unknown or unavailable device name (the message lists the available ones)."""


def available_devices() -> list:
    """Aliases of the devices Warp can use here (``"cpu"``, ``"cuda:0"``, ...); initialises Warp."""
    import warp as wp

    return [d.alias for d in wp.get_devices()]


def _listing(aliases) -> str:
    return f"available: {', '.join(aliases) or 'none'} (and 'auto')"


def resolve_device(device="auto") -> str:
    """Alias of the Warp device ``device`` names (see the module docstring).

    ``device`` may be a name (case-insensitive), a Warp ``Device`` (returned by alias) or None
    (Warp's default device). ``"cpu"`` is answered without initialising Warp."""
    import warp as wp

    if device is None:
        return wp.get_device().alias
    if hasattr(device, "alias") and hasattr(device, "is_cuda"):  # a warp Device
        return device.alias
    if not isinstance(device, str):
        raise DeviceError(f"device must be a name such as 'cpu', 'cuda:0' or 'auto', got {type(device).__name__} {device!r}")
    name = device.strip().lower()
    if name == "cpu":
        return "cpu"
    if name == "auto":
        return wp.get_device("cuda").alias if wp.get_cuda_device_count() > 0 else "cpu"
    aliases = available_devices()
    count = wp.get_cuda_device_count()
    if name in aliases or device.strip() in aliases:
        return name if name in aliases else device.strip()
    if name == "cuda" or (name.startswith("cuda:") and name[5:].isdigit()):
        if name == "cuda" and count > 0:  # the current CUDA device
            return wp.get_device("cuda").alias
        why = "no CUDA device here (no NVIDIA driver or GPU)" if count == 0 else f"{count} CUDA device(s)"
        raise DeviceError(f"device {device!r} is not available: {why}; {_listing(aliases)}")
    hint = " (Warp calls GPUs 'cuda' or 'cuda:N')" if name in ("gpu", "nvidia") or name.startswith("gpu:") else ""
    raise DeviceError(f"unknown device {device!r}{hint}; {_listing(aliases)}")


def get_device(device="auto"):
    """The Warp ``Device`` for ``device`` (checked by :func:`resolve_device`); initialises Warp
    quietly (:func:`init_warp`) when it is not yet."""
    import warp as wp

    init_warp(device if isinstance(device, str) else "cpu")
    return wp.get_device(resolve_device(device))
