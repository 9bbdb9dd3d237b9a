"""Tet meshes: ``TetMesh`` with validation, box generator, file I/O, boundary faces, mass, and
tetrahedralisation of closed surfaces (optional mesher: ``pip install warpfem[mesh]``)."""

from .box import HEX_TO_TETS, box_tet_mesh
from .io import load_mesh, save_mesh
from .mass import consistent_mass, lumped_mass
from .select import select_vertices_in_box
from .tetmesh import TET_FACES, MeshError, TetMesh, boundary_faces, tet_volumes
from .tetrahedralization import (MesherNotInstalled, Tetrahedralization, check_surface, read_surface, tetrahedralize,
                             tetrahedralize_file)

__all__ = [
    "TetMesh",
    "MeshError",
    "box_tet_mesh",
    "load_mesh",
    "save_mesh",
    "lumped_mass",
    "consistent_mass",
    "boundary_faces",
    "select_vertices_in_box",
    "tet_volumes",
    "TET_FACES",
    "HEX_TO_TETS",
    "tetrahedralize",
    "tetrahedralize_file",
    "check_surface",
    "read_surface",
    "Tetrahedralization",
    "MesherNotInstalled",
]
