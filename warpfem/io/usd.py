"""Animated triangle meshes to USD (one UsdGeom.Mesh per surface, points time-sampled per frame).

``pxr`` is imported lazily inside functions so that importing warpfem does not need usd-core.

File layout::

    #usda 1.0
    (
        defaultPrim = "Root"  upAxis = "Y"  metersPerUnit = 1
        timeCodesPerSecond = fps  framesPerSecond = fps
        startTimeCode = first frame  endTimeCode = last written frame
        customLayerData = { dictionary warpfem = { bool complete, int framesWritten, ... } }
    )
    def Xform "Root" { def Mesh "<name>" { faceVertexCounts, faceVertexIndices,
                                            points.timeSamples, extent.timeSamples, ... } }

The layer is saved every ``save_every`` frames and on :meth:`UsdMeshWriter.close`, and the end
time code always equals the last frame written, so a run killed part-way leaves a readable file
with the frames up to the last save. Frames are written straight into the USD layer; nothing is
kept in Python lists (the layer itself holds the samples in USD's own memory until the writer is
closed).
"""

from __future__ import annotations

import math
import numbers
import os

import numpy as np

__all__ = ["UsdMeshWriter", "read_usd_mesh_frames", "usd_validation_errors", "UsdWriterError"]

_EXTENSIONS = (".usda", ".usd", ".usdc")
META_KEY = "warpfem"


class UsdWriterError(ValueError):
    """Bad input to :class:`UsdMeshWriter` (names, shapes, frame order, closed writer)."""


def _to_numpy(a):
    if hasattr(a, "numpy") and not isinstance(a, np.ndarray):  # wp.array (CPU or CUDA)
        a = a.numpy()
    return np.asarray(a)


def _open_new_stage(path):
    from pxr import Sdf, Usd

    layer = Sdf.Layer.Find(path)
    if layer is not None:  # the file is open in this process (e.g. a previous writer / reader)
        layer.Clear()
        return Usd.Stage.Open(layer)
    return Usd.Stage.CreateNew(path)


