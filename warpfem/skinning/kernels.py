"""Warp kernel for x_surface = W x (k weights per surface point), generic over float32/float64."""

from typing import Any

import warp as wp

wp.set_module_options({"enable_backward": False})


@wp.kernel
def skin_points_kernel(
    x: wp.array(dtype=Any),  # (n,) vec3 / vec3d mesh positions
    vertex_ids: wp.array2d(dtype=wp.int32),  # (p, k): k = 4 (tet4), 10 (tet10), 8 (hex8), 27 (hex27)
    weights: wp.array2d(dtype=Any),  # (p, k) float32 / float64
    out: wp.array(dtype=Any),  # (p,) vec3 / vec3d surface positions
):
    i = wp.tid()
    s = weights[i, 0] * x[vertex_ids[i, 0]]
    for a in range(1, vertex_ids.shape[1]):
        s += weights[i, a] * x[vertex_ids[i, a]]
    out[i] = s
