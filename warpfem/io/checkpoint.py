"""A simulator's full step state in one file: save it, load it into a freshly built simulator of
the same scene, and the continued run is the same, bit for bit, as one that never stopped.

The state itself is the simulator's: ``sim.state_dict()`` returns a flat dict of numpy arrays and
Python scalars under namespaced keys ("x", "v", "time", "integrator/x_prev",
"form/contact/kappa", "linear_solver/active", ...) and ``sim.load_state_dict(d)`` checks every key
(shape, dtype, precision) before anything is written. This module holds what both sides share
(:class:`StateView`, the checked reader of such a dict, and :class:`CheckpointError`) and the
file format: :func:`save_state` writes one ``.npz`` atomically (a temporary file in the same
folder, flushed to disk, then renamed over the target: a reader sees the old file or the new one,
never a part), with a format version and an optional physics fingerprint (a dict of the scene's
keys, stored as JSON) that :func:`load_state` compares when asked to.

Only numpy is used here (no Warp, no solver import): the simulator does the work through its two
methods.
"""

from __future__ import annotations

import json
import math
import os
import tempfile
import zipfile
from collections.abc import Mapping

import numpy as np

__all__ = ["CheckpointError", "StateView", "save_state", "load_state", "read_state", "FORMAT_VERSION",
           "fingerprint_differences"]

#: the version of the checkpoint layout; a file of another version is refused
FORMAT_VERSION = 1
_META = "checkpoint/"  # the file's own keys (not part of the simulator's state)


class CheckpointError(ValueError):
    """A state (or checkpoint file) that does not fit the simulator, or a fingerprint that differs;
    the message names the key."""


def _plain(value):
    """A value of a state dict as Python scalar (0-d arrays from a file) or numpy array."""
    if isinstance(value, np.ndarray) and value.ndim == 0:
        return value.item()
    if isinstance(value, np.generic):
        return value.item()
    return value


class StateView(Mapping):
    """A checked, read-only view of a flat state dict under a key prefix.

    ``view["key"]`` is the raw value of ``prefix + "key"`` (a missing key raises
    :class:`CheckpointError` naming it); :meth:`array`, :meth:`integer`, :meth:`number`,
    :meth:`flag`, :meth:`text` check the type (and an array's shape and dtype) and raise a
    one-line :class:`CheckpointError` naming the key otherwise. :meth:`view` is the view of a
    sub-namespace (``view("form/contact")``). The keys read are recorded, so the simulator can
    refuse a state that holds keys it does not know (:meth:`unused`)."""

    def __init__(self, data: Mapping, prefix: str = "", used: set | None = None, *, restoring: bool = False):
        self._data = data
        self.prefix = prefix
        self._used = set() if used is None else used
        #: the simulator's own state put back after a failed load (parts skip checks that only a
        #: foreign state needs, such as a pattern that cannot shrink)
        self.restoring = restoring

    # -- Mapping -----------------------------------------------------------------------------------
    def _full(self, key):
        return self.prefix + key

    def __getitem__(self, key):
        full = self._full(key)
        if full not in self._data:
            raise CheckpointError(f"state key {full!r} is missing (saved from another scene or simulator?)")
        self._used.add(full)
        return _plain(self._data[full])

    def __contains__(self, key):
        return self._full(key) in self._data

    def __iter__(self):
        n = len(self.prefix)
        return (k[n:] for k in self._data if k.startswith(self.prefix))

    def __len__(self):
        return sum(1 for _ in self)

    def get(self, key, default=None):
        return self[key] if key in self else default

    def view(self, sub: str) -> "StateView":
        """The view of the keys under ``sub + "/"`` (sharing the record of keys read)."""
        return StateView(self._data, f"{self.prefix}{sub}/", self._used, restoring=self.restoring)

    def use_all(self):
        """Record every key of this view as read (a part that owns its namespace)."""
        self._used.update(self._full(k) for k in self)

    def unused(self) -> list:
        """The keys of this view that nothing has read, in full."""
        return sorted(self._full(k) for k in self if self._full(k) not in self._used)

    # -- checked access --------------------------------------------------------------------------------
    def error(self, key, message) -> CheckpointError:
        return CheckpointError(f"state key {self._full(key)!r}: {message}")

    def array(self, key, shape=None, dtype=None, *, finite=False) -> np.ndarray:
        """The array at ``key``; ``shape`` (a tuple, None entries free) and ``dtype`` checked."""
        a = self[key]
        if not isinstance(a, np.ndarray):
            raise self.error(key, f"expected an array, got {type(a).__name__}")
        if shape is not None and (a.ndim != len(shape) or any(s is not None and s != t for s, t in zip(shape, a.shape))):
            want = "(" + ", ".join("any" if s is None else str(s) for s in shape) + ("," if len(shape) == 1 else "") + ")"
            raise self.error(key, f"shape {a.shape}, this simulator needs {want}")
        if dtype is not None and a.dtype != np.dtype(dtype):
            raise self.error(key, f"dtype {a.dtype}, this simulator needs {np.dtype(dtype)}")
        if finite and a.dtype.kind == "f" and not np.all(np.isfinite(a)):
            raise self.error(key, "holds NaN or inf")
        return a

    def integer(self, key) -> int:
        v = self[key]
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)):
            raise self.error(key, f"expected an integer, got {v!r}")
        return int(v)

    def number(self, key, *, optional=False):
        """A float; with ``optional``, NaN stands for None."""
        v = self[key]
        if isinstance(v, bool) or not isinstance(v, (int, float, np.integer, np.floating)):
            raise self.error(key, f"expected a number, got {v!r}")
        v = float(v)
        return None if optional and math.isnan(v) else v

    def flag(self, key) -> bool:
        v = self[key]
        if not isinstance(v, (bool, np.bool_)):
            raise self.error(key, f"expected true or false, got {v!r}")
        return bool(v)

    def text(self, key) -> str:
        v = self[key]
        if not isinstance(v, str):
            raise self.error(key, f"expected a text, got {v!r}")
        return v

    def expect_text(self, key, value: str, what: str):
        """Refuse the state unless the text at ``key`` is ``value`` (``what`` names it in the message)."""
        saved = self.text(key)
        if saved != value:
            raise self.error(key, f"saved from {what} {saved!r}, this simulator has {value!r}")


