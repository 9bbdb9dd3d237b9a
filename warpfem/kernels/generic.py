"""Declare the float32 and float64 overloads of generic kernels up front.

Warp recompiles a whole module each time a generic kernel meets a new argument type, so a module
whose kernels were instantiated lazily compiled once per new overload. Declaring both precisions
at import time makes each module compile once (per device) with every variant in it.
"""

from __future__ import annotations

import warp as wp

PRECISION_TYPES = (
    {"s": wp.float32, "v": wp.vec3, "m": wp.mat33},
    {"s": wp.float64, "v": wp.vec3d, "m": wp.mat33d},
)


def both_precisions(**roles):
    """Kernel decorator: ``roles`` maps each generic argument to "s" (scalar value), "s[]", "v[]",
    "m[]" (1-d arrays of scalar, vec3, mat33), "s[,]" or "v[,]" (2-d scalar / vec3 arrays)."""

    def decorate(kernel):
        for types in PRECISION_TYPES:
            arg_types = {}
            for arg in kernel.adj.args:
                role = roles.get(arg.label)
                if role is None:
                    arg_types[arg.label] = arg.type
                elif role == "s":
                    arg_types[arg.label] = types["s"]
                elif role in ("s[,]", "v[,]"):
                    arg_types[arg.label] = wp.array2d(dtype=types[role[0]])
                else:
                    arg_types[arg.label] = wp.array(dtype=types[role[0]])
            wp.overload(kernel, arg_types)
        return kernel

    return decorate
