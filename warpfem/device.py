"""Device names: one place that checks a Warp device name and says which devices exist.

``resolve_device(name)`` turns ``"cpu"``, ``"cuda"``, ``"cuda:N"``, any other alias Warp lists
(``wp.get_devices()``) or ``"auto"`` (CUDA when a CUDA device is present, else the CPU) into the
alias of an existing Warp device, and raises :class:`DeviceError` naming the available devices
otherwise. The simulators call :func:`get_device`, so ``Simulator(model, device="auto")`` works
and ``device="gpu"`` fails at once with that list instead of deep inside Warp.
"""

from __future__ import annotations

__all__ = ["DeviceError", "available_devices", "resolve_device", "get_device"]


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
    """The Warp ``Device`` for ``device`` (checked by :func:`resolve_device`)."""
    import warp as wp

    return wp.get_device(resolve_device(device))
