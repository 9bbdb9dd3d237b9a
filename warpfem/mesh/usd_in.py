"""Meshes from USD files: a ``UsdGeom.TetMesh`` (a volume, read as Tet4) or a closed ``UsdGeom.Mesh``
(a surface, tetrahedralised like .obj/.off/.ply/.stl files: :func:`warpfem.mesh.tetrahedralize`).

``pxr`` (usd-core) is imported when a USD file is read. Points are taken at the prim's earliest time
sample (its default value when it has none) and moved to world space by the prim's transform, so a
mesh placed under transformed Xforms loads where it is shown. Every error names the file and the prim.
"""

from __future__ import annotations

import os

import numpy as np

from .volume_mesh import MeshError, VolumeMesh

__all__ = ["USD_EXTENSIONS", "is_usd_path", "read_usd_geometry", "load_usd_mesh"]

USD_EXTENSIONS = (".usd", ".usda", ".usdc")


def is_usd_path(path) -> bool:
    return os.path.splitext(os.fspath(path))[1].lower() in USD_EXTENSIONS


def _candidates(stage):
    from pxr import UsdGeom

    return [p for p in stage.Traverse() if p.IsA(UsdGeom.TetMesh) or p.IsA(UsdGeom.Mesh)]


def read_usd_geometry(path, prim=None):
    """``(kind, vertices (n, 3) float64 in world space, cells, prim path)`` of a USD file's mesh prim:
    kind "tets" with cells (m, 4) for a TetMesh, "surface" with triangles (f, 3) for a Mesh (polygons
    fanned into triangles, left-handed orientation flipped so that triangles are right-handed).

    ``prim``: the prim path ("/World/Bunny"); default the file's only TetMesh or Mesh prim (an error
    lists them when there are several). Raises :class:`MeshError` naming the file and prim.
    """
    from pxr import Usd, UsdGeom

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"mesh file not found: {path}")
    try:
        stage = Usd.Stage.Open(path)
    except Exception as exc:  # pxr raises Tf.ErrorException on unreadable layers
        raise MeshError(f"{path}: cannot open as a USD stage: {str(exc).strip().splitlines()[-1] if str(exc).strip() else exc}") from exc
    if stage is None:
        raise MeshError(f"{path}: cannot open as a USD stage")
    found = _candidates(stage)
    listed = ", ".join(f"{p.GetPath()} ({p.GetTypeName()})" for p in found) or "none"
    if prim is None:
        if not found:
            raise MeshError(f"{path}: no UsdGeom.TetMesh or UsdGeom.Mesh prim in the file")
        if len(found) > 1:
            raise MeshError(f"{path}: {len(found)} mesh prims ({listed}); choose one with prim = \"<path>\" "
                            "([mesh].prim in a scene)")
        p = found[0]
    else:
        if not isinstance(prim, str) or not prim.startswith("/"):
            raise MeshError(f"{path}: prim must be an absolute prim path such as \"/World/Bunny\", got {prim!r}")
        p = stage.GetPrimAtPath(prim)
        if not p or not p.IsValid():
            raise MeshError(f"{path}: no prim {prim!r}; TetMesh / Mesh prims in the file: {listed}")
        if not (p.IsA(UsdGeom.TetMesh) or p.IsA(UsdGeom.Mesh)):
            raise MeshError(f"{path}: prim {prim!r} is a {p.GetTypeName() or 'typeless prim'}, not a UsdGeom.TetMesh "
                            f"or UsdGeom.Mesh; TetMesh / Mesh prims in the file: {listed}")
    where = f"{path}: prim {str(p.GetPath())!r}"
    geom = UsdGeom.PointBased(p)
    attr = geom.GetPointsAttr()
    t = Usd.TimeCode.EarliestTime() if attr.GetNumTimeSamples() else Usd.TimeCode.Default()
    pts = attr.Get(t)
    V = np.asarray(pts, dtype=np.float64).reshape(-1, 3) if pts is not None else np.zeros((0, 3))
    if len(V) == 0:
        raise MeshError(f"{where}: has no points")
    if not np.all(np.isfinite(V)):
        i = int(np.nonzero(~np.all(np.isfinite(V), axis=1))[0][0])
        raise MeshError(f"{where}: point {i} is not finite: {V[i].tolist()}")
    M = np.asarray(UsdGeom.Xformable(p).ComputeLocalToWorldTransform(t), dtype=np.float64)  # row-vector convention
    if not np.allclose(M, np.eye(4)):
        V = V @ M[:3, :3] + M[3, :3]
    left = UsdGeom.Gprim(p).GetOrientationAttr().Get() == UsdGeom.Tokens.leftHanded
    if p.IsA(UsdGeom.TetMesh):
        raw = UsdGeom.TetMesh(p).GetTetVertexIndicesAttr().Get(t)
        T = np.asarray(raw, dtype=np.int64).reshape(-1, 4) if raw is not None else np.zeros((0, 4), dtype=np.int64)
        if len(T) == 0:
            raise MeshError(f"{where}: TetMesh has no tetrahedra (tetVertexIndices is empty)")
        bad = np.nonzero(np.any((T < 0) | (T >= len(V)), axis=1))[0]
        if bad.size:
            raise MeshError(f"{where}: tet {int(bad[0])} {T[bad[0]].tolist()} has a vertex index outside [0, {len(V)})")
        if left:
            T = T[:, [0, 2, 1, 3]]
        return "tets", V, T, str(p.GetPath())
    mesh = UsdGeom.Mesh(p)
    counts = mesh.GetFaceVertexCountsAttr().Get(t)
    idx = mesh.GetFaceVertexIndicesAttr().Get(t)
    counts = np.asarray(counts if counts is not None else [], dtype=np.int64)
    idx = np.asarray(idx if idx is not None else [], dtype=np.int64)
    if counts.size == 0:
        raise MeshError(f"{where}: Mesh has no faces")
    if np.any(counts < 3):
        f = int(np.nonzero(counts < 3)[0][0])
        raise MeshError(f"{where}: face {f} has {int(counts[f])} vertices (faces need at least 3)")
    if counts.sum() != idx.size:
        raise MeshError(f"{where}: faceVertexCounts sum to {int(counts.sum())} but faceVertexIndices has {idx.size} entries")
    if idx.size and (idx.min() < 0 or idx.max() >= len(V)):
        raise MeshError(f"{where}: a face vertex index is outside [0, {len(V)})")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    tris = []
    for k in range(3, int(counts.max()) + 1):  # fan every polygon of k vertices: (0, j, j + 1)
        s = starts[counts == k]
        for j in range(1, k - 1):
            tris.append(np.stack([idx[s], idx[s + j], idx[s + j + 1]], axis=1))
    F = np.concatenate(tris)
    if left:
        F = F[:, [0, 2, 1]]
    return "surface", V, F, str(p.GetPath())


def load_usd_mesh(path, *, prim=None, max_edge_length=None, max_radius_edge_ratio=None, mesher=None, target_tets=None,
                  **kw):
    """A Tet4 ``VolumeMesh`` from a USD file: a TetMesh prim as it is, or a closed Mesh prim
    tetrahedralised (the options of :func:`warpfem.mesh.tetrahedralize`; an open or dirty surface is
    refused naming the file and prim). ``kw`` goes to ``VolumeMesh`` for a TetMesh."""
    kind, V, cells, prim_path = read_usd_geometry(path, prim)
    name = f"{os.fspath(path)}:{prim_path}"
    if kind == "tets":
        kw.setdefault("name", name)
        return VolumeMesh(V, cells, **kw)
    from .tetrahedralization import tetrahedralize

    opts = {k: v for k, v in dict(max_edge_length=max_edge_length, max_radius_edge_ratio=max_radius_edge_ratio,
                                  mesher=mesher, target_tets=target_tets).items() if v is not None}
    mesh = tetrahedralize(V, cells, name=name, **opts)
    mesh.usd_surface = (V, cells)  # the prim's own triangles (a render surface at full resolution)
    return mesh