class UsdMeshWriter:
    """Write animated triangle meshes to a USD file (``.usda`` text, ``.usd``/``.usdc`` binary).

    Usage::

        with UsdMeshWriter("out/run.usda", fps=60) as w:
            w.add_mesh("body", faces, num_points)
            for frame in range(n):
                w.write_frame(frame, {"body": points})

    Parameters
    ----------
    path : output file; parent directories are created; an existing file is replaced.
    fps : frames per second (timeCodesPerSecond = framesPerSecond = fps; one time code per frame).
    up_axis : "Y" or "Z".
    meters_per_unit : stage linear unit in metres (1.0 = SI).
    save_every : save the layer every this many written frames (and always on close).
    root_name : name of the root Xform (the stage's defaultPrim).
    """

    def __init__(self, path, *, fps: float, up_axis: str = "Y", meters_per_unit: float = 1.0,
                 save_every: int = 10, root_name: str = "Root"):
        from pxr import Sdf, UsdGeom

        path = os.fspath(path)
        ext = os.path.splitext(path)[1].lower()
        if ext not in _EXTENSIONS:
            raise UsdWriterError(f"{path}: USD file must end in one of {', '.join(_EXTENSIONS)}")
        if not (isinstance(fps, numbers.Real) and math.isfinite(fps) and fps > 0):
            raise UsdWriterError(f"fps must be a positive number, got {fps!r}")
        up = str(up_axis).upper()
        if up not in ("Y", "Z"):
            raise UsdWriterError(f"up_axis must be 'Y' or 'Z', got {up_axis!r}")
        if not (isinstance(meters_per_unit, numbers.Real) and math.isfinite(meters_per_unit) and meters_per_unit > 0):
            raise UsdWriterError(f"meters_per_unit must be a positive number, got {meters_per_unit!r}")
        if not (isinstance(save_every, numbers.Integral) and save_every >= 1):
            raise UsdWriterError(f"save_every must be an integer >= 1, got {save_every!r}")
        if not Sdf.Path.IsValidIdentifier(root_name):
            raise UsdWriterError(f"root_name {root_name!r} is not a valid USD prim name")

        self.path = path
        self.fps = float(fps)
        self.save_every = int(save_every)
        parent = os.path.dirname(os.path.abspath(path))
        os.makedirs(parent, exist_ok=True)

        self._stage = _open_new_stage(path)
        stage = self._stage
        stage.SetTimeCodesPerSecond(self.fps)
        stage.SetFramesPerSecond(self.fps)
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up == "Y" else UsdGeom.Tokens.z)
        UsdGeom.SetStageMetersPerUnit(stage, float(meters_per_unit))
        root = UsdGeom.Xform.Define(stage, Sdf.Path.absoluteRootPath.AppendChild(root_name))
        stage.SetDefaultPrim(root.GetPrim())
        self._root_path = root.GetPath()
        stage.GetRootLayer().documentation = "Written by warpfem (UsdMeshWriter)"

        self._meshes = {}  # name -> (UsdGeom.Mesh, num_points, has_normals)
        self._first_frame = None
        self._last_frame = None
        self._frames_written = 0
        self._unsaved = 0
        self._closed = False
        self._set_status(complete=False)
        self.save()

    # ------------------------------------------------------------------ metadata
    @property
    def frames_written(self) -> int:
        return self._frames_written

    @property
    def last_frame(self):
        """Index of the last frame written (None before the first)."""
        return self._last_frame

    @property
    def closed(self) -> bool:
        return self._closed

    @property
    def stage(self):
        """The open Usd.Stage (None after close)."""
        return self._stage

    def _set_status(self, *, complete: bool, reason: str | None = None):
        info = {"complete": bool(complete), "framesWritten": int(self._frames_written)}
        if self._last_frame is not None:
            info["lastFrame"] = int(self._last_frame)
        if reason:
            info["incompleteReason"] = str(reason)
        layer = self._stage.GetRootLayer()
        data = dict(layer.customLayerData)
        data[META_KEY] = info
        layer.customLayerData = data

    def _check_open(self):
        if self._closed:
            raise UsdWriterError(f"{self.path}: writer is closed")

    # ------------------------------------------------------------------ topology
    def add_mesh(self, name: str, faces, num_points: int):
        """Add a triangle mesh ``name`` (faces (f, 3) indices into its ``num_points`` points).

        Topology is written once (not time-sampled). Returns the prim path as a string.
        """
        from pxr import Sdf, UsdGeom, Vt

        self._check_open()
        if not isinstance(name, str) or not Sdf.Path.IsValidIdentifier(name):
            raise UsdWriterError(f"mesh name {name!r} is not a valid USD prim name (letters, digits, _)")
        if name in self._meshes:
            raise UsdWriterError(f"mesh {name!r} already added")
        if not (isinstance(num_points, numbers.Integral) and num_points > 0):
            raise UsdWriterError(f"mesh {name!r}: num_points must be a positive integer, got {num_points!r}")
        faces = _to_numpy(faces)
        if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] == 0:
            raise UsdWriterError(f"mesh {name!r}: faces must have shape (f, 3) with f > 0, got {faces.shape}")
        if not np.issubdtype(faces.dtype, np.integer):
            raise UsdWriterError(f"mesh {name!r}: faces must be integers, got dtype {faces.dtype}")
        bad = np.nonzero(np.any((faces < 0) | (faces >= num_points), axis=1))[0]
        if bad.size:
            raise UsdWriterError(
                f"mesh {name!r}: face {bad[0]} {faces[bad[0]].tolist()} has an index outside [0, {num_points})"
            )
        mesh = UsdGeom.Mesh.Define(self._stage, self._root_path.AppendChild(name))
        mesh.CreateFaceVertexCountsAttr(Vt.IntArray.FromNumpy(np.full(faces.shape[0], 3, dtype=np.int32)))
        mesh.CreateFaceVertexIndicesAttr(Vt.IntArray.FromNumpy(np.ascontiguousarray(faces.reshape(-1), dtype=np.int32)))
        mesh.CreateSubdivisionSchemeAttr(UsdGeom.Tokens.none)
        mesh.CreateOrientationAttr(UsdGeom.Tokens.rightHanded)
        mesh.CreatePointsAttr()
        mesh.CreateExtentAttr()
        self._meshes[name] = [mesh, int(num_points), False]
        return str(mesh.GetPath())

    # ------------------------------------------------------------------ frames
    def write_frame(self, frame_index: int, points: dict, normals: dict | None = None):
        """Write one frame: ``points[name]`` (p, 3) for meshes added with :meth:`add_mesh`.

        The time code is ``frame_index`` (frames must be written in increasing order). Extent is
        the bounding box of the points written (as float32). ``normals`` optionally maps names
        to per-vertex normals (p, 3). Meshes not given keep their previous sample.
        """
        from pxr import UsdGeom, Vt

        self._check_open()
        if isinstance(frame_index, bool) or not isinstance(frame_index, numbers.Integral):
            raise UsdWriterError(f"frame_index must be an integer, got {frame_index!r}")
        frame_index = int(frame_index)
        if frame_index < 0:
            raise UsdWriterError(f"frame_index must be >= 0, got {frame_index}")
        if self._last_frame is not None and frame_index <= self._last_frame:
            raise UsdWriterError(f"frame {frame_index} written after frame {self._last_frame}: frames must increase")
        if not isinstance(points, dict) or not points:
            raise UsdWriterError("points must be a non-empty dict {mesh name: (p, 3) array}")
        normals = normals or {}
        # validate everything before writing anything, so a bad frame leaves no partial samples
        prepared = []
        for name, pts in points.items():
            if name not in self._meshes:
                raise UsdWriterError(f"unknown mesh {name!r} (add it with add_mesh first; known: {sorted(self._meshes)})")
            n = self._meshes[name][1]
            p = _to_numpy(pts)
            if p.shape != (n, 3):
                raise UsdWriterError(f"frame {frame_index}, mesh {name!r}: points must have shape ({n}, 3), got {p.shape}")
            p = np.ascontiguousarray(p, dtype=np.float32)
            if not np.all(np.isfinite(p)):
                i = int(np.nonzero(~np.all(np.isfinite(p), axis=1))[0][0])
                raise UsdWriterError(f"frame {frame_index}, mesh {name!r}: point {i} is not finite: {p[i].tolist()}")
            nr = None
            if name in normals:
                nr = _to_numpy(normals[name])
                if nr.shape != (n, 3):
                    raise UsdWriterError(f"frame {frame_index}, mesh {name!r}: normals must have shape ({n}, 3), got {nr.shape}")
                nr = np.ascontiguousarray(nr, dtype=np.float32)
                if not np.all(np.isfinite(nr)):
                    raise UsdWriterError(f"frame {frame_index}, mesh {name!r}: non-finite normals")
            prepared.append((name, p, nr))
        for name in normals:
            if name not in points:
                raise UsdWriterError(f"frame {frame_index}: normals given for {name!r} without its points")

        t = float(frame_index)
        for name, p, nr in prepared:
            entry = self._meshes[name]
            mesh = entry[0]
            mesh.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(p), t)
            extent = np.stack([p.min(axis=0), p.max(axis=0)])
            mesh.GetExtentAttr().Set(Vt.Vec3fArray.FromNumpy(extent), t)
            if nr is not None:
                if not entry[2]:
                    mesh.CreateNormalsAttr()
                    mesh.SetNormalsInterpolation(UsdGeom.Tokens.vertex)
                    entry[2] = True
                mesh.GetNormalsAttr().Set(Vt.Vec3fArray.FromNumpy(nr), t)

        if self._first_frame is None:
            self._first_frame = frame_index
            self._stage.SetStartTimeCode(t)
        self._last_frame = frame_index
        self._stage.SetEndTimeCode(t)
        self._frames_written += 1
        self._unsaved += 1
        if self._unsaved >= self.save_every:
            self._set_status(complete=False)
            self.save()

    def save(self):
        """Save the layer now (the file then holds every frame written so far)."""
        self._check_open()
        self._stage.GetRootLayer().Save()
        self._unsaved = 0

    def close(self, complete: bool = True, reason: str | None = None):
        """Record whether the run completed, save, and release the stage. Idempotent."""
        if self._closed:
            return
        self._set_status(complete=complete, reason=None if complete else (reason or "closed before completion"))
        self.save()
        self._closed = True
        self._stage = None
        self._meshes = {}

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close(complete=True)
        else:
            self.close(complete=False, reason=f"{exc_type.__name__}: {exc}")
        return False