def optional_number(v) -> float:
    """None as NaN (how the state dicts store an unset number)."""
    return float("nan") if v is None else float(v)


# -- files -------------------------------------------------------------------------------------------
def _json_default(v):
    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, np.generic):
        return v.item()
    raise TypeError(f"fingerprint value {v!r} is not JSON-serialisable")


def _canonical(fingerprint) -> dict:
    """The fingerprint as it reads back from JSON (tuples as lists, numpy values as Python's)."""
    if fingerprint is None:
        return None
    if not isinstance(fingerprint, Mapping):
        raise TypeError(f"fingerprint must be a dict of scene keys, got {type(fingerprint).__name__}")
    return json.loads(json.dumps(dict(fingerprint), sort_keys=True, default=_json_default))


def fingerprint_differences(saved, expected) -> list:
    """The keys whose values differ between two fingerprints (a key in one only counts), sorted."""
    a, b = _canonical(saved) or {}, _canonical(expected) or {}
    return sorted(k for k in set(a) | set(b) if k not in a or k not in b or a[k] != b[k])


def save_state(sim, path, *, fingerprint=None) -> str:
    """Write ``sim.state_dict()`` to ``path`` (a ``.npz``) atomically; returns the path.

    ``fingerprint``: an optional dict of the scene's physics keys (JSON-serialisable), stored with
    the state so that :func:`load_state` can refuse a state saved from a different scene. The file
    is written to a temporary file in the same folder, flushed to disk (fsync) and renamed over
    ``path`` (``os.replace``): after a crash at any moment ``path`` holds the previous complete
    checkpoint or the new one. Raises OSError naming the file when it cannot be written."""
    path = os.fspath(path)
    state = sim.state_dict()
    clash = [k for k in state if k.startswith(_META)]
    if clash:
        raise ValueError(f"save_state: state keys {clash} use the checkpoint's own prefix {_META!r}")
    payload = {k: np.asarray(v) for k, v in state.items()}
    payload[_META + "format_version"] = np.asarray(FORMAT_VERSION)
    if fingerprint is not None:
        payload[_META + "fingerprint"] = np.asarray(json.dumps(_canonical(fingerprint), sort_keys=True))
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(dir=folder, prefix="." + os.path.basename(path) + ".", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **payload)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    try:  # the rename itself on disk (POSIX; a no-op elsewhere)
        dfd = os.open(folder, os.O_RDONLY)
        try:
            os.fsync(dfd)
        finally:
            os.close(dfd)
    except OSError:
        pass
    return path


def read_state(path):
    """(state dict, fingerprint dict or None) of a checkpoint file written by :func:`save_state`.
    Raises FileNotFoundError when there is no such file and :class:`CheckpointError` naming the file
    when it is not a checkpoint (damaged, or of another format version)."""
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no checkpoint file {path!r}")
    try:
        with np.load(path, allow_pickle=False) as z:
            data = {k: z[k] for k in z.files}
    except (zipfile.BadZipFile, ValueError, OSError, EOFError) as e:
        raise CheckpointError(f"{path}: not a readable checkpoint ({e})") from e
    version = data.pop(_META + "format_version", None)
    if version is None:
        raise CheckpointError(f"{path}: not a warpfem checkpoint (no {_META}format_version)")
    if int(version) != FORMAT_VERSION:
        raise CheckpointError(f"{path}: checkpoint format version {int(version)}, this warpfem reads {FORMAT_VERSION}")
    fp = data.pop(_META + "fingerprint", None)
    fingerprint = None if fp is None else json.loads(str(fp.item()))
    return {k: _plain(v) for k, v in data.items()}, fingerprint


def load_state(sim, path, *, expect_fingerprint=None):
    """Load a checkpoint written by :func:`save_state` into ``sim`` (``sim.load_state_dict``);
    returns the fingerprint stored with it (None when none was).

    ``expect_fingerprint``: the fingerprint of the scene ``sim`` was built from; when given, a
    checkpoint whose stored fingerprint differs is refused with a :class:`CheckpointError` listing
    the keys that differ (nothing is loaded). A missing file raises FileNotFoundError; a state that
    does not fit ``sim`` (another mesh, precision, contact set-up) raises :class:`CheckpointError`
    naming the key, and ``sim`` is left as it was."""
    state, fingerprint = read_state(path)
    if expect_fingerprint is not None:
        if fingerprint is None:
            raise CheckpointError(f"{os.fspath(path)}: the checkpoint has no fingerprint to compare with the scene's")
        diff = fingerprint_differences(fingerprint, expect_fingerprint)
        if diff:
            saved, now = _canonical(fingerprint), _canonical(expect_fingerprint)
            parts = [f"{k} (saved {json.dumps(saved.get(k))}, now {json.dumps(now.get(k))})" for k in diff]
            raise CheckpointError(f"{os.fspath(path)}: the scene changed since the checkpoint: " + "; ".join(parts))
    sim.load_state_dict(state)
    return fingerprint
