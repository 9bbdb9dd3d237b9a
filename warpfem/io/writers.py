"""The one protocol of a run's outputs: :class:`FrameWriter` (``open``, ``write``, ``close``), fed one
:class:`FrameSnapshot` per frame, and described once by a :class:`RunInfo`.

A run (``warpfem.scenes.SceneRun.run``) builds its writers from the scene's ``[output]`` table
(:data:`warpfem.io.outputs.OUTPUT_FORMATS`: key -> writer class), then::

    for w in writers: w.open(run_info)                 # frame 0 follows as the first snapshot
    for each frame: snapshot = FrameSnapshot(...)      # built once per frame
                    for w in writers: w.write(snapshot)
    for w in writers: w.close(complete, reason)        # reason: why the run stopped (None when complete)

A snapshot computes what a writer asks for only when first asked, once per frame, from functions
the run provides (``positions``, ``velocities``, ``surface_points``, ``element_fields``, ...):
a writer never reaches into the simulator. A new output format is one file: a ``FrameWriter``
subclass and its line in ``OUTPUT_FORMATS``.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable

import numpy as np

__all__ = ["FrameWriter", "FrameSnapshot", "RunInfo", "OutputWriteError"]


class OutputWriteError(OSError):
    """An output that could not be written during a run (full disk, folder removed): the message
    names the file and the frame; the run stops, every earlier frame stays readable."""


@dataclass
class RunInfo:
    """What every writer may need before the first frame (built once by the run).

    fps, total_frames : output rate and the last frame index the run writes.
    resume_after : None for a new run; k when the run continues after frame k (a writer keeps the
        frames 0..k it holds and drops any later one; the next snapshot is frame k + 1).
    rest : (n, 3) rest positions of every vertex (m), float64.
    version : the warpfem version.
    surfaces : [(prim name, faces (f, 3), number of points)]: the render surfaces.
    rigid_surfaces : [(prim name, faces (f, 3), points (p, 3) relative to the centre of mass)]: the
        rigid bodies' surfaces, moved by the snapshot's ``transforms`` (4x4, USD's row-vector form).
    volumes : [(prim name, tets (m, 4), boundary faces or None, first vertex, end vertex)]:
        ``[output] usd_volume`` tet meshes.
    colliders : [(prim name, faces (f, 3), number of points)]: collider meshes.
    blocks : [(name or None, cells (m, k) in the block's vertex numbering, element type, first vertex,
        end vertex)]: the volume mesh by body (one block named None for a one-body scene).
    states_extra : extra arrays of the states file (several bodies: body_offsets, body_names).
    options : the scene's ``[output]`` table (writer settings such as up_axis, clip_frames).
    """

    fps: float
    total_frames: int
    rest: np.ndarray
    resume_after: int | None = None
    version: str = ""
    surfaces: list = field(default_factory=list)
    rigid_surfaces: list = field(default_factory=list)
    volumes: list = field(default_factory=list)
    colliders: list = field(default_factory=list)
    blocks: list = field(default_factory=list)
    states_extra: dict = field(default_factory=dict)
    options: dict = field(default_factory=dict)


class FrameSnapshot:
    """One frame as the writers see it: ``frame`` (index), ``time`` (s), ``stats`` (the frame's
    ``FrameStats``; None for frame 0), ``sync`` (True: the run checkpoints this frame, so every writer
    makes all its frames up to this one readable on disk now), and lazily computed quantities:

    * ``positions`` (n, 3) float64 every vertex, ``velocities`` (n, 3);
    * ``surface_points`` {prim name: (p, 3)} of the render surfaces, volumes and colliders;
    * ``element_fields`` [{"J", "cauchy_stress", "von_mises"} per block] (ParaView);
    * ``transforms`` {prim name: 4x4} of the rigid bodies' surfaces (``RunInfo.rigid_surfaces``).

    Each is computed by the function the run gave (``providers``) on first access and kept for the
    other writers of the frame; ``snapshot.get(name)`` reads any provider by name.
    """

    def __init__(self, frame: int, time: float, *, stats=None, sync: bool = False,
                 providers: dict[str, Callable[[], Any]] | None = None):
        self.frame, self.time, self.stats, self.sync = int(frame), float(time), stats, bool(sync)
        self._providers = dict(providers or {})
        self._cache = {}

    def get(self, name: str):
        if name not in self._cache:
            if name not in self._providers:
                raise KeyError(f"frame snapshot has no {name!r} (provided: {sorted(self._providers)})")
            self._cache[name] = self._providers[name]()
        return self._cache[name]

    @property
    def positions(self) -> np.ndarray:
        return self.get("positions")

    @property
    def velocities(self) -> np.ndarray:
        return self.get("velocities")

    @property
    def surface_points(self) -> dict:
        return self.get("surface_points")

    @property
    def element_fields(self) -> list:
        return self.get("element_fields")

    @property
    def transforms(self) -> dict:
        return self.get("transforms") if "transforms" in self._providers else {}


class FrameWriter:
    """Base of a run output. Subclasses set ``label`` (how messages name the output, e.g. ``"[output]
    usd"``) and implement :meth:`open`, :meth:`write` and :meth:`close`; ``path`` is the file.

    ``open(run)`` prepares the file for a :class:`RunInfo` (with ``run.resume_after = k``: keep
    frames 0..k already on disk, drop later ones); ``write(snapshot)`` adds one frame; ``close(complete,
    reason)`` finishes the file, recording an incomplete run's reason where the format can.
    ``abandon()`` releases the file after a failed write without writing more (default: nothing).
    """

    label = "output"

    def __init__(self, path, **options):
        import os

        self.path = os.fspath(path)
        self.options = options

    def open(self, run: RunInfo) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def write(self, snapshot: FrameSnapshot) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def close(self, complete: bool, reason: str | None = None) -> None:  # pragma: no cover - interface
        raise NotImplementedError

    def failed(self, record: dict) -> None:
        """A frame whose step raised: ``record`` = {frame, converged: False, error, newton_iterations}
        (the statistics log writes it; default: nothing)."""

    def abandon(self) -> None:
        """After a failed :meth:`write`: release what is open, write nothing more."""
