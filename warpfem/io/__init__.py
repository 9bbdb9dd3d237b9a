"""Input/output: USD export of animated surfaces (pxr imported lazily), streamed npz states, ParaView
collections (.pvd + .vtu) of the volume mesh, preview pictures (matplotlib, lazily), and the comparison of
two runs' outputs (:func:`compare_runs`)."""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the same names for type checkers and the API docs (read statically)
    from .compare import CompareError, compare_runs
    from .states import StatesWriter
    from .usd import UsdMeshWriter, UsdWriterError, clip_directory, read_usd_mesh_frames, usd_validation_errors
    from .vtu import (VtuBodiesWriter, VtuSeriesWriter, VtuWriterError, element_stress_fields, read_pvd,
                      warpfem_version)

from warpfem.lazy import lazy_attributes  # noqa: E402

# name -> defining module, imported on first access (PEP 562): checking output paths
# (warpfem.io.outputs) or writing one kind of output does not load the others' modules.
_LAZY = {
    **dict.fromkeys(["CompareError", "compare_runs"], "warpfem.io.compare"),
    "StatesWriter": "warpfem.io.states",
    **dict.fromkeys(["UsdMeshWriter", "UsdWriterError", "clip_directory", "read_usd_mesh_frames",
                     "usd_validation_errors"], "warpfem.io.usd"),
    **dict.fromkeys(["VtuBodiesWriter", "VtuSeriesWriter", "VtuWriterError", "element_stress_fields", "read_pvd",
                     "warpfem_version"], "warpfem.io.vtu"),
}

__all__ = ["UsdMeshWriter", "UsdWriterError", "clip_directory", "read_usd_mesh_frames", "usd_validation_errors",
           "StatesWriter", "VtuSeriesWriter", "VtuBodiesWriter", "VtuWriterError", "element_stress_fields", "read_pvd",
           "warpfem_version", "compare_runs", "CompareError"]


__getattr__, __dir__ = lazy_attributes(__name__, _LAZY)