# ---------------------------------------------------------------------- reading / checking
def _open_stage(path):
    from pxr import Usd

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"USD file not found: {path}")
    stage = Usd.Stage.Open(path)
    if stage is None:
        raise ValueError(f"{path}: cannot open USD stage")
    return stage


def read_usd_mesh_frames(path, name: str):
    """Read the animation of mesh ``name`` (a child of the default prim, or an absolute prim path).

    Returns ``(times (k,) float64, [points (p, 3) float32 per time sample])``.
    """
    from pxr import UsdGeom

    stage = _open_stage(path)
    if name.startswith("/"):
        prim = stage.GetPrimAtPath(name)
    else:
        root = stage.GetDefaultPrim()
        prim = root.GetChild(name) if root else None
        if prim is None or not prim.IsValid():
            prim = next((p for p in stage.Traverse() if p.GetName() == name), None)
    if prim is None or not prim.IsValid() or not prim.IsA(UsdGeom.Mesh):
        raise KeyError(f"{path}: no mesh named {name!r}")
    attr = UsdGeom.Mesh(prim).GetPointsAttr()
    times = np.array(attr.GetTimeSamples(), dtype=np.float64)
    frames = [np.array(attr.Get(t), dtype=np.float32).reshape(-1, 3) for t in times]
    return times, frames


def usd_validation_errors(stage_or_path, *, include_warnings: bool = False):
    """Run every registered ``pxr.UsdValidation`` validator; return [(type, name, message)] of errors."""
    from pxr import Usd, UsdValidation

    stage = stage_or_path if isinstance(stage_or_path, Usd.Stage) else _open_stage(stage_or_path)
    registry = UsdValidation.ValidationRegistry()
    context = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())
    kinds = {UsdValidation.ValidationErrorType.Error}
    if include_warnings:
        kinds.add(UsdValidation.ValidationErrorType.Warn)
    return [
        (str(e.GetType()).rsplit(".", 1)[-1], e.GetName(), e.GetMessage())
        for e in context.Validate(stage)
        if e.GetType() in kinds
    ]
