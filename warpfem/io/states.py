"""Per-frame simulation positions streamed to disk, readable after any fault, assembled into an ``.npz``.

While a run goes, the frames of ``STATES.npz`` are appended to a **stream folder** next to it,
``STATES.npz.stream/`` (:func:`stream_directory`)::

    meta.npz        rest (n, 3), fps and the extra arrays (body_offsets, body_names), written once
    positions.f64   the frames' positions: (n, 3) little-endian float64 per frame, appended
    times.f64       one little-endian float64 per frame (s), appended after the frame's positions

A frame counts once its time is written, so the number of frames is ``min(size(times.f64) / 8,
size(positions.f64) / (24 n))``: whatever stopped the process (SIGKILL included), the stream holds
every frame written before. :meth:`StatesWriter.close` assembles the ``.npz`` from it (in chunks of at
most ``chunk_bytes``, through a temporary file and a rename) and then deletes the stream folder. Python
memory stays at one frame plus one chunk whatever the run length. The writes are ordinary file
writes (no memory map), so a full disk is an ``OSError`` naming the file, not a crash.

:func:`read_states` is the reader: the ``.npz`` when it is complete, else the stream (a run that was
killed or could not write its ``.npz``); :func:`recover_states` writes the ``.npz`` of a stream
(``warpfem recover``).

The ``.npz`` holds ``rest`` (n, 3) float64 rest positions (m), ``positions`` (k, n, 3) float64
(frame 0 is the state before the first step), ``times`` (k,) s and ``fps`` (and, for several
bodies, ``body_offsets`` and ``body_names``: rest and positions hold every body's vertices in body
order); a run closed early (failure, interrupt) holds the k frames written. Its bytes depend only
on the arrays (the zip entries carry a fixed date), so two runs with the same frames write the same
file.
"""

from __future__ import annotations

import os
import shutil
import zipfile

import numpy as np

from .writers import FrameWriter

__all__ = ["StatesWriter", "StatesOutput", "read_states", "recover_states", "stream_directory", "StatesError"]

_F8 = np.dtype("<f8")
_ZIP_DATE = (1980, 1, 1, 0, 0, 0)  # fixed: the npz bytes depend on the arrays only


class StatesError(ValueError):
    """A states file or stream that cannot be read (the message names it and why)."""


def stream_directory(path) -> str:
    """The folder a states file's frames stream to while the run goes (``out/run.npz`` ->
    ``out/run.npz.stream``)."""
    return os.fspath(path) + ".stream"


