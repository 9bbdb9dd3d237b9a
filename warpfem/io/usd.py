"""Animated triangle meshes to USD (one UsdGeom.Mesh per surface, points time-sampled per frame).

``pxr`` is imported lazily inside functions so that importing warpfem does not need usd-core.

Memory is bounded by splitting the animation into **value clips** (USD's mechanism for
animation spread over several layers). For ``out/run.usda`` the writer produces::

    out/run.usda                     the stage: metadata, topology, clip metadata (no samples)
    out/run.clips/manifest.usda      which attributes the clips animate (points, extent, normals)
    out/run.clips/clip_000000.usdc   frames [0, clip_frames)           time samples only
    out/run.clips/clip_000001.usdc   frames [clip_frames, 2 clip_frames)  ...

The main layer::

    #usda 1.0
    (
        defaultPrim = "Root"  upAxis = "Y"  metersPerUnit = 1
        timeCodesPerSecond = fps  framesPerSecond = fps
        startTimeCode = first frame  endTimeCode = last written frame
        customLayerData = { dictionary warpfem = { bool complete, int framesWritten, ... } }
    )
    def Xform "Root" (clips = { dictionary default = { asset[] assetPaths, double2[] active,
                                 string primPath = "/Root", asset manifestAssetPath } })
    { def Mesh "<name>" { faceVertexCounts, faceVertexIndices, points, extent (declared) } }

Clip time = stage time (no ``times`` mapping); clip k is active from its first frame on. The
writer authors the layers with Sdf and keeps no ``Usd.Stage`` open (a stage would open every clip
it composes). At most one clip layer is open at a time: it holds at most ``clip_frames`` frames, is saved every
``save_every`` frames and released when full, so the writer's memory does not grow with the run.
After each save the main layer lists the clips written so far and its end time code is the last
frame written, so a run killed or failing part-way leaves a readable stage with the frames up to
the last save. ``clip_frames=None`` writes every sample into the main layer instead (one
self-contained file; the layer then keeps the whole animation in memory until closed).
"""

from __future__ import annotations

import math
import numbers
import os
import re

import numpy as np

from .writers import FrameWriter

__all__ = ["UsdMeshWriter", "UsdOutput", "read_usd_mesh_frames", "usd_validation_errors", "UsdWriterError",
           "clip_directory"]

_EXTENSIONS = (".usda", ".usd", ".usdc")
META_KEY = "warpfem"
_CLIP_RE = re.compile(r"^clip_\d{6}\.usdc$")


class UsdWriterError(ValueError):
    """Bad input to :class:`UsdMeshWriter` (names, shapes, frame order, closed writer)."""


def _to_numpy(a):
    if hasattr(a, "numpy") and not isinstance(a, np.ndarray):  # wp.array (CPU or CUDA)
        a = a.numpy()
    return np.asarray(a)


def clip_directory(path) -> str:
    """The folder holding the value clips of USD file ``path`` (``out/run.usda`` -> ``out/run.clips``)."""
    path = os.fspath(path)
    return os.path.splitext(path)[0] + ".clips"


def _new_layer(path):
    """A new empty layer at ``path``; a layer of that name already open in this process (a previous
    writer or a reader) is cleared and reused."""
    from pxr import Sdf

    layer = Sdf.Layer.Find(path)
    if layer is not None:
        layer.Clear()
    else:
        layer = Sdf.Layer.CreateNew(path)
        if layer is None:  # pragma: no cover - pxr raises on failure
            raise UsdWriterError(f"{path}: cannot create USD layer")
    return layer


# (attribute name, Sdf value type name) of the animated attributes
_ANIMATED = (("points", "Point3fArray"), ("extent", "Float3Array"), ("normals", "Normal3fArray"))
#: a rigid body's Xform: its pose as one 4x4 matrix (row vectors: [[A^T, 0], [p, 1]])
_TRANSFORM = "xformOp:transform"
_TYPES = dict(_ANIMATED, **{_TRANSFORM: "Matrix4d"})


