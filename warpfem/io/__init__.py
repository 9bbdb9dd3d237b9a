"""Input/output: USD export of animated surfaces (pxr imported lazily)."""

from .usd import UsdMeshWriter, UsdWriterError, read_usd_mesh_frames, usd_validation_errors

__all__ = ["UsdMeshWriter", "UsdWriterError", "read_usd_mesh_frames", "usd_validation_errors"]
