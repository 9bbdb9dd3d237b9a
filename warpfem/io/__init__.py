"""Input/output: USD export of animated surfaces (pxr imported lazily), streamed npz states."""

from .states import StatesWriter
from .usd import UsdMeshWriter, UsdWriterError, clip_directory, read_usd_mesh_frames, usd_validation_errors

__all__ = ["UsdMeshWriter", "UsdWriterError", "clip_directory", "read_usd_mesh_frames", "usd_validation_errors",
           "StatesWriter"]
