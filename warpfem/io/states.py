"""Per-frame simulation positions streamed to an ``.npz`` without keeping them in memory.

Frames go, as they are written, into a disk-backed array (a ``.npy`` memory map next to the
output, ``<out>.npz.frames.npy``, and the same for the times); :meth:`StatesWriter.close`
assembles the ``.npz`` from it in chunks of at most ``chunk_bytes`` and deletes the temporary
files. Python memory therefore stays at one frame plus one chunk whatever the run length (the
memory map's pages belong to the operating system's file cache, which can drop them).

The ``.npz`` holds ``rest`` (n, 3) float64 rest positions (m), ``positions`` (k, n, 3) float64
(frame 0 is the state before the first step), ``times`` (k,) s and ``fps`` (and, for several
bodies, ``body_offsets`` and ``body_names``: rest and positions hold every body's vertices in body
order); a run closed early (failure, interrupt) holds the k frames written.
"""

from __future__ import annotations

import os
import zipfile

import numpy as np

__all__ = ["StatesWriter"]


class StatesWriter:
    """Stream (n, 3) position frames to ``path`` (.npz).

    Parameters
    ----------
    path : output ``.npz`` (parent folders are created; an existing file is replaced at close).
    rest : (n, 3) rest positions (m).
    max_frames : frames that may be written (the disk-backed buffer's length).
    fps : frames per second, stored as ``fps``.
    chunk_bytes : largest block copied at once when assembling the ``.npz``.
    extra : {name: array} stored as they are (several bodies: ``body_offsets``, the first vertex of
        each body then the total, and ``body_names``).
    """

    def __init__(self, path, *, rest, max_frames: int, fps: float, chunk_bytes: int = 8 << 20, extra=None):
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
        clash = set(self.extra) & {"rest", "times", "fps", "positions"}
        if clash:
            raise ValueError(f"extra arrays may not be named {sorted(clash)}")
        os.makedirs(os.path.dirname(os.path.abspath(path)) or ".", exist_ok=True)
        self._tmp = path + ".frames.npy"
        self._tmp_times = path + ".times.npy"
        fmt = np.lib.format
        self._frames = fmt.open_memmap(self._tmp, mode="w+", dtype=np.float64, shape=(self.max_frames, len(rest), 3))
        self._times = fmt.open_memmap(self._tmp_times, mode="w+", dtype=np.float64, shape=(self.max_frames,))
        self.frames_written = 0
        self.closed = False

    @property
    def temporary_files(self):
        """The disk-backed buffers (deleted by :meth:`close`)."""
        return (self._tmp, self._tmp_times)

    def write_frame(self, positions, time: float):
        """Append one frame: positions (n, 3) (m) at ``time`` (s)."""
        if self.closed:
            raise ValueError(f"{self.path}: states writer is closed")
        if self.frames_written >= self.max_frames:
            raise ValueError(f"{self.path}: more than max_frames = {self.max_frames} frames written")
        p = np.asarray(positions, dtype=np.float64)
        if p.shape != self.rest.shape:
            raise ValueError(f"positions must have shape {self.rest.shape}, got {p.shape}")
        self._frames[self.frames_written] = p
        self._times[self.frames_written] = float(time)
        self.frames_written += 1

    def close(self):
        """Write the ``.npz`` with the frames written so far and delete the buffers. Idempotent."""
        if self.closed:
            return
        self.closed = True
        k = self.frames_written
        try:
            self._frames.flush()
            tmp_npz = self.path + ".partial"
            with zipfile.ZipFile(tmp_npz, mode="w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
                for key, value in (("rest", self.rest), ("times", np.array(self._times[:k])),
                                   ("fps", np.array(self.fps)), *self.extra.items()):
                    with zf.open(f"{key}.npy", "w", force_zip64=True) as f:
                        np.lib.format.write_array(f, np.require(value, requirements="C"))
                view = self._frames[:k]
                with zf.open("positions.npy", "w", force_zip64=True) as f:
                    fmt = np.lib.format
                    header = {"descr": fmt.dtype_to_descr(np.dtype(np.float64)), "fortran_order": False,
                              "shape": (k, len(self.rest), 3)}
                    fmt.write_array_header_2_0(f, header)
                    per = max(1, self.chunk_bytes // max(1, view[0].nbytes if k else 1))
                    for i in range(0, k, per):
                        f.write(np.ascontiguousarray(view[i:i + per]).tobytes())
            os.replace(tmp_npz, self.path)
        finally:
            del self._frames, self._times
            for f in self.temporary_files:
                if os.path.exists(f):
                    os.remove(f)

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False