def _write_npz(path, arrays, *, positions=None, chunk_bytes=8 << 20):
    """Write an ``.npz`` (no compression, fixed dates) through ``path.partial`` and a rename.
    ``positions``: (array-like (k, n, 3) read in chunks) stored as ``positions``."""
    tmp = os.fspath(path) + ".partial"
    try:
        with zipfile.ZipFile(tmp, mode="w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
            for key, value in arrays.items():
                with zf.open(zipfile.ZipInfo(f"{key}.npy", date_time=_ZIP_DATE), "w", force_zip64=True) as f:
                    np.lib.format.write_array(f, np.require(value, requirements="C"))
            if positions is not None:
                k, n = len(positions), positions.shape[1]
                with zf.open(zipfile.ZipInfo("positions.npy", date_time=_ZIP_DATE), "w", force_zip64=True) as f:
                    fmt = np.lib.format
                    fmt.write_array_header_2_0(f, {"descr": fmt.dtype_to_descr(np.dtype(np.float64)),
                                                   "fortran_order": False, "shape": (k, n, 3)})
                    per = max(1, int(chunk_bytes) // max(1, n * 24))
                    for i in range(0, k, per):
                        f.write(np.ascontiguousarray(positions[i:i + per], dtype=np.float64).tobytes())
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.remove(tmp)
        raise


def _stream_arrays(folder):
    """(meta {name: array}, positions (k, n, 3) memory map or array, times (k,)) of a stream folder."""
    meta_path = os.path.join(folder, "meta.npz")
    try:
        with np.load(meta_path, allow_pickle=False) as z:
            meta = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile) as e:
        raise StatesError(f"{meta_path}: cannot read the stream's metadata: {e}") from None
    n = len(meta["rest"])
    pos_path, t_path = os.path.join(folder, "positions.f64"), os.path.join(folder, "times.f64")
    size_p = os.path.getsize(pos_path) if os.path.exists(pos_path) else 0
    size_t = os.path.getsize(t_path) if os.path.exists(t_path) else 0
    k = min(size_t // 8, size_p // (24 * n)) if n else 0
    times = np.fromfile(t_path, dtype=_F8, count=k).astype(np.float64) if k else np.zeros(0)
    positions = (np.memmap(pos_path, dtype=_F8, mode="r", shape=(k, n, 3)) if k
                 else np.zeros((0, n, 3)))
    return meta, positions, times


def read_states(path) -> dict:
    """The arrays of a states file as a dict (``rest``, ``positions``, ``times``, ``fps`` and the extra
    arrays), plus ``complete`` (bool): True for a written ``.npz``, False when read from the stream
    folder of a run that stopped before writing it (killed, or a failed write). The stream is read when
    it exists (a run in progress, or stopped), else the ``.npz``; ``positions`` of a stream is a
    read-only memory map."""
    path = os.fspath(path)
    folder = stream_directory(path)
    if os.path.isdir(folder) and os.path.exists(os.path.join(folder, "meta.npz")):
        meta, positions, times = _stream_arrays(folder)
        return {**meta, "positions": positions, "times": times, "complete": False}
    if not os.path.exists(path):
        raise StatesError(f"{path}: no such states file (and no stream folder {folder})")
    try:
        with np.load(path, allow_pickle=False) as z:
            out = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile) as e:
        raise StatesError(f"{path}: cannot read it as an .npz: {e}") from None
    out["complete"] = True
    return out


def recover_states(path, *, chunk_bytes: int = 8 << 20) -> int | None:
    """Write the ``.npz`` of a stopped run from its stream folder and delete the folder; returns the
    number of frames, or None when there is no stream (nothing to recover)."""
    path = os.fspath(path)
    folder = stream_directory(path)
    if not os.path.isdir(folder):
        return None
    meta, positions, times = _stream_arrays(folder)
    arrays = {"rest": meta.pop("rest"), "times": times, "fps": meta.pop("fps"), **meta}
    _write_npz(path, arrays, positions=positions, chunk_bytes=chunk_bytes)
    k = len(times)
    del positions
    shutil.rmtree(folder)
    return k


class StatesWriter:
    """Stream (n, 3) position frames to ``path`` (.npz) through its stream folder.

    Parameters
    ----------
    path : output ``.npz`` (parent folders are created; an existing file is replaced at close).
    rest : (n, 3) rest positions (m).
    max_frames : frames that may be written.
    fps : frames per second, stored as ``fps``.
    chunk_bytes : largest block copied at once when assembling the ``.npz``.
    extra : {name: array} stored as they are (several bodies: ``body_offsets``, the first vertex of
        each body then the total, and ``body_names``).
    keep_frames : None (a new stream: an earlier one is replaced), or k: continue the frames already
        there (the stream, else the ``.npz``), keeping the first k and appending after them.
    """

    def __init__(self, path, *, rest, max_frames: int, fps: float, chunk_bytes: int = 8 << 20, extra=None,
                 keep_frames: int | None = None):
        path = os.fspath(path)
        rest = np.array(rest, dtype=np.float64)
        if rest.ndim != 2 or rest.shape[1] != 3:
            raise ValueError(f"rest must have shape (n, 3), got {rest.shape}")
        if isinstance(max_frames, bool) or int(max_frames) != max_frames or max_frames < 1:
            raise ValueError(f"max_frames must be an integer >= 1, got {max_frames!r}")
        self.path = path
        self.rest = rest
        self.fps = float(fps)
        self.max_frames = int(max_frames)
        self.chunk_bytes = int(chunk_bytes)
        self.extra = {k: np.asarray(v) for k, v in (extra or {}).items()}
        clash = set(self.extra) & {"rest", "times", "fps", "positions", "complete"}
        if clash:
            raise ValueError(f"extra arrays may not be named {sorted(clash)}")
        self.folder = stream_directory(path)
        self._pos_path = os.path.join(self.folder, "positions.f64")
        self._times_path = os.path.join(self.folder, "times.f64")
        self.closed = False
        self.frames_written = 0
        if keep_frames is None:
            if os.path.isdir(self.folder):
                shutil.rmtree(self.folder)
            os.makedirs(self.folder)
            _write_npz(os.path.join(self.folder, "meta.npz"),
                       {"rest": self.rest, "fps": np.array(self.fps), **self.extra})
        else:
            self._continue(int(keep_frames))
        self._pos = open(self._pos_path, "ab")
        self._times = open(self._times_path, "ab")

    def _continue(self, k: int):
        """Keep frames 0..k-1 of the stream (or, without one, of the ``.npz``) and append after them."""
        n = len(self.rest)
        if os.path.isdir(self.folder) and not os.path.exists(os.path.join(self.folder, "meta.npz")):
            shutil.rmtree(self.folder)  # killed before its first frame: nothing in it
        if os.path.isdir(self.folder) and os.path.exists(self.path):
            _, positions, times = _stream_arrays(self.folder)
            if len(times) < k:  # a stream cut short while it was being rebuilt from the .npz: again
                shutil.rmtree(self.folder)
            del positions
        if not os.path.isdir(self.folder):  # a completed run: its frames back into a stream
            have = read_states(self.path)
            if len(have["times"]) < k:
                raise StatesError(f"{self.path}: holds {len(have['times'])} frames, {k} needed to continue")
            os.makedirs(self.folder)
            _write_npz(os.path.join(self.folder, "meta.npz"),
                       {"rest": self.rest, "fps": np.array(self.fps), **self.extra})
            with open(self._pos_path, "wb") as f:
                per = max(1, self.chunk_bytes // max(1, n * 24))
                for i in range(0, k, per):
                    np.ascontiguousarray(have["positions"][i:min(k, i + per)], dtype=_F8).tofile(f)
            np.ascontiguousarray(have["times"][:k], dtype=_F8).tofile(self._times_path)
        else:
            _, positions, times = _stream_arrays(self.folder)
            if len(times) < k:
                raise StatesError(f"{self.path}: its stream holds {len(times)} frames, {k} needed to continue")
            del positions
            os.truncate(self._pos_path, k * n * 24)
            os.truncate(self._times_path, k * 8)
        self.frames_written = k

    @property
    def temporary_files(self):
        """The stream's frame files (deleted by :meth:`close` once the ``.npz`` is written)."""
        return (self._pos_path, self._times_path)

    def write_frame(self, positions, time: float):
        """Append one frame: positions (n, 3) (m) at ``time`` (s); on disk (the operating system's
        cache) when this returns."""
        if self.closed:
            raise ValueError(f"{self.path}: states writer is closed")
        if self.frames_written >= self.max_frames:
            raise ValueError(f"{self.path}: more than max_frames = {self.max_frames} frames written")
        p = np.asarray(positions)
        if p.shape != self.rest.shape:
            raise ValueError(f"positions must have shape {self.rest.shape}, got {p.shape}")
        try:
            np.ascontiguousarray(p, dtype=_F8).tofile(self._pos)
            self._pos.flush()
            self._times.write(np.array([time], dtype=_F8).tobytes())
            self._times.flush()
        except OSError:
            # a partial frame is ignored by the readers (no time); cut it so that a retry appends cleanly
            self._cut(self.frames_written)
            raise
        self.frames_written += 1

    def _cut(self, k):
        for f, size in ((self._pos, k * len(self.rest) * 24), (self._times, k * 8)):
            try:
                f.truncate(size)
            except (OSError, ValueError):
                pass

    def close(self, *, assemble: bool = True):
        """Write the ``.npz`` with the frames written so far and delete the stream folder (``assemble``
        False: keep the stream, e.g. for a later resume, and write nothing). Idempotent. When the
        ``.npz`` cannot be written (full disk) the stream is kept and the error propagates."""
        if self.closed:
            return
        self.closed = True
        for f in (self._pos, self._times):
            try:
                f.close()
            except OSError:
                pass
        if assemble:
            recover_states(self.path, chunk_bytes=self.chunk_bytes)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


class StatesOutput(FrameWriter):
    """``[output] states``: every frame's positions (all vertices, float64) into a :class:`StatesWriter`."""

    label = "[output] states"

    def __init__(self, path, **_options):
        super().__init__(path)
        self._w = None

    def open(self, run):
        keep = None if run.resume_after is None else run.resume_after + 1
        self._w = StatesWriter(self.path, rest=run.rest, max_frames=run.total_frames + 1, fps=run.fps,
                               extra=run.states_extra, keep_frames=keep)

    def write(self, snapshot):
        self._w.write_frame(snapshot.positions, snapshot.time)

    def close(self, complete: bool, reason: str | None = None):
        if self._w is not None:
            self._w.close()

    def abandon(self):
        if self._w is not None:
            self._w.close(assemble=False)