class UsdMeshWriter:
    """Write animated triangle meshes to a USD file (``.usda`` text, ``.usd``/``.usdc`` binary).

    Usage::

        with UsdMeshWriter("out/run.usda", fps=60) as w:
            w.add_mesh("body", faces, num_points)
            for frame in range(n):
                w.write_frame(frame, {"body": points})

    Parameters
    ----------
    path : output file; parent directories are created; an existing file is replaced (and stale
        clips of a previous run in its clip folder are removed).
    fps : frames per second (timeCodesPerSecond = framesPerSecond = fps; one time code per frame).
    up_axis : "Y" or "Z".
    meters_per_unit : stage linear unit in metres (1.0 = SI).
    save_every : save every this many written frames (and always on close and when a clip is full).
    clip_frames : frames per value-clip layer (binary ``.usdc`` files in :func:`clip_directory`);
        the writer never holds more than this many frames in memory. ``None``: no clips, every
        sample in the main file (memory grows with the run).
    root_name : name of the root Xform (the stage's defaultPrim).
    """

    def __init__(self, path, *, fps: float, up_axis: str = "Y", meters_per_unit: float = 1.0,
                 save_every: int = 10, clip_frames: int | None = 100, root_name: str = "Root"):
        from pxr import Sdf, Usd, UsdGeom

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
        if isinstance(save_every, bool) or not (isinstance(save_every, numbers.Integral) and save_every >= 1):
            raise UsdWriterError(f"save_every must be an integer >= 1, got {save_every!r}")
        if clip_frames is not None and (isinstance(clip_frames, bool) or not (
                isinstance(clip_frames, numbers.Integral) and clip_frames >= 1)):
            raise UsdWriterError(f"clip_frames must be an integer >= 1 or None, got {clip_frames!r}")
        if not Sdf.Path.IsValidIdentifier(root_name):
            raise UsdWriterError(f"root_name {root_name!r} is not a valid USD prim name")

        self.path = path
        self.fps = float(fps)
        self.save_every = int(save_every)
        self.clip_frames = None if clip_frames is None else int(clip_frames)
        parent = os.path.dirname(os.path.abspath(path))
        os.makedirs(parent, exist_ok=True)
        self.clip_dir = clip_directory(path) if self.clip_frames is not None else None
        self._remove_stale_clips()
        if self.clip_dir is not None:
            os.makedirs(self.clip_dir, exist_ok=True)

        self._layer = _new_layer(path)
        stage = Usd.Stage.Open(self._layer)  # stage metadata through the Usd API, then released
        stage.SetTimeCodesPerSecond(self.fps)
        stage.SetFramesPerSecond(self.fps)
        UsdGeom.SetStageUpAxis(stage, UsdGeom.Tokens.y if up == "Y" else UsdGeom.Tokens.z)
        UsdGeom.SetStageMetersPerUnit(stage, float(meters_per_unit))
        root = UsdGeom.Xform.Define(stage, Sdf.Path.absoluteRootPath.AppendChild(root_name))
        stage.SetDefaultPrim(root.GetPrim())
        self._root_path = root.GetPath()
        self._layer.documentation = "Written by warpfem (UsdMeshWriter)"
        del stage, root

        self._meshes = {}  # name -> [UsdGeom.Mesh, num_points, has_normals]
        self._last = {}  # name -> {attr: last value written} (re-written for meshes a frame omits)
        self._first_frame = None
        self._last_frame = None
        self._frames_written = 0
        self._unsaved = 0
        self._closed = False
        # value clips: the open clip layer, its frame count, and the clips written so far
        self._clip = None
        self._clip_count = 0
        self._clip_assets = []  # relative asset paths
        self._clip_starts = []  # first frame of each clip
        self._manifest_attrs = set()  # (mesh name, attr) declared in the manifest
        self._manifest_written = set()
        self._peak_frames_in_memory = 0
        self._set_status(complete=False)
        self.save()

    @classmethod
    def resume(cls, path, last_frame: int, *, save_every: int = 10) -> "UsdMeshWriter":
        """Reopen a file written by this writer to continue after frame ``last_frame``: its meshes,
        clips and frames 0..``last_frame`` are kept as they are, every later sample (and clip) is
        removed, and :meth:`write_frame` continues from ``last_frame + 1``. The file must hold
        ``last_frame`` (:class:`UsdWriterError` otherwise)."""
        from pxr import Sdf

        path = os.fspath(path)
        k = int(last_frame)
        if not os.path.isfile(path):
            raise UsdWriterError(f"{path}: cannot continue it: no such file")
        layer = Sdf.Layer.FindOrOpen(path)
        if layer is None:  # pragma: no cover - pxr raises on failure
            raise UsdWriterError(f"{path}: cannot open it")
        layer.Reload(True)
        info = dict(layer.customLayerData).get(META_KEY)
        if not info or not layer.defaultPrim:
            raise UsdWriterError(f"{path}: cannot continue it: not written by warpfem's UsdMeshWriter")
        self = cls.__new__(cls)
        self.path, self.fps, self.save_every = path, float(layer.timeCodesPerSecond), int(save_every)
        self.clip_frames = int(info["clipFrames"]) if "clipFrames" in info else None
        self.clip_dir = clip_directory(path) if self.clip_frames is not None else None
        self._layer = layer
        self._root_path = Sdf.Path.absoluteRootPath.AppendChild(layer.defaultPrim)
        root = layer.GetPrimAtPath(self._root_path)
        self._clip, self._clip_count, self._clip_assets, self._clip_starts = None, 0, [], []
        holder = layer  # the layer with the samples of frame k
        removed = 0
        if self.clip_frames is not None:
            clips = (root.GetInfo("clips") or {}).get("default", {}) if root.HasInfo("clips") else {}
            assets = [a.path for a in clips.get("assetPaths", [])]
            starts = [int(a[0]) for a in clips.get("active", [])]
            keep = [i for i, s in enumerate(starts) if s <= k]
            if not keep:
                raise UsdWriterError(f"{path}: cannot continue after frame {k}: it holds no frame up to it")
            base = os.path.dirname(os.path.abspath(path))
            for i in range(keep[-1] + 1, len(assets)):  # clips wholly after frame k
                f = os.path.join(base, assets[i])
                if os.path.exists(f):
                    removed += len(Sdf.Layer.FindOrOpen(f).ListAllTimeSamples())
                    os.remove(f)
            self._clip_assets, self._clip_starts = assets[:len(keep)], starts[:len(keep)]
            holder = Sdf.Layer.FindOrOpen(os.path.join(base, assets[keep[-1]]))
            holder.Reload(True)
        times = sorted(holder.ListAllTimeSamples())
        if float(k) not in times:
            have = f"frames up to {int(max(times))}" if times else "no frame"
            raise UsdWriterError(f"{path}: cannot continue after frame {k}: it holds {have}")
        self._meshes, self._last = {}, {}
        for prim in root.nameChildren:
            if prim.typeName == "Xform" and _TRANSFORM in prim.attributes:  # a rigid body
                apath = self._root_path.AppendChild(prim.name).AppendProperty(_TRANSFORM)
                for t in holder.ListTimeSamplesForPath(apath):
                    if t > k:
                        holder.EraseTimeSample(apath, t)
                self._meshes[prim.name] = [prim, None, False]
                value = holder.QueryTimeSample(apath, float(k)) if holder.GetAttributeAtPath(apath) else None
                if value is not None:
                    self._last.setdefault(prim.name, {})[_TRANSFORM] = np.array(value, dtype=np.float64).reshape(4, 4)
                continue
            if prim.typeName not in ("Mesh", "TetMesh"):
                continue
            name = prim.name
            self._meshes[name] = [prim, 0, "normals" in prim.attributes]
            for attr, _ in _ANIMATED:
                apath = self._root_path.AppendChild(name).AppendProperty(attr)
                for t in holder.ListTimeSamplesForPath(apath):
                    if t > k:
                        holder.EraseTimeSample(apath, t)
                value = holder.QueryTimeSample(apath, float(k)) if holder.GetAttributeAtPath(apath) else None
                if value is not None:
                    value = np.array(value, dtype=np.float32).reshape(-1, 3)
                    self._last.setdefault(name, {})[attr] = value
                    if attr == "points":
                        self._meshes[name][1] = len(value)
        removed += sum(1 for t in times if t > k)
        self._manifest_attrs = {(n, a) for n, e in self._meshes.items()
                                for a in ((_TRANSFORM,) if e[1] is None else
                                          ("points", "extent") + (("normals",) if e[2] else ()))}
        self._manifest_written = set(self._manifest_attrs)
        self._first_frame = int(layer.startTimeCode) if layer.HasStartTimeCode() else None
        self._last_frame = k
        self._frames_written = int(info.get("framesWritten", 0)) - removed
        self._unsaved = 0
        self._closed = False
        self._peak_frames_in_memory = 0
        if self.clip_frames is not None:
            self._clip = holder
            self._clip_count = len([t for t in holder.ListAllTimeSamples() if t <= k])
            self._clip.Save()
            if self._clip_count >= self.clip_frames:
                self._clip = None
        self._set_status(complete=False)
        self.save()
        return self

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
    def layer(self):
        """The main Sdf.Layer (None after close)."""
        return self._layer

    @property
    def num_clips(self) -> int:
        """Value-clip layers written so far (0 with ``clip_frames=None``)."""
        return len(self._clip_assets)

    def frames_in_memory(self) -> int:
        """Distinct time codes held by the layers this writer has open (main + current clip):
        at most ``clip_frames`` with clips."""
        if self._closed:
            return 0
        times = set(self._layer.ListAllTimeSamples())
        if self._clip is not None:
            times |= set(self._clip.ListAllTimeSamples())
        return len(times)

    @property
    def peak_frames_in_memory(self) -> int:
        """Largest :meth:`frames_in_memory` seen after any :meth:`write_frame`."""
        return self._peak_frames_in_memory

    def _set_status(self, *, complete: bool, reason: str | None = None):
        info = {"complete": bool(complete), "framesWritten": int(self._frames_written)}
        if self._last_frame is not None:
            info["lastFrame"] = int(self._last_frame)
        if self.clip_frames is not None:
            info["clipFrames"] = int(self.clip_frames)
            info["clips"] = len(self._clip_assets)
        if reason:
            info["incompleteReason"] = str(reason)
        data = dict(self._layer.customLayerData)
        data[META_KEY] = info
        self._layer.customLayerData = data

    def _check_open(self):
        if self._closed:
            raise UsdWriterError(f"{self.path}: writer is closed")

    def _remove_stale_clips(self):
        """Delete clip files of an earlier run written to the same path (they would be unreferenced)."""
        d = clip_directory(self.path)
        if not os.path.isdir(d):
            return
        for f in os.listdir(d):
            if _CLIP_RE.match(f) or f == "manifest.usda":
                os.remove(os.path.join(d, f))
        if self.clip_frames is None and not os.listdir(d):
            os.rmdir(d)

    # ------------------------------------------------------------------ topology
    def add_mesh(self, name: str, faces, num_points: int):
        """Add a triangle mesh ``name`` (faces (f, 3) indices into its ``num_points`` points).

        Topology is written once (not time-sampled) into the main layer. Returns the prim path.
        """
        from pxr import Sdf, UsdGeom, Vt

        self._check_open()
        if not isinstance(name, str) or not Sdf.Path.IsValidIdentifier(name):
            raise UsdWriterError(f"mesh name {name!r} is not a valid USD prim name (letters, digits, _)")
        if name in self._meshes:
            raise UsdWriterError(f"mesh {name!r} already added")
        if isinstance(num_points, bool) or not (isinstance(num_points, numbers.Integral) and num_points > 0):
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
        prim = Sdf.CreatePrimInLayer(self._layer, self._root_path.AppendChild(name))
        prim.specifier = Sdf.SpecifierDef
        prim.typeName = "Mesh"
        tn = Sdf.ValueTypeNames
        for attr, type_name, value, uniform in (
                ("faceVertexCounts", tn.IntArray, Vt.IntArray.FromNumpy(np.full(faces.shape[0], 3, dtype=np.int32)), False),
                ("faceVertexIndices", tn.IntArray, Vt.IntArray.FromNumpy(np.ascontiguousarray(faces.reshape(-1), dtype=np.int32)), False),
                ("subdivisionScheme", tn.Token, UsdGeom.Tokens.none, True),
                ("orientation", tn.Token, UsdGeom.Tokens.rightHanded, True),
                ("points", tn.Point3fArray, None, False),
                ("extent", tn.Float3Array, None, False)):
            spec = Sdf.AttributeSpec(prim, attr, type_name, Sdf.VariabilityUniform if uniform else Sdf.VariabilityVarying)
            if value is not None:
                spec.default = value
        mesh = prim
        self._meshes[name] = [mesh, int(num_points), False]
        self._manifest_attrs |= {(name, "points"), (name, "extent")}
        return str(prim.path)

    def add_rigid_mesh(self, name: str, faces, points):
        """Add a rigid body ``name``: an Xform whose transform (``xformOp:transform``, a 4x4 matrix
        written by :meth:`write_frame`'s ``transforms``) moves the Mesh ``name/mesh`` of ``points``
        (written once, relative to the body's centre of mass). Returns the Xform's prim path."""
        from pxr import Sdf, UsdGeom, Vt

        self._check_open()
        if not isinstance(name, str) or not Sdf.Path.IsValidIdentifier(name):
            raise UsdWriterError(f"mesh name {name!r} is not a valid USD prim name (letters, digits, _)")
        if name in self._meshes:
            raise UsdWriterError(f"mesh {name!r} already added")
        faces = np.asarray(_to_numpy(faces), dtype=np.int64)
        pts = np.ascontiguousarray(_to_numpy(points), dtype=np.float32)
        if pts.ndim != 2 or pts.shape[1] != 3 or not len(pts) or not np.all(np.isfinite(pts)):
            raise UsdWriterError(f"rigid mesh {name!r}: points must be finite, of shape (p, 3), got {pts.shape}")
        if faces.ndim != 2 or faces.shape[1] != 3 or not len(faces) or faces.min() < 0 or faces.max() >= len(pts):
            raise UsdWriterError(f"rigid mesh {name!r}: faces must have shape (f, 3) with indices in [0, {len(pts)})")
        xf = Sdf.CreatePrimInLayer(self._layer, self._root_path.AppendChild(name))
        xf.specifier, xf.typeName = Sdf.SpecifierDef, "Xform"
        tn = Sdf.ValueTypeNames
        Sdf.AttributeSpec(xf, _TRANSFORM, tn.Matrix4d)
        order = Sdf.AttributeSpec(xf, "xformOpOrder", tn.TokenArray, Sdf.VariabilityUniform)
        order.default = Vt.TokenArray([_TRANSFORM])
        prim = Sdf.CreatePrimInLayer(self._layer, self._root_path.AppendChild(name).AppendChild("mesh"))
        prim.specifier, prim.typeName = Sdf.SpecifierDef, "Mesh"
        for attr, type_name, value, uniform in (
                ("faceVertexCounts", tn.IntArray, Vt.IntArray.FromNumpy(np.full(faces.shape[0], 3, dtype=np.int32)), False),
                ("faceVertexIndices", tn.IntArray, Vt.IntArray.FromNumpy(np.ascontiguousarray(faces.reshape(-1), dtype=np.int32)), False),
                ("subdivisionScheme", tn.Token, UsdGeom.Tokens.none, True),
                ("orientation", tn.Token, UsdGeom.Tokens.rightHanded, True),
                ("points", tn.Point3fArray, Vt.Vec3fArray.FromNumpy(pts), False),
                ("extent", tn.Float3Array, Vt.Vec3fArray.FromNumpy(np.stack([pts.min(axis=0), pts.max(axis=0)])), False)):
            spec = Sdf.AttributeSpec(prim, attr, type_name, Sdf.VariabilityUniform if uniform else Sdf.VariabilityVarying)
            spec.default = value
        self._meshes[name] = [xf, None, False]  # num_points None: a rigid body (transforms, not points)
        self._manifest_attrs.add((name, _TRANSFORM))
        return str(xf.path)

    def add_tet_mesh(self, name: str, tets, num_points: int, surface_faces=None):
        """Add a volume ``name``: a ``UsdGeom.TetMesh`` over ``num_points`` points with tetrahedra
        ``tets`` (m, 4), positively oriented (its right-handed faces point out, as USD's
        ``ComputeSurfaceFaces`` expects), and optionally its outward ``surfaceFaceVertexIndices``
        (f, 3). Its points are animated by :meth:`write_frame` like a mesh's. Returns the prim path."""
        from pxr import Sdf, UsdGeom, Vt

        self._check_open()
        if not isinstance(name, str) or not Sdf.Path.IsValidIdentifier(name):
            raise UsdWriterError(f"tet mesh name {name!r} is not a valid USD prim name (letters, digits, _)")
        if name in self._meshes:
            raise UsdWriterError(f"mesh {name!r} already added")
        if isinstance(num_points, bool) or not (isinstance(num_points, numbers.Integral) and num_points > 0):
            raise UsdWriterError(f"tet mesh {name!r}: num_points must be a positive integer, got {num_points!r}")
        tets = _to_numpy(tets)
        if tets.ndim != 2 or tets.shape[1] != 4 or tets.shape[0] == 0 or not np.issubdtype(tets.dtype, np.integer):
            raise UsdWriterError(f"tet mesh {name!r}: tets must be integers of shape (m, 4) with m > 0, got {tets.shape}")
        if tets.min() < 0 or tets.max() >= num_points:
            raise UsdWriterError(f"tet mesh {name!r}: a tet vertex index is outside [0, {num_points})")
        prim = Sdf.CreatePrimInLayer(self._layer, self._root_path.AppendChild(name))
        prim.specifier = Sdf.SpecifierDef
        prim.typeName = "TetMesh"
        tn = Sdf.ValueTypeNames
        values = [("tetVertexIndices", tn.Int4Array, Vt.Vec4iArray.FromNumpy(np.ascontiguousarray(tets, dtype=np.int32)), False),
                  ("orientation", tn.Token, UsdGeom.Tokens.rightHanded, True),
                  ("points", tn.Point3fArray, None, False), ("extent", tn.Float3Array, None, False)]
        if surface_faces is not None:
            f = np.asarray(_to_numpy(surface_faces), dtype=np.int64).reshape(-1, 3)
            values.append(("surfaceFaceVertexIndices", tn.Int3Array, Vt.Vec3iArray.FromNumpy(np.ascontiguousarray(f, dtype=np.int32)),
                           False))
        for attr, type_name, value, uniform in values:
            spec = Sdf.AttributeSpec(prim, attr, type_name, Sdf.VariabilityUniform if uniform else Sdf.VariabilityVarying)
            if value is not None:
                spec.default = value
        self._meshes[name] = [prim, int(num_points), False]
        self._manifest_attrs |= {(name, "points"), (name, "extent")}
        return str(prim.path)

    # ------------------------------------------------------------------ frames
    def write_frame(self, frame_index: int, points: dict, normals: dict | None = None, transforms: dict | None = None):
        """Write one frame: ``points[name]`` (p, 3) for meshes added with :meth:`add_mesh`.

        The time code is ``frame_index`` (frames must be written in increasing order). Extent is
        the bounding box of the points written (as float32). ``normals`` optionally maps names
        to per-vertex normals (p, 3). ``transforms`` maps rigid meshes (:meth:`add_rigid_mesh`) to
        their 4x4 pose. Meshes not given keep their previous values (re-written at this time code, so
        every clip is self-contained).
        """
        from pxr import Sdf, UsdGeom

        self._check_open()
        if isinstance(frame_index, bool) or not isinstance(frame_index, numbers.Integral):
            raise UsdWriterError(f"frame_index must be an integer, got {frame_index!r}")
        frame_index = int(frame_index)
        if frame_index < 0:
            raise UsdWriterError(f"frame_index must be >= 0, got {frame_index}")
        if self._last_frame is not None and frame_index <= self._last_frame:
            raise UsdWriterError(f"frame {frame_index} written after frame {self._last_frame}: frames must increase")
        transforms = transforms or {}
        if not isinstance(points, dict) or not (points or transforms):
            raise UsdWriterError("points must be a non-empty dict {mesh name: (p, 3) array}")
        normals = normals or {}
        # validate everything before writing anything, so a bad frame leaves no partial samples
        prepared = {}
        for name, M in transforms.items():
            if name not in self._meshes or self._meshes[name][1] is not None:
                raise UsdWriterError(f"unknown rigid mesh {name!r} (add it with add_rigid_mesh first)")
            M = np.asarray(M, dtype=np.float64)
            if M.shape != (4, 4) or not np.all(np.isfinite(M)):
                raise UsdWriterError(f"frame {frame_index}, rigid mesh {name!r}: the transform must be a finite 4x4 matrix")
            prepared[name] = {_TRANSFORM: M}
        for name, pts in points.items():
            if name not in self._meshes or self._meshes[name][1] is None:
                raise UsdWriterError(f"unknown mesh {name!r} (add it with add_mesh first; known: {sorted(self._meshes)})")
            n = self._meshes[name][1]
            p = _to_numpy(pts)
            if p.shape != (n, 3):
                raise UsdWriterError(f"frame {frame_index}, mesh {name!r}: points must have shape ({n}, 3), got {p.shape}")
            p = np.ascontiguousarray(p, dtype=np.float32)
            if not np.all(np.isfinite(p)):
                i = int(np.nonzero(~np.all(np.isfinite(p), axis=1))[0][0])
                raise UsdWriterError(f"frame {frame_index}, mesh {name!r}: point {i} is not finite: {p[i].tolist()}")
            values = {"points": p, "extent": np.stack([p.min(axis=0), p.max(axis=0)])}
            if name in normals:
                nr = _to_numpy(normals[name])
                if nr.shape != (n, 3):
                    raise UsdWriterError(f"frame {frame_index}, mesh {name!r}: normals must have shape ({n}, 3), got {nr.shape}")
                nr = np.ascontiguousarray(nr, dtype=np.float32)
                if not np.all(np.isfinite(nr)):
                    raise UsdWriterError(f"frame {frame_index}, mesh {name!r}: non-finite normals")
                values["normals"] = nr
            prepared[name] = values
        for name in normals:
            if name not in points:
                raise UsdWriterError(f"frame {frame_index}: normals given for {name!r} without its points")

        for name, values in prepared.items():
            entry = self._meshes[name]
            if "normals" in values and not entry[2]:
                spec = Sdf.AttributeSpec(entry[0], "normals", Sdf.ValueTypeNames.Normal3fArray)
                spec.SetInfo("interpolation", UsdGeom.Tokens.vertex)
                entry[2] = True
                self._manifest_attrs.add((name, "normals"))
            self._last.setdefault(name, {}).update(values)
        if self.clip_frames is not None and (self._clip is None or self._clip_count >= self.clip_frames):
            self._start_clip(frame_index)
        layer = self._clip if self._clip is not None else self._layer
        t = float(frame_index)
        for name, values in self._last.items():  # meshes omitted from this frame keep their last values
            for attr, value in values.items():
                self._set_sample(layer, name, attr, t, value)

        if self._first_frame is None:
            self._first_frame = frame_index
            self._layer.startTimeCode = t
        self._last_frame = frame_index
        self._frames_written += 1
        self._clip_count += 1
        self._unsaved += 1
        self._peak_frames_in_memory = max(self._peak_frames_in_memory, self.frames_in_memory())
        if self._unsaved >= self.save_every or (self.clip_frames is not None and self._clip_count >= self.clip_frames):
            self.save()
            if self.clip_frames is not None and self._clip_count >= self.clip_frames:
                self._clip = None  # full: saved and released (the next frame opens a new clip)

    def _set_sample(self, layer, name, attr, t, value):
        from pxr import Sdf, Vt

        path = self._root_path.AppendChild(name).AppendProperty(attr)
        if layer.GetAttributeAtPath(path) is None:
            prim = Sdf.CreatePrimInLayer(layer, path.GetPrimPath())
            Sdf.AttributeSpec(prim, attr, getattr(Sdf.ValueTypeNames, _TYPES[attr]))
        if attr == _TRANSFORM:
            from pxr import Gf

            layer.SetTimeSample(path, t, Gf.Matrix4d(*np.asarray(value, dtype=np.float64).ravel().tolist()))
        else:
            layer.SetTimeSample(path, t, Vt.Vec3fArray.FromNumpy(value))

    def _start_clip(self, frame_index):
        index = len(self._clip_assets)
        fname = f"clip_{index:06d}.usdc"
        self._clip = _new_layer(os.path.join(self.clip_dir, fname))
        self._clip_count = 0
        self._clip_assets.append(f"./{os.path.basename(self.clip_dir)}/{fname}")
        self._clip_starts.append(int(frame_index))

    def _write_manifest(self):
        """The clip manifest: every attribute the clips animate, declared without values."""
        from pxr import Sdf

        layer = _new_layer(os.path.join(self.clip_dir, "manifest.usda"))
        for name, attr in sorted(self._manifest_attrs):
            prim = Sdf.CreatePrimInLayer(layer, self._root_path.AppendChild(name))
            Sdf.AttributeSpec(prim, attr, getattr(Sdf.ValueTypeNames, _TYPES[attr]))
        layer.Save()
        self._manifest_written = set(self._manifest_attrs)

    def _update_clip_metadata(self):
        """The ``clips`` metadata of the root prim (Sdf: no stage, so no clip is opened)."""
        from pxr import Sdf, Vt

        if self._manifest_attrs != self._manifest_written:
            self._write_manifest()
        clips = {"default": {
            "assetPaths": Sdf.AssetPathArray([Sdf.AssetPath(a) for a in self._clip_assets]),
            "primPath": str(self._root_path),
            "active": Vt.Vec2dArray([(float(s), float(i)) for i, s in enumerate(self._clip_starts)]),
            "manifestAssetPath": Sdf.AssetPath(f"./{os.path.basename(self.clip_dir)}/manifest.usda"),
        }}
        self._layer.GetPrimAtPath(self._root_path).SetInfo("clips", clips)

    @property
    def unsaved_frames(self) -> int:
        """Frames written since the last :meth:`save`."""
        return self._unsaved

    def save(self):
        """Save now: the current clip, then the main layer (clip list, status, end time code), so
        the file holds every frame written so far."""
        self._check_open()
        if self._clip is not None:
            self._clip.Save()
        if self.clip_frames is not None and self._clip_assets:
            self._update_clip_metadata()
        if self._last_frame is not None:
            self._layer.endTimeCode = float(self._last_frame)
        if not getattr(self, "_closing", False):
            self._set_status(complete=False)
        self._layer.Save()
        self._unsaved = 0

    def close(self, complete: bool = True, reason: str | None = None):
        """Record whether the run completed, save, and release the layers. Idempotent."""
        if self._closed:
            return
        self._set_status(complete=complete, reason=None if complete else (reason or "closed before completion"))
        self._closing = True
        self.save()
        self._closed = True
        self._layer = None
        self._clip = None
        self._meshes = {}
        self._last = {}

    def __enter__(self):
        return self

    def __exit__(self, exc_type, exc, tb):
        if exc_type is None:
            self.close(complete=True)
        else:
            self.close(complete=False, reason=f"{exc_type.__name__}: {exc}")
        return False


