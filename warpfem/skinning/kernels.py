"""Warp kernel for x_surface = W x (4 weights per surface point), generic over float32/float64."""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def skin_points_kernel(
    x: wp.array(dtype=Any),  # (n,) vec3 / vec3d mesh positions
    vertex_ids: wp.array2d(dtype=wp.int32),  # (p, 4)
    weights: wp.array2d(dtype=Any),  # (p, 4) float32 / float64
    out: wp.array(dtype=Any),  # (p,) vec3 / vec3d surface positions
):
    i = wp.tid()
    s = weights[i, 0] * x[vertex_ids[i, 0]]
    s += weights[i, 1] * x[vertex_ids[i, 1]]
    s += weights[i, 2] * x[vertex_ids[i, 2]]
    s += weights[i, 3] * x[vertex_ids[i, 3]]
    out[i] = s
