"""Device-side skinning: surface positions from simulation positions with a Warp kernel."""

from __future__ import annotations

import numpy as np
import warp as wp

from warpfem.device import get_device as _get_device

from .embedding import Embedding
from .kernels import skin_points_kernel

__all__ = ["SurfaceSkinner", "resolve_precision"]


def resolve_precision(precision):
    """Map "float32"/"float64" (or numpy / Warp float types) to (scalar, vec3) Warp types."""
    if precision is wp.float32:
        return wp.float32, wp.vec3
    if precision is wp.float64:
        return wp.float64, wp.vec3d
    try:
        dt = np.dtype(precision)
    except TypeError:
        dt = None
    if dt == np.float32:
        return wp.float32, wp.vec3
    if dt == np.float64:
        return wp.float64, wp.vec3d
    raise ValueError(f"precision must be 'float32' or 'float64', got {precision!r}")


class SurfaceSkinner:
    """Applies an :class:`Embedding` on the device: ``x_surface = W x``.

    Parameters
    ----------
    embedding : the embedding of the surface points into the mesh (:func:`embed_points` or
        :func:`embed_points_in_mesh`; k weights per point, k = 4, 10, 8 or 27).
    tets : (m, k) element connectivity the embedding was computed with (its ``tet_index`` refers
        to it), or the mesh object itself (``warpfem.mesh.VolumeMesh``).
    device : Warp device ("cpu", "cuda:0", ...); None means the default device.
    precision : "float32" or "float64"; positions are arrays of wp.vec3 / wp.vec3d.
    """

    def __init__(self, embedding: Embedding, tets, *, device=None, precision="float32"):
        if hasattr(tets, "elements"):  # a mesh object (VolumeMesh)
            tets = tets.elements
        elif hasattr(tets, "tets"):
            tets = tets.tets
        tets = np.asarray(tets)
        k = int(np.shape(embedding.weights)[1]) if np.ndim(embedding.weights) == 2 else -1
        if tets.ndim != 2 or tets.shape[1] != k:
            raise ValueError(f"elements must have shape (m, {k}) (k = weights per point of the embedding), got {tets.shape}")
        ti = np.asarray(embedding.tet_index)
        if ti.size and (ti.min() < 0 or ti.max() >= tets.shape[0]):
            raise ValueError(f"embedding refers to tet {int(ti.max())} but the mesh has {tets.shape[0]} tets")
        vids = tets[ti].astype(np.int64)
        if not np.array_equal(vids, np.asarray(embedding.vertex_ids)):
            raise ValueError("embedding was computed with a different element connectivity")
        if embedding.num_vertices >= 2**31:
            raise ValueError("mesh too large for int32 vertex ids")
        self.scalar_type, self.vec_type = resolve_precision(precision)
        self.device = _get_device(device)
        self.num_points = int(ti.shape[0])
        self.weights_per_point = k
        self.num_vertices = int(embedding.num_vertices)
        np_scalar = np.float32 if self.scalar_type == wp.float32 else np.float64
        self.vertex_ids = wp.array(vids.astype(np.int32), dtype=wp.int32, device=self.device)
        self.weights = wp.array(
            np.asarray(embedding.weights, dtype=np_scalar), dtype=self.scalar_type, device=self.device
        )

    def apply(self, x: wp.array, out: wp.array | None = None) -> wp.array:
        """Surface positions (p,) vec3 in the skinner's precision, from mesh positions x (n,)."""
        if not isinstance(x, wp.array):
            raise TypeError(f"x must be a wp.array of {self.vec_type.__name__}, got {type(x).__name__}")
        if x.dtype != self.vec_type:
            raise TypeError(f"x has dtype {x.dtype.__name__}, expected {self.vec_type.__name__} (skinner precision)")
        if x.shape[0] != self.num_vertices:
            raise ValueError(f"x has {x.shape[0]} vertices, the embedding expects {self.num_vertices}")
        if x.device != self.device:
            raise ValueError(f"x is on {x.device}, the skinner is on {self.device}")
        if out is None:
            out = wp.empty(self.num_points, dtype=self.vec_type, device=self.device)
        elif out.dtype != self.vec_type or out.shape[0] != self.num_points or out.device != self.device:
            raise ValueError("out must be a wp.array of the skinner's vec3 type, length num_points, same device")
        if self.num_points:
            wp.launch(
                skin_points_kernel,
                dim=self.num_points,
                inputs=[x, self.vertex_ids, self.weights],
                outputs=[out],
                device=self.device,
            )
        return out

    def apply_numpy(self, x) -> np.ndarray:
        """Same as :meth:`apply` for a numpy (n, 3) array; returns numpy (p, 3)."""
        x = np.asarray(x)
        if x.ndim != 2 or x.shape[1] != 3:
            raise ValueError(f"x must have shape (n, 3), got {x.shape}")
        np_scalar = np.float32 if self.scalar_type == wp.float32 else np.float64
        xw = wp.array(x.astype(np_scalar), dtype=self.vec_type, device=self.device)
        return self.apply(xw).numpy()
