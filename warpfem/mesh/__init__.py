"""Volume meshes: ``VolumeMesh`` (any registered element type, validated), generators, file I/O,
boundary faces, mass, point location and tetrahedralisation of closed surfaces (optional mesher:
``pip install warpfem[mesh]``); the element types themselves are in ``element_types/``."""

from .box import HEX_TO_TETS, box_hex_mesh, box_tet_mesh, icosphere_surface, tet10_from_tet4
from .io import load_element_mesh, load_mesh, save_element_mesh, save_mesh
from .locate import embed_points_in_elements
from .mass import consistent_mass, element_mass_matrices, lumped_mass, mass_matrices
from .select import select_vertices_in_box
from .volume_mesh import TET_FACES, ElementMesh, MeshError, TetMesh, VolumeMesh, boundary_faces, tet_volumes
from .tetrahedralization import (MesherNotInstalled, Tetrahedralization, check_surface, read_surface, tetrahedralize,
                                 tetrahedralize_file)

__all__ = [
    "VolumeMesh",
    "TetMesh",
    "ElementMesh",
    "MeshError",
    "box_tet_mesh",
    "icosphere_surface",
    "box_hex_mesh",
    "tet10_from_tet4",
    "load_mesh",
    "save_mesh",
    "load_element_mesh",
    "save_element_mesh",
    "embed_points_in_elements",
    "lumped_mass",
    "consistent_mass",
    "mass_matrices",
    "element_mass_matrices",
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
