"""Input/output: the run outputs' one protocol (:class:`FrameWriter`, fed a :class:`FrameSnapshot` per
frame), USD export of animated surfaces (pxr imported lazily), streamed npz states readable after any
fault (:func:`read_states`), ParaView collections (.pvd + .vtu) of the volume mesh, the statistics log,
preview pictures (matplotlib, lazily), and the comparison of two runs' outputs (:func:`compare_runs`)."""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the same names for type checkers and the API docs (read statically)
    from .compare import CompareError, compare_runs
    from .states import StatesError, StatesWriter, read_states, recover_states
    from .usd import UsdMeshWriter, UsdWriterError, clip_directory, read_usd_mesh_frames, usd_validation_errors
    from .vtu import (VtuBodiesWriter, VtuSeriesWriter, VtuWriterError, element_stress_fields, read_pvd,
                      warpfem_version)
    from .writers import FrameSnapshot, FrameWriter, OutputWriteError, RunInfo

from warpfem.lazy import lazy_attributes  # noqa: E402

# name -> defining module, imported on first access (PEP 562): checking output paths
# (warpfem.io.outputs) or writing one kind of output does not load the others' modules.
_LAZY = {
    **dict.fromkeys(["CompareError", "compare_runs"], "warpfem.io.compare"),
    **dict.fromkeys(["StatesError", "StatesWriter", "read_states", "recover_states"], "warpfem.io.states"),
    **dict.fromkeys(["UsdMeshWriter", "UsdWriterError", "clip_directory", "read_usd_mesh_frames",
                     "usd_validation_errors"], "warpfem.io.usd"),
    **dict.fromkeys(["VtuBodiesWriter", "VtuSeriesWriter", "VtuWriterError", "element_stress_fields", "read_pvd",
                     "warpfem_version"], "warpfem.io.vtu"),
    **dict.fromkeys(["FrameSnapshot", "FrameWriter", "OutputWriteError", "RunInfo"], "warpfem.io.writers"),
}

__all__ = ["UsdMeshWriter", "UsdWriterError", "clip_directory", "read_usd_mesh_frames", "usd_validation_errors",
           "StatesWriter", "StatesError", "read_states", "recover_states", "VtuSeriesWriter", "VtuBodiesWriter",
           "VtuWriterError", "element_stress_fields", "read_pvd", "warpfem_version", "compare_runs", "CompareError",
           "FrameWriter", "FrameSnapshot", "RunInfo", "OutputWriteError"]


__getattr__, __dir__ = lazy_attributes(__name__, _LAZY)
