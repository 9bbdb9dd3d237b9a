"""Input/output: the run outputs' one protocol (:class:`FrameWriter`, fed a :class:`FrameSnapshot` per
frame), USD export of animated surfaces (pxr imported lazily), streamed npz states readable after any
fault (:func:`read_states`), ParaView collections (.pvd + .vtu) of the volume mesh, the statistics log,
preview pictures (matplotlib, lazily), and the comparison of two runs' outputs (:func:`compare_runs`)."""

from .compare import CompareError, compare_runs
from .states import StatesError, StatesWriter, read_states, recover_states
from .vtu import VtuBodiesWriter, VtuSeriesWriter, VtuWriterError, element_stress_fields, read_pvd, warpfem_version
from .usd import UsdMeshWriter, UsdWriterError, clip_directory, read_usd_mesh_frames, usd_validation_errors
from .writers import FrameSnapshot, FrameWriter, OutputWriteError, RunInfo

__all__ = ["UsdMeshWriter", "UsdWriterError", "clip_directory", "read_usd_mesh_frames", "usd_validation_errors",
           "StatesWriter", "StatesError", "read_states", "recover_states", "VtuSeriesWriter", "VtuBodiesWriter",
           "VtuWriterError", "element_stress_fields", "read_pvd", "warpfem_version", "compare_runs", "CompareError",
           "FrameWriter", "FrameSnapshot", "RunInfo", "OutputWriteError"]
