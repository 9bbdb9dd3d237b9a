"""Input/output: USD export of animated surfaces (pxr imported lazily), streamed npz states, ParaView
collections (.pvd + .vtu) of the volume mesh, preview pictures (matplotlib, lazily), and the comparison of
two runs' outputs (:func:`compare_runs`)."""

from .compare import CompareError, compare_runs
from .states import StatesWriter
from .vtu import VtuBodiesWriter, VtuSeriesWriter, VtuWriterError, element_stress_fields, read_pvd, warpfem_version
from .usd import UsdMeshWriter, UsdWriterError, clip_directory, read_usd_mesh_frames, usd_validation_errors

__all__ = ["UsdMeshWriter", "UsdWriterError", "clip_directory", "read_usd_mesh_frames", "usd_validation_errors",
           "StatesWriter", "VtuSeriesWriter", "VtuBodiesWriter", "VtuWriterError", "element_stress_fields", "read_pvd",
           "warpfem_version", "compare_runs", "CompareError"]