class UsdOutput(FrameWriter):
    """``[output] usd``: the render surfaces (and ``usd_volume`` tet meshes, colliders) of every frame
    through a :class:`UsdMeshWriter` (options ``up_axis``, ``clip_frames``; 0 = no clips). A
    snapshot with ``sync`` saves the file, so that it holds that frame after a kill."""

    label = "[output] usd"

    def __init__(self, path, **options):
        super().__init__(path, **options)
        self._w = None

    def open(self, run):
        self._run, self._pending = run, None
        if run.resume_after is not None:
            self._w = UsdMeshWriter.resume(self.path, run.resume_after)

    def _make(self):
        """The stage (pxr imported here) with the run's prims, and the frame kept until now."""
        run = self._run
        o = run.options
        self._w = UsdMeshWriter(self.path, fps=run.fps, up_axis=o.get("up_axis", "Y"),
                                clip_frames=o.get("clip_frames", 100) or None)
        for name, faces, count in run.surfaces:
            self._w.add_mesh(name, faces, count)
        for name, faces, local in run.rigid_surfaces:
            self._w.add_rigid_mesh(name, faces, local)
        for name, tets, faces, lo, hi in run.volumes:
            self._w.add_tet_mesh(name, tets, hi - lo, surface_faces=faces)
        for name, faces, count in run.colliders:
            self._w.add_mesh(name, faces, count)
        if self._pending is not None:
            self._w.write_frame(*self._pending)
            self._pending = None

    def write(self, snapshot):
        if self._w is None and self._pending is None and not snapshot.sync:
            # the start (frame 0) is kept in memory and the stage made with the next frame: the USD
            # library (~0.2 s to import) does not hold up the first step
            self._pending = (snapshot.frame, {k: np.array(v, copy=True) for k, v in snapshot.surface_points.items()},
                             None, {k: np.array(v, copy=True) for k, v in snapshot.transforms.items()})
            return
        if self._w is None:
            self._make()
        self._w.write_frame(snapshot.frame, snapshot.surface_points, transforms=snapshot.transforms)
        if snapshot.sync and self._w.unsaved_frames:
            self._w.save()

    def close(self, complete, reason=None):
        if self._w is None and self._pending is not None:  # stopped before frame 1: frame 0 is still written
            self._make()
        if self._w is not None:
            self._w.close(complete=complete, reason=reason)

    def abandon(self):
        self._w = None


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
