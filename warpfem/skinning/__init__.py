"""Embedding a render surface in the volume mesh (barycentric / shape-function skinning), numpy and Warp."""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the same names for type checkers and the API docs (read statically)
    from .embedding import Embedding, barycentric_coordinates, embed_points, embed_points_in_mesh, point_tet_distance
    from .skinner import SurfaceSkinner, resolve_precision
    from .surface import SurfaceError, boundary_faces, load_surface, mesh_boundary_surface

from warpfem.lazy import lazy_attributes  # noqa: E402

# name -> defining module, imported on first access (PEP 562): a scene's default render surface (the
# mesh boundary, numpy only) does not load the skinning kernels.
_LAZY = {
    **dict.fromkeys(["Embedding", "barycentric_coordinates", "embed_points", "embed_points_in_mesh",
                     "point_tet_distance"], "warpfem.skinning.embedding"),
    **dict.fromkeys(["SurfaceSkinner", "resolve_precision"], "warpfem.skinning.skinner"),
    **dict.fromkeys(["SurfaceError", "boundary_faces", "load_surface", "mesh_boundary_surface"],
                    "warpfem.skinning.surface"),
}

__all__ = [
    "Embedding",
    "embed_points",
    "embed_points_in_mesh",
    "barycentric_coordinates",
    "point_tet_distance",
    "SurfaceSkinner",
    "resolve_precision",
    "boundary_faces",
    "mesh_boundary_surface",
    "load_surface",
    "SurfaceError",
]


__getattr__, __dir__ = lazy_attributes(__name__, _LAZY)
