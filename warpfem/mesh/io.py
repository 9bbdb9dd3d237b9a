"""Reading and writing volume meshes through meshio (.mesh, .msh, .vtu, .vtk, ...).

``load_mesh`` / ``save_mesh``: Tet4 (``tetra`` cells); surface files (.obj, .off, .ply, .stl) are
tetrahedralised on load (see ``tetrahedralization.py``). ``load_element_mesh`` /
``save_element_mesh``: any registered element type (its ``meshio_cell``)."""

from __future__ import annotations

import os

import numpy as np

from .element_types import ELEMENTS, get_element
from .volume_mesh import MeshError, VolumeMesh

__all__ = ["load_mesh", "save_mesh", "load_element_mesh", "save_element_mesh"]


def load_mesh(path, *, inside_surface=False, max_edge_length=None, max_radius_edge_ratio=None, mesher=None,
              cache=None, target_tets=None, prim=None, coarsen_only=False, **kw):
    """Load the ``tetra`` cells of any meshio-readable file as a Tet4 ``VolumeMesh``.

    A surface file (.obj, .off, .ply, .stl: chosen by the extension) is checked and
    tetrahedralised instead, through a cache (``warpfem.mesh.tetrahedralize_file``,
    needs ``pip install warpfem[mesh]``); ``max_edge_length``, ``max_radius_edge_ratio``,
    ``mesher``, ``target_tets`` (about this many tets, within 10 %: a finer surface is meshed coarser,
    a coarser one finer unless ``coarsen_only``), ``coarsen_only`` and ``cache`` apply to such files
    only (``MeshError`` for a tet file).

    Other cell types (surface triangles, lines, ...) are ignored, except with
    ``inside_surface=True``: then only the tets inside the closed surface formed by the file's
    triangle cells are kept (for convex-hull tetrahedralisations such as libigl's bunny.mesh);
    ``vertex_map`` still maps file vertex indices to mesh indices. ``kw`` goes to ``VolumeMesh``
    (``reorient``, ``remove_unreferenced``). Errors and warnings name the file.

    A USD file (.usd, .usda, .usdc) holds a ``UsdGeom.TetMesh`` (read as it is) or a closed
    ``UsdGeom.Mesh`` (tetrahedralised, not cached): ``prim`` names the prim path, default the file's
    only one (:func:`warpfem.mesh.usd_in.load_usd_mesh`).
    """
    import meshio

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"mesh file not found: {path}")
    from .usd_in import is_usd_path, load_usd_mesh

    if is_usd_path(path):
        if inside_surface:
            raise MeshError(f"{path}: inside_surface applies to tet files with triangle cells, not to USD files")
        return load_usd_mesh(path, prim=prim, max_edge_length=max_edge_length, max_radius_edge_ratio=max_radius_edge_ratio,
                             mesher=mesher, target_tets=target_tets, **kw)
    if prim is not None:
        raise MeshError(f"{path}: prim applies to USD files (.usd, .usda, .usdc) only")
    from .tetrahedralization import SURFACE_EXTENSIONS, tetrahedralize_file

    tetra_opts = {"max_edge_length": max_edge_length, "max_radius_edge_ratio": max_radius_edge_ratio,
                  "mesher": mesher, "cache": cache, "target_tets": target_tets}
    if coarsen_only:
        tetra_opts["coarsen_only"] = True

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
        return VolumeMesh(points.astype(np.float64), tets, **kw)

    from .region import tets_inside_surface

    tris = [c.data for c in m.cells if c.type == "triangle" and len(c.data)]
    if not tris:
        raise MeshError(f"{path}: inside_surface=True but the file has no triangle cells")
    kw["remove_unreferenced"] = False
    full = VolumeMesh(points.astype(np.float64), tets, **kw)
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


def load_element_mesh(path, *, element_type=None):
    """Read a meshio file with the volume cells of one registered element type (``tetra``,
    ``tetra10``, ``hexahedron``, ``hexahedron27``, ...: each type's ``meshio_cell``).

    With ``element_type=None`` the file must hold volume cells of exactly one of these types
    (other cells, e.g. surface triangles, are ignored). Unreferenced points are kept. Errors name
    the file and the cell types found.
    """
    import meshio

    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"mesh file not found: {path}")
    try:
        m = meshio.read(path)
    except Exception as exc:
        raise MeshError(f"{path}: meshio could not read the file: {type(exc).__name__}: {exc}") from exc
    to_type = {e.meshio_cell: name for name, e in ELEMENTS.items()}
    found = {to_type[c.type] for c in m.cells if c.type in to_type and len(c.data)}
    if element_type is not None:
        found &= {get_element(element_type).name}
    if len(found) != 1:
        types = sorted({f"{c.type} ({len(c.data)})" for c in m.cells}) or ["none"]
        what = "no supported volume cells" if not found else f"several volume cell types {sorted(found)} (pass element_type=)"
        raise MeshError(f"{path}: {what}; cell types in file: {', '.join(types)}")
    element = get_element(found.pop())
    data = np.concatenate([c.data for c in m.cells if c.type == element.meshio_cell and len(c.data)])
    points = np.asarray(m.points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise MeshError(f"{path}: points must be 3D, got shape {points.shape}")
    import warnings

    with warnings.catch_warnings():  # kept unreferenced points (e.g. Gmsh geometry points) are expected here
        warnings.filterwarnings("ignore", message=".*unreferenced vertices kept")
        return VolumeMesh(points, data.astype(np.int64), element, remove_unreferenced=False, name=path)


def save_element_mesh(mesh, path, **kw):
    """Write a mesh of any element type (nodes + its cells) with meshio; the format comes from the
    extension (".msh" writes Gmsh 4.1 ASCII). ``kw`` goes to ``meshio.write``."""
    import meshio

    path = os.fspath(path)
    cells = [(get_element(mesh.element_type).meshio_cell, np.asarray(mesh.elements, dtype=np.int64))]
    if path.endswith(".msh"):  # Gmsh (meshio would otherwise pick ANSYS, which has no quadratic cells)
        kw.setdefault("file_format", "gmsh")
        kw.setdefault("binary", False)
    meshio.write(path, meshio.Mesh(np.asarray(mesh.vertices, dtype=np.float64), cells), **kw)
    return path
