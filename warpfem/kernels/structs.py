"""Warp structs that bundle the arguments every quadrature-point kernel shares (as ``warp.fem``
passes its ``Arg`` structs), so a kernel reads ``qp_energy_kernel(x, points, material, energy_out)``.

- ``QuadraturePoints``: one set of quadrature points and the mesh they live on: rest positions
  ``X`` (vec3 per vertex), flat connectivity ``elements`` with ``k`` nodes per element, and per
  point q its element ``element[q]``, weight ``weight[q]`` (Gauss weight x det J, the volume it
  represents, m^3) and shape-function gradients ``dNdX[q * k + a]`` (docs/design.md).
- ``MaterialParams``: the material ``kind`` (int, see ``warpfem.materials``) and the two kernel
  parameters ``mu``, ``lam`` (``Material.kernel_mu`` / ``kernel_lam``, Pa).
- ``WarpedTets``: the fixed data of the stiffness-warping kernels (``kernels.warping``): rest
  positions ``X``, Tet4 connectivity ``elements`` (4 per tet), ``dNdX[e * 4 + a]`` and the rest
  stiffness blocks ``Ke[(e * 4 + a) * 4 + b]`` (N/m).

Warp structs are not generic, so each exists once per precision (``QuadraturePoints32`` /
``QuadraturePoints64``, ``MaterialParams32`` / ``MaterialParams64``, ``WarpedTets32`` /
``WarpedTets64``), made by :func:`_make_struct`; generic kernels declare them with the roles "qp",
"mat" and "tets" of
:func:`warpfem.kernels.generic.both_precisions`. Build instances with :func:`quadrature_points` and
:func:`material_params`, which pick the type from the scalar type.

Instances are treated as values: code that changes what a kernel should see builds a new instance
(or assigns a field of the one it owns; the recorded launches of ``generic.launch`` read the
instance's own C buffer, so an assigned field is seen by the next launch either way).
"""

from __future__ import annotations

import warp as wp

__all__ = [
    "QuadraturePoints32", "QuadraturePoints64", "MaterialParams32", "MaterialParams64", "WarpedTets32",
    "WarpedTets64", "quadrature_points", "material_params", "warped_tets", "STRUCT_TYPES",
]


def _make_struct(name: str, fields: dict):
    """A ``wp.struct`` named ``name`` (its Warp key and C++ name) with ``fields`` (name -> type)."""
    cls = type(name, (), {"__annotations__": dict(fields), "__module__": __name__, "__qualname__": name,
                          "__doc__": f"Warp struct {name}: {', '.join(fields)} (see warpfem.kernels.structs)."})
    return wp.struct(cls)


def _quadrature_points(name, s, v):
    return _make_struct(name, {
        "X": wp.array(dtype=v),            # rest positions (m), per vertex
        "elements": wp.array(dtype=wp.int32),  # flat connectivity, k per element
        "k": int,                          # nodes per element
        "element": wp.array(dtype=wp.int32),   # point -> element
        "weight": wp.array(dtype=s),       # Gauss weight x det J (m^3)
        "dNdX": wp.array(dtype=v),         # dN_a/dX at point q: [q * k + a] (1/m)
    })


def _material_params(name, s):
    return _make_struct(name, {"kind": int, "mu": s, "lam": s})


def _warped_tets(name, v, m):
    return _make_struct(name, {"X": wp.array(dtype=v), "elements": wp.array(dtype=wp.int32),
                               "dNdX": wp.array(dtype=v), "Ke": wp.array(dtype=m)})


QuadraturePoints32 = _quadrature_points("QuadraturePoints32", wp.float32, wp.vec3)
QuadraturePoints64 = _quadrature_points("QuadraturePoints64", wp.float64, wp.vec3d)
MaterialParams32 = _material_params("MaterialParams32", wp.float32)
MaterialParams64 = _material_params("MaterialParams64", wp.float64)
WarpedTets32 = _warped_tets("WarpedTets32", wp.vec3, wp.mat33)
WarpedTets64 = _warped_tets("WarpedTets64", wp.vec3d, wp.mat33d)

#: scalar type -> {"qp": points struct, "mat": material struct, "tets": stiffness-warping struct}
STRUCT_TYPES = {
    wp.float32: {"qp": QuadraturePoints32, "mat": MaterialParams32, "tets": WarpedTets32},
    wp.float64: {"qp": QuadraturePoints64, "mat": MaterialParams64, "tets": WarpedTets64},
}


def _types(scalar):
    try:
        return STRUCT_TYPES[scalar]
    except KeyError:
        raise TypeError(f"kernel structs exist for wp.float32 and wp.float64, not {scalar!r}") from None


def quadrature_points(scalar, X, elements, k: int, element, weight, dNdX):
    """A ``QuadraturePoints32/64`` (by ``scalar``) over device arrays already in that precision."""
    p = _types(scalar)["qp"]()
    p.X, p.elements, p.k, p.element, p.weight, p.dNdX = X, elements, int(k), element, weight, dNdX
    return p


def material_params(scalar, kind: int, mu: float, lam: float):
    """A ``MaterialParams32/64`` (by ``scalar``): material ``kind`` and kernel parameters mu, lam."""
    m = _types(scalar)["mat"]()
    m.kind, m.mu, m.lam = int(kind), scalar(mu), scalar(lam)
    return m


def warped_tets(scalar, X, elements, dNdX, Ke):
    """A ``WarpedTets32/64`` (by ``scalar``) over device arrays already in that precision."""
    t = _types(scalar)["tets"]()
    t.X, t.elements, t.dNdX, t.Ke = X, elements, dNdX, Ke
    return t
