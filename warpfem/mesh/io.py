"""Reading and writing tet meshes through meshio (.mesh, .msh, .vtu, .vtk, ...); surface files
(.obj, .off, .ply, .stl) are tetrahedralised on load (see ``tetrahedralization.py``)."""

from __future__ import annotations

import os

import numpy as np

from .tetmesh import MeshError, TetMesh

__all__ = ["load_mesh", "save_mesh"]


def load_mesh(path, *, inside_surface=False, max_edge_length=None, max_radius_edge_ratio=None, mesher=None,
              cache=None, **kw):
    """Load the ``tetra`` cells of any meshio-readable file as a ``TetMesh``.

    A surface file (.obj, .off, .ply, .stl: chosen by the extension) is checked and
    tetrahedralised instead, through a cache (``warpfem.mesh.tetrahedralize_file``,
    needs ``pip install warpfem[mesh]``); ``max_edge_length``, ``max_radius_edge_ratio``,
    ``mesher`` and ``cache`` apply to such files only (``MeshError`` for a tet file).

    Other cell types (surface triangles, lines, ...) are ignored, except with
    ``inside_surface=True``: then only the tets inside the closed surface formed by the file's
    triangle cells are kept (for convex-hull tetrahedralisations such as libigl's bunny.mesh);
    ``vertex_map`` still maps file vertex indices to mesh indices. ``kw`` goes to ``TetMesh``
    (``reorient``, ``remove_unreferenced``). Errors and warnings name the file.
    """
    import meshio

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"mesh file not found: {path}")
    from .tetrahedralization import SURFACE_EXTENSIONS, tetrahedralize_file

    tetra_opts = {"max_edge_length": max_edge_length, "max_radius_edge_ratio": max_radius_edge_ratio,
                  "mesher": mesher, "cache": cache}

    def surface():
        if inside_surface:
            raise MeshError(f"{path}: inside_surface applies to tet files; this is a surface file, tetrahedralised as a whole")
        opts = {k: v for k, v in tetra_opts.items() if v is not None}
        return tetrahedralize_file(path, **opts)

    if os.path.splitext(path)[1].lower() in SURFACE_EXTENSIONS:
        return surface()
    try:
        m = meshio.read(path)
    except Exception as exc:  # meshio raises ReadError / ValueError / KeyError on bad input
        raise MeshError(f"{path}: meshio could not read the file: {type(exc).__name__}: {exc}") from exc

    blocks = [c.data for c in m.cells if c.type == "tetra" and len(c.data)]
    given = [k for k, v in tetra_opts.items() if v is not None]
    if blocks and given:
        raise MeshError(f"{path}: {', '.join(given)} only apply to surface files (tetrahedralised on load); "
                        "this file already holds tets")
    if not blocks:
        found = sorted({f"{c.type} ({len(c.data)})" for c in m.cells}) or ["none"]
        hint = ""
        if any(c.type in ("triangle", "quad") and len(c.data) for c in m.cells):
            hint = f" (a closed surface? save it as {'/'.join(SURFACE_EXTENSIONS)} to tetrahedralise it on load)"
        raise MeshError(f"{path}: no tetra cells found; cell types in file: {', '.join(found)}{hint}")
    tets = np.concatenate(blocks, axis=0)
    points = np.asarray(m.points)
    if points.ndim == 2 and points.shape[1] == 2:
        raise MeshError(f"{path}: points are 2D, a tet mesh needs 3D points")
    kw.setdefault("name", path)
    if not inside_surface:
        return TetMesh(points.astype(np.float64), tets, **kw)

    from .region import tets_inside_surface

    tris = [c.data for c in m.cells if c.type == "triangle" and len(c.data)]
    if not tris:
        raise MeshError(f"{path}: inside_surface=True but the file has no triangle cells")
    kw["remove_unreferenced"] = False
    full = TetMesh(points.astype(np.float64), tets, **kw)
    mask = tets_inside_surface(full, np.concatenate(tris, axis=0))
    if not mask.any():
        raise MeshError(f"{path}: no tets inside the triangle surface")
    # full keeps every file vertex, so the submesh's vertex_map maps file indices directly.
    return full.submesh(mask)


def save_mesh(mesh, path, **kw):
    """Write ``mesh`` (vertices + tetra cells) with meshio; format from the extension.

    ``kw`` goes to ``meshio.write`` (e.g. ``file_format="gmsh22"``).
    """
    import meshio

    path = os.fspath(path)
    out = meshio.Mesh(np.asarray(mesh.vertices, dtype=np.float64),
                      [("tetra", np.asarray(mesh.tets, dtype=np.int64))])
    if path.endswith(".msh"):
        kw.setdefault("binary", False)
    meshio.write(path, out, **kw)
    return path
