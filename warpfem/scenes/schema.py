"""TOML scene schema and validation (pure Python: no Warp, no kernels, no mesh loading).

A scene file is parsed into a plain, fully validated :class:`SceneSpec` (dicts of checked values
with defaults filled in) before anything is built. Every problem raises :class:`SceneError`
naming the file, the key (``[section].key`` or ``[[fixed]] #2.box_min``) and, for misspelt keys,
the closest known key.

The schema is data (``SCHEMA``) so that other modules can add keys; integrator types add their own
``[integrator]`` keys through :func:`warpfem.scenes.register_integrator`.
"""

from __future__ import annotations

import difflib
import math
import numbers
import os
from dataclasses import dataclass, field
from typing import Any, Callable

try:  # Python 3.11+
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib

from warpfem.contact.colliders import COLLIDER_TYPES, collider_scene_keys
from warpfem.materials import MATERIAL_TYPES  # importing the package registers every material

__all__ = ["SceneError", "Key", "SCHEMA", "SceneSpec", "parse_scene_file", "parse_scene_dict",
           "INTEGRATOR_KEYS", "ELEMENTS", "INTEGRATOR_ELEMENTS"]


class SceneError(ValueError):
    """An invalid scene: the message names the file, the key and what is wrong."""


# ----------------------------------------------------------------------------- key specs
@dataclass
class Key:
    """One allowed key: its kind, default and range check.

    kind: "float", "int", "bool", "str", "vec3", "int3", "path", "choice", "stiffness" (a number or "auto").
    check: optional ``f(value) -> str | None`` returning a problem description.
    """

    kind: str
    default: Any = None
    required: bool = False
    choices: tuple = ()
    check: Callable[[Any], str | None] | None = None
    doc: str = ""


#: ``[mesh] target_tets`` of a surface file when neither it nor max_edge_length is given (measured
#: error against cost: docs/meshing.md, kernels_bench/bench_target_tets.py)
TARGET_TETS_DEFAULT = 20_000


def _positive(v):
    return None if v > 0 else "must be > 0"


def _non_negative(v):
    return None if v >= 0 else "must be >= 0"


def _unit_interval(v):
    return None if 0 < v < 1 else "must be in (0, 1)"


def _poisson(v):
    return None if -1.0 < v < 0.5 else "must be in (-1, 0.5) (nu >= 0.5 is incompressible, not supported)"


def _positive_int3(v):
    return None if all(c >= 1 for c in v) else "must be 3 integers >= 1"


def _positive_vec3(v):
    return None if all(c > 0 for c in v) else "must be 3 numbers > 0"


def _components(v):
    ok = bool(v) and all(c in "xyz" for c in v) and len(set(v)) == len(v)
    return None if ok else "must be a non-empty subset of 'xyz' without repeats, e.g. \"xyz\", \"z\", \"xz\""


# Elements a scene may name ([mesh].element) -> what it is: every registered element type
# (warpfem.mesh.element_types; see docs/elements.md), with the type object's own description.
# Scene._make_mesh asks the type object: generator = "box" -> ``box_mesh`` (tet4 / tet10 split each
# cell into 6 tets, tet10 adding shared edge mid-nodes; hex8 / hex27 one hexahedron per cell); a
# tet file or a tetrahedralised surface -> ``from_tet4`` (tet4, tet10); otherwise a file with the
# type's own cells (meshio cell type ``meshio_cell``).
from warpfem.mesh.element_types import ELEMENTS as _ELEMENT_TYPES  # noqa: E402

ELEMENTS: dict[str, str] = {n: e.description for n, e in _ELEMENT_TYPES.items()}
ELEMENTS_WITH_BOX: tuple = tuple(n for n, e in _ELEMENT_TYPES.items() if e.has_box_mesh)
ELEMENTS_FROM_TETS: tuple = tuple(n for n, e in _ELEMENT_TYPES.items() if e.has_from_tet4)
ELEMENTS_LINEAR_TET: tuple = tuple(n for n, e in _ELEMENT_TYPES.items() if e.is_linear_tet)
ELEMENTS_REDUCED_VOLUMETRIC: tuple = tuple(n for n, e in _ELEMENT_TYPES.items() if e.has_reduced_volumetric_rule)


def _tet_types() -> str:
    return " or ".join(f'"{n}"' for n in ELEMENTS_FROM_TETS)

# Integrators that work with some element types only (others: every element type). An
# IntegratorType may also carry its own ``elements`` tuple, which takes precedence.
INTEGRATOR_ELEMENTS: dict[str, tuple] = {"stiffness_warping": ELEMENTS_LINEAR_TET}

_SELECTION = {
    "box_min": Key("vec3", doc="lower corner of the selection box (m)"),
    "box_max": Key("vec3", doc="upper corner of the selection box (m)"),
    "indices": Key("intlist", doc="explicit vertex indices"),
    "indices_file": Key("path", doc="text file of vertex indices (whitespace separated)"),
}

SCHEMA: dict[str, dict[str, Key]] = {
    "": {  # top level
        "name": Key("str", default=None, doc="scene name (USD prim name of the surface)"),
        "description": Key("str", default="", doc="free text"),
        "gravity": Key("vec3", default=(0.0, 0.0, 0.0), doc="m/s^2"),
    },
    "mesh": {
        "generator": Key("choice", choices=("box",), doc="procedural mesh"),
        "size": Key("vec3", check=_positive_vec3, doc="box size (m)"),
        "cells": Key("int3", check=_positive_int3, doc="box cells per axis (6 tets or 1 hex each)"),
        "origin": Key("vec3", default=(0.0, 0.0, 0.0), doc="box min corner (m)"),
        "path": Key("path", doc="volume mesh file (meshio: .mesh, .msh, .vtu, ...), closed surface (.obj, .off, .ply, .stl) "
                            "or USD file (.usd, .usda, .usdc: a TetMesh, or a closed Mesh tetrahedralised)"),
        "inside_surface": Key("bool", default=False, doc="keep only tets inside the file's triangles (tet files)"),
        "prim": Key("str", default=None, check=lambda v: None if v.startswith("/") else "must be an absolute prim path "
                    "such as \"/World/Bunny\"", doc="USD files (.usd/.usda/.usdc): the TetMesh or closed Mesh prim "
                    "to read; default the file's only one"),
        "element": Key("choice", default="tet4", choices=tuple(ELEMENTS), doc="element type: " + ", ".join(ELEMENTS)),
        # surface files (.obj/.off/.ply/.stl) are tetrahedralised on load (warpfem.mesh.tetrahedralize, docs/meshing.md)
        "max_edge_length": Key("float", default=None, check=_positive,
                               doc="surface files: target largest tet edge (m); default: the surface's own resolution"),
        "max_radius_edge_ratio": Key("float", default=None, check=lambda v: None if v >= 1.1 else "must be >= 1.1",
                                     doc="surface files: TetGen quality bound, circumradius / shortest edge (default 2)"),
        "mesher": Key("choice", default=None, choices=("auto", "tetgen", "tetwild"),
                      doc="surface files: 'tetgen' (warpfem[mesh]), 'tetwild' (warpfem[tetwild]); default auto "
                          "(a surface that is not clean goes to TetWild when installed)"),
        "target_tets": Key("int", default=None, check=lambda v: None if v >= 10 else "must be >= 10",
                           doc=f"surface files: at most about this many tets (a finer surface is meshed coarser, "
                               f"decimated for the physics mesh; default {TARGET_TETS_DEFAULT} unless max_edge_length "
                               f"is given; docs/meshing.md)"),
        "embed_surface": Key("bool", default=True,
                             doc="surface files: the input surface is the render surface, embedded in the tets "
                                 "(unless [surface] names another); false: the tet mesh's boundary"),
    },
    "material": {
        "model": Key("choice", required=True, choices=tuple(MATERIAL_TYPES),
                     doc="material model (the material registry): " + ", ".join(MATERIAL_TYPES)),
        "youngs_modulus": Key("float", required=True, check=_positive, doc="E (Pa)"),
        "poisson_ratio": Key("float", required=True, check=_poisson, doc="nu"),
        "density": Key("float", default=1000.0, check=_positive, doc="kg/m^3"),
        "mass_matrix": Key("choice", default="lumped", choices=("lumped", "consistent")),
        "volumetric_integration": Key("choice", default="full", choices=("full", "reduced"),
                                      doc="hex8 only: 'reduced' = selective reduced integration of the volumetric energy (no locking)"),
    },
    "fixed": {**_SELECTION, "components": Key("str", default="xyz", check=_components)},
    "handle": {
        **_SELECTION,
        "components": Key("str", default="xyz", check=_components),
        "translation": Key("vec3", default=(0.0, 0.0, 0.0), doc="total displacement over the ramp (m)"),
        "rotation_axis": Key("vec3", default=None, doc="rotation axis (any length > 0)"),
        "rotation_angle": Key("float", default=0.0, doc="total rotation over the ramp (degrees)"),
        "rotation_center": Key("vec3", default=None, doc="point on the axis (m); default: handle centroid"),
        "ramp_time": Key("float", default=None, check=_positive, doc="s; default: the whole run"),
    },
    "force": {**_SELECTION, "force": Key("vec3", required=True, doc="N on each selected vertex")},
    # kinematic colliders (warpfem.contact, docs/contact.md): keys per type in COLLIDER_TYPE_KEYS
    "collider": {
        "type": Key("choice", required=True, choices=COLLIDER_TYPES),
        "name": Key("str", default=None, doc="USD prim / message name (default: the type)"),
        "friction": Key("float", default=0.0, check=_non_negative, doc="Coulomb coefficient mu"),
        "dhat": Key("float", default=None, check=_positive, doc="contact distance (m); default 0.1 x mean surface edge"),
        "stiffness": Key("stiffness", default=None, check=_positive,
                         doc='barrier stiffness kappa (N/m); default from E and the weight; "auto": adaptive'),
        "friction_velocity": Key("float", default=None, check=_positive, doc="m/s below which friction sticks (smoothing)"),
        "point": Key("vec3", default=(0.0, 0.0, 0.0), doc="plane: a point on it (m)"),
        "normal": Key("vec3", default=(0.0, 1.0, 0.0), doc="plane: normal towards the body"),
        "center": Key("vec3", default=None, doc="sphere, capsule: centre (m)"),
        "radius": Key("float", default=None, check=_positive, doc="sphere, capsule: radius (m)"),
        "half_length": Key("float", default=None, check=_non_negative, doc="capsule: half length of its segment (m)"),
        "axis": Key("choice", default="y", choices=("x", "y", "z"), doc="capsule: the segment's axis"),
        "box_min": Key("vec3", default=None, doc="box: lower corner (m)"),
        "box_max": Key("vec3", default=None, doc="box: upper corner (m)"),
        "path": Key("path", default=None, doc="mesh: triangle mesh file (meshio)"),
        "scale": Key("float", default=1.0, check=_positive, doc="mesh: scale of the file's coordinates"),
        "offset": Key("vec3", default=(0.0, 0.0, 0.0), doc="mesh: translation after scaling (m)"),
        "translation": Key("vec3", default=(0.0, 0.0, 0.0), doc="motion over the ramp (m), as [[handle]]"),
        "rotation_axis": Key("vec3", default=None),
        "rotation_angle": Key("float", default=0.0, doc="degrees over the ramp"),
        "rotation_center": Key("vec3", default=None, doc="default: the collider's centre"),
        "ramp_time": Key("float", default=None, check=_positive, doc="s; default: the whole run"),
    },
    # contact between the bodies and of each with itself (warpfem.contact.surface, docs/contact.md);
    # the keys of Simulator.set_contact, plus the friction lagging iterations (colliders too)
    "contact": {
        "bodies": Key("bool", default=None, doc="contact between different bodies / components; default: true when "
                                                "the model has two or more"),
        "self": Key("bool", default=False, doc="contact of a body with itself"),
        "friction": Key("float", default=0.0, check=_non_negative, doc="Coulomb coefficient mu of the surface pairs"),
        "dhat": Key("float", default=None, check=_positive, doc="contact distance (m); default 0.1 x mean surface edge"),
        "stiffness": Key("stiffness", default=None, check=_positive,
                         doc="barrier kappa of the squared-distance barrier (N/m^3); default from Young's modulus; "
                             '"auto": adaptive'),
        "friction_velocity": Key("float", default=None, check=_positive, doc="m/s below which friction sticks (smoothing)"),
        "friction_iterations": Key("int", default=1, check=_non_negative,
                                   doc="updates of friction's normal forces and normals from an iterate near the "
                                       "solution, inside the step's Newton solve (colliders too); 0 = lagged once "
                                       "from the step start"),
        "friction_tol": Key("float", default=0.01, check=_positive,
                            doc="no further update when the normal forces change by less than this fraction"),
        "friction_update_tol": Key("float", default=0.0, check=_non_negative,
                                   doc="> 0: the first update only when a normal force changes by more than this "
                                       "fraction of the largest (0: always)"),
        "friction_lag_below": Key("float", default=None, check=_positive,
                                  doc="relative gradient at which a full Newton step's iterate is near enough to "
                                      "update friction from; default 0.01 (larger: earlier, cheaper, less exact)"),
    },
    "traction": {
        "box_min": Key("vec3", required=True),
        "box_max": Key("vec3", required=True),
        "force_per_area": Key("vec3", required=True, doc="Pa, on boundary faces inside the box"),
    },
    "integrator": {
        "type": Key("str", default="backward_euler", doc="a registered integrator type"),
    },
    "output": {
        "fps": Key("float", default=24.0, check=_positive, doc="frames per second"),
        "frames": Key("int", default=24, check=lambda v: None if v >= 1 else "must be >= 1"),
        "usd": Key("outpath", default=None, doc="animated USD (.usda/.usd/.usdc)"),
        "states": Key("outpath", default=None, doc=".npz with rest and per-frame positions"),
        "stats": Key("outpath", default=None, doc="JSON-lines per-frame statistics; default next to usd"),
        "vtu": Key("outpath", default=None, check=lambda v: None if v.lower().endswith(".pvd") else "must end in .pvd",
                   doc="ParaView collection (.pvd + one .vtu per frame in <name>.vtu/) of the volume mesh"),
        "up_axis": Key("choice", default="Y", choices=("Y", "Z")),
        "usd_volume": Key("bool", default=False,
                          doc="also write each body's volume as an animated UsdGeom.TetMesh (prim <body>_volume, or "
                              "volume for a one-body scene) beside its surface Mesh (corner tets of higher-order elements)"),
        "clip_frames": Key("int", default=100, check=_non_negative,
                           doc="frames per USD value clip (bounds the writer's memory); 0 = one file, all in memory"),
        "checkpoint_every": Key("int", default=1, check=_non_negative,
                                doc="checkpoint the whole simulation state every this many frames (and at the last), "
                                    "in <output>.checkpoint/ next to the outputs, for `warpfem run --resume`; each "
                                    "output is then saved to disk too; 0 = no checkpoints (docs/cli.md, \"Resuming\")"),
    },
    "surface": {
        "path": Key("path", required=True, doc="render surface (.obj/.off/.ply/.stl)"),
        "name": Key("str", default="surface", doc="USD prim name"),
    },
    # Reduced simulation (x = X + U q with trained cubature); present => the run is reduced.
    # Owned by warpfem.reduced (warpfem/reduced/scene.py builds it; `warpfem train` fills the cache).
    "subspace": {
        "modes": Key("int", default=20, check=lambda v: None if v >= 1 else "must be >= 1",
                     doc="subspace size r (columns of U)"),
        "modal_derivatives": Key("bool", default=True,
                                 doc="add modal derivatives, mass-PCA down to r (false: linear modes only, "
                                     "which cannot follow large deflections: docs/tradeoff.md)"),
        "cubature_tolerance": Key("float", default=0.01, check=_unit_interval,
                                  doc="relative training force error at which greedy cubature stops"),
        "max_cubature_points": Key("int", default=200, check=_positive, doc="cap on cubature elements"),
        "seed": Key("int", default=0, doc="seed of training poses and candidate sampling"),
        "cache": Key("outpath", default=None,
                     doc=".npz holding basis + cubature (relative to the scene file); default <scene>.subspace.npz next to it"),
        "load_response": Key("bool", default=True,
                             doc="make the linear static response to the loads (K^-1 f_ext) one of the r columns"),
        "training": Key("choice", default="mixed", choices=("mixed", "snapshots", "random"),
                        doc="cubature training poses: 'snapshots' = frames of a full run of this scene projected onto "
                            "the basis (every 4th held out for validation); 'random' = random poses with amplitude "
                            "~ 1/frequency; 'mixed' = both (random poses validate)"),
        "training_frames": Key("int", default=None, check=_positive,
                               doc="frames of the full training run (snapshots); default [output].frames"),
        "training_poses": Key("int", default=100, check=_positive, doc="number of random training poses (random)"),
        "validation_poses": Key("int", default=30, check=_positive, doc="number of random validation poses (random)"),
        "pod_modes": Key("int", default=0, check=_non_negative,
                         doc="extra basis columns from the training run: mass-weighted POD of its displacements "
                             "(r = modes + pod_modes; needs training 'snapshots' or 'mixed')"),
        "training_dt_scale": Key("int", default=1, check=_positive,
                                 doc="the full training run steps dt x this (same simulated time, fewer full steps; "
                                     "snapshots per step)"),
        "rotation_lifting": Key("int", default=0,
                                check=lambda v: None if v == 0 or 2 <= v <= 15 else "must be 0 (linear lifting) or 2..15",
                                doc="handles (all three components) move the interior by their rotation angle, not "
                                    "linearly: series order J (7 is exact to 1e-4 at 90 degrees); 0 = linear lifting"),
        "max_error": Key("float", default=0.02, check=lambda v: None if 0 <= v < 1 else "must be in [0, 1) (0 = no budget)",
                         doc="error budget of `warpfem train`: while the reduced replay of the training run is above "
                             "this RMS trajectory error (max over frames of the RMS vertex error / bounding-box "
                             "diagonal), POD columns of the training run are added (pod_modes, then 4, 8, 16, ... up "
                             "to max_pod_modes); train fails, writing no cache, when that is not enough. 0 = no "
                             "budget (train the given sizes only); not checked with training = 'random'"),
        "max_pod_modes": Key("int", default=32, check=_non_negative,
                             doc="cap on the POD columns train may use to meet max_error"),
        "max_validation_error": Key("float", default=None, check=_unit_interval,
                                    doc="`warpfem run` warns (log + stderr) when the cache's cubature validation "
                                        "error is above this"),
    },
}

# the (repeated) [[array]] sections
ARRAY_SECTIONS = ("fixed", "handle", "force", "traction", "collider")

# [[body]] tables (several bodies, each its own mesh and material): a body's own keys, and the
# sections it holds (the keys of today's top-level ones; a scene has either these at the top level or
# [[body]] tables). Selection boxes, handle centres and traction boxes are in scene coordinates, after
# the body's offset.
BODY_KEYS: dict[str, Key] = {
    "name": Key("str", default=None, doc="body name: USD prim, ParaView block, messages (default body<i>)"),
    "offset": Key("vec3", default=(0.0, 0.0, 0.0), doc="translation of the body's mesh (m)"),
    "initial_velocity": Key("vec3", default=(0.0, 0.0, 0.0), doc="velocity of every vertex at t = 0 (m/s)"),
    "kind": Key("choice", default="soft", choices=("soft", "rigid"),
                doc="'soft' (finite elements) or 'rigid' (an affine body, docs/rigid.md)"),
    "initial_angular_velocity": Key("vec3", default=None,
                                    doc="rigid bodies: angular velocity about the centre of mass at t = 0 (rad/s)"),
    "stiffness": Key("float", default=None, check=_positive,
                     doc="rigid bodies: stiffness kappa (Pa) of the orthogonality energy (default 1e8)"),
}
#: a rigid body's own keys (others, 'soft' bodies'), its material's only key, the sections it refuses
RIGID_ONLY_KEYS = ("initial_angular_velocity", "stiffness")
RIGID_MATERIAL = {"density": Key("float", required=True, check=_positive, doc="kg/m^3")}
RIGID_REFUSED_SECTIONS = {"fixed": "fixed components", "handle": "handles (prescribed motion)",
                          "traction": "tractions", "surface": "an embedded render surface"}
BODY_SECTIONS = ("mesh", "material", "fixed", "handle", "force", "traction", "surface")
# integrator types (and sections) that simulate one body only
SINGLE_BODY_INTEGRATORS = ("stiffness_warping",)

# [[collider]]: the keys each type needs (required) and the keys only some types take, as each
# collider class declares them (``scene_keys``, warpfem.contact.colliders)
COLLIDER_TYPE_KEYS = collider_scene_keys()

# Newton/time-stepping keys shared by the built-in integrators (integrators list which they accept).
INTEGRATOR_KEYS: dict[str, Key] = {
    "dt": Key("float", default=None, check=_positive, doc="time step (s); default 1/fps"),
    "tol": Key("float", default=1e-6, check=_unit_interval,
               doc="relative Newton gradient tolerance: converged when ||g|| <= tol ||g at the step's start|| "
                   "(friction's lag updates included; docs/integrators.md)"),
    "atol": Key("float", default=0.0, check=_non_negative),
    "cg_tol": Key("float", default=1e-4, check=_unit_interval, doc="relative PCG tolerance"),
    "max_iters": Key("int", default=None, check=_positive,
                     doc="Newton iterations per solve; default 30, or 100 in a scene with contact (impacts take tens)"),
    "max_cg_iters": Key("int", default=2000, check=_positive, doc="PCG iterations per Newton iteration"),
    "project_hessian": Key("bool", default=True),
    "hessian_projection": Key("choice", default="on_demand", choices=("always", "on_demand"),
                              doc="with project_hessian: project every Newton system, or only once the exact "
                                  "Hessian fails (docs/integrators.md)"),
    "require_convergence": Key("bool", default=False,
                               doc="fail the run on a non-converged step (exit 1, outputs kept marked incomplete); "
                                   "off: such steps are counted and reported (docs/cli.md)"),
    "damping_mass": Key("float", default=0.0, check=_non_negative, doc="Rayleigh alpha (1/s)"),
    "damping_stiffness": Key("float", default=0.0, check=_non_negative, doc="Rayleigh beta (s)"),
    "load_steps": Key("int", default=1, check=_positive, doc="static: load ramp steps per frame"),
    "linear_solver": Key("choice", default="auto", choices=("auto", "pcg", "direct", "amg", "multigrid"),
                         doc="solver of the Newton systems (docs/linear_solvers.md)"),
}


# ----------------------------------------------------------------------------- the result
@dataclass
class SceneSpec:
    """A validated scene (plain data, paths absolute)."""

    path: str | None
    base_dir: str
    top: dict
    mesh: dict
    material: dict
    integrator: dict
    output: dict
    surface: dict | None
    subspace: dict | None = None
    contact: dict | None = None
    fixed: list = field(default_factory=list)
    handle: list = field(default_factory=list)
    force: list = field(default_factory=list)
    traction: list = field(default_factory=list)
    collider: list = field(default_factory=list)
    extra: dict = field(default_factory=dict)  # sections handled by registered extensions
    # [[body]] scenes: one dict per body (name, offset, initial_velocity, spec: the body's own SceneSpec
    # with its mesh, material, fixed, handle, force, traction, surface); empty for a single-body scene
    bodies: list = field(default_factory=list)


# ----------------------------------------------------------------------------- checking
class _Ctx:
    def __init__(self, path, base_dir, body=""):
        self.path, self.base_dir = path, base_dir
        self.body = body  # "[[body]] #2 'right'" while a body's own sections are checked

    def fail(self, where, msg):
        src = self.path or "<scene>"
        if self.body and where and where.lstrip("[").split("]")[0].split(".")[0] in BODY_SECTIONS:
            where = f"{self.body}: {where}"
        raise SceneError(f"{src}: {where}: {msg}" if where else f"{src}: {msg}")


def _suggest(key, known):
    close = difflib.get_close_matches(key, list(known), n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


def _typename(v):
    return {bool: "boolean", int: "integer", float: "float", str: "string", list: "array", dict: "table"}.get(type(v), type(v).__name__)


def _is_number(v):
    return isinstance(v, numbers.Real) and not isinstance(v, bool)


def _convert(ctx, where, key: Key, value):
    kind = key.kind
    if kind == "stiffness":  # a barrier stiffness: a number, or "auto" (adaptive, docs/contact.md)
        if isinstance(value, str) and value == "auto":
            return value
        kind = "float"
    if kind == "float":
        if not _is_number(value):
            ctx.fail(where, f"expected a number, got {_typename(value)} {value!r}")
        value = float(value)
        if not math.isfinite(value):
            ctx.fail(where, f"must be finite, got {value!r}")
    elif kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            ctx.fail(where, f"expected an integer, got {_typename(value)} {value!r}")
    elif kind == "bool":
        if not isinstance(value, bool):
            ctx.fail(where, f"expected true or false, got {_typename(value)} {value!r}")
    elif kind in ("str", "choice", "path", "outpath"):
        if not isinstance(value, str):
            ctx.fail(where, f"expected a string, got {_typename(value)} {value!r}")
        if kind == "choice" and value not in key.choices:
            ctx.fail(where, f"must be one of {', '.join(repr(c) for c in key.choices)}, got {value!r}"
                     + _suggest(value, key.choices))
        if kind == "path":
            p = value if os.path.isabs(value) else os.path.join(ctx.base_dir, value)
            p = os.path.normpath(p)
            if not os.path.isfile(p):
                ctx.fail(where, f"file not found: {value!r} (looked for {p})")
            value = p
        if kind == "outpath" and not value:
            ctx.fail(where, "must be a non-empty file name")
    elif kind in ("vec3", "int3"):
        ok = isinstance(value, list) and len(value) == 3 and all(
            (isinstance(c, int) and not isinstance(c, bool)) if kind == "int3" else _is_number(c) for c in value)
        if not ok:
            what = "3 integers" if kind == "int3" else "3 numbers"
            ctx.fail(where, f"expected an array of {what}, got {value!r}")
        value = tuple(int(c) for c in value) if kind == "int3" else tuple(float(c) for c in value)
        if not all(math.isfinite(c) for c in value):
            ctx.fail(where, f"must be finite, got {list(value)}")
    elif kind == "intlist":
        if not (isinstance(value, list) and value and all(isinstance(c, int) and not isinstance(c, bool) and c >= 0 for c in value)):
            ctx.fail(where, f"expected a non-empty array of integers >= 0, got {value!r}")
        value = list(value)
    else:  # pragma: no cover - schema bug
        raise AssertionError(f"unknown key kind {kind!r}")
    if key.check is not None:
        problem = key.check(value)
        if problem:
            shown = list(value) if isinstance(value, tuple) else value
            ctx.fail(where, f"{problem}, got {shown!r}")
    return value


def _where_section(section, index=None):
    if section == "":
        return ""
    return f"[[{section}]] #{index + 1}" if index is not None else f"[{section}]"


def _check_table(ctx, section, table, schema, index=None):
    """Validate one table against ``schema``; returns a dict with defaults filled in."""
    label = _where_section(section, index)
    if not isinstance(table, dict):
        ctx.fail(label, f"expected a table, got {_typename(table)}")
    out = {}
    for k, v in table.items():
        where = f"{label}.{k}" if label else k
        if k not in schema:
            hint = _suggest(k, schema)
            if not hint:  # a key of another section?
                homes = [s for s, keys in SCHEMA.items() if k in keys and s != section]
                if homes:
                    hint = f" (it belongs in [{homes[0]}])" if homes[0] else " (it belongs at the top level, before any [table])"
            known = ", ".join(sorted(schema))
            ctx.fail(where, f"unknown key{hint}; known keys here: {known}")
        out[k] = _convert(ctx, where, schema[k], v)
    for k, key in schema.items():
        if k not in out:
            if key.required:
                ctx.fail(f"{label}.{k}" if label else k, "required key missing")
            out[k] = key.default
    return out


def _check_selection(ctx, section, i, entry, *, require=True):
    label = _where_section(section, i)
    ways = []
    if entry.get("box_min") is not None or entry.get("box_max") is not None:
        ways.append("box")
    ways += [w for w in ("indices", "indices_file") if entry.get(w) is not None]
    if len(ways) == 0 and require:
        ctx.fail(label, "select vertices with box_min and box_max, indices, or indices_file")
    if len(ways) > 1:
        ctx.fail(label, f"give exactly one vertex selection, got {' and '.join(ways)}")
    if "box" in ways:
        lo, hi = entry.get("box_min"), entry.get("box_max")
        if lo is None or hi is None:
            ctx.fail(f"{label}.{'box_min' if lo is None else 'box_max'}", "required with the other box corner")
        bad = [a for a, l, h in zip("xyz", lo, hi) if l > h]
        if bad:
            ctx.fail(f"{label}.box_min", f"box_min exceeds box_max on axis {', '.join(bad)} ({list(lo)} > {list(hi)})")
    if entry.get("indices_file") is not None:
        import numpy as np

        try:
            ids = np.loadtxt(entry["indices_file"], dtype=np.float64, ndmin=1).ravel()
        except ValueError as e:
            ctx.fail(f"{label}.indices_file", f"{entry['indices_file']}: cannot read vertex indices: {e}")
        if ids.size == 0 or np.any(ids != np.round(ids)) or np.any(ids < 0):
            ctx.fail(f"{label}.indices_file", f"{entry['indices_file']}: expected non-negative integer vertex indices")
        entry["indices"] = ids.astype(np.int64).tolist()


def parse_scene_dict(data: dict, *, path: str | None = None, base_dir: str | None = None,
                     integrators: dict | None = None, _body: str = "") -> SceneSpec:
    """Validate a parsed TOML document; ``integrators`` maps type names to their registry entries."""
    if integrators is None:
        from . import INTEGRATORS as integrators
    ctx = _Ctx(path, base_dir or (os.path.dirname(os.path.abspath(path)) if path else os.getcwd()), _body)
    if "body" in data:
        return _parse_bodies(ctx, data, integrators)
    sections = set(SCHEMA) - {""}
    top_schema = dict(SCHEMA[""])
    for s in sections:
        top_schema[s] = Key("table")
    # unknown top-level keys / sections first
    for k, v in data.items():
        if k not in top_schema:
            hint = _suggest(k, top_schema)
            if not hint:
                homes = [s for s, keys in SCHEMA.items() if k in keys and s]
                if homes:
                    hint = f" (it belongs in [{homes[0]}])"
            what = "section" if isinstance(v, (dict, list)) else "key"
            ctx.fail(k, f"unknown {what}{hint}; known: {', '.join(sorted(top_schema))}")
        if k in ARRAY_SECTIONS and not isinstance(v, list):
            ctx.fail(k, f"write it as an array of tables [[{k}]] (got a single [{k}] table)")
        if k in sections and k not in ARRAY_SECTIONS and not isinstance(v, dict):
            ctx.fail(k, f"expected a [{k}] table, got {_typename(v)}")
    top = _check_table(ctx, "", {k: v for k, v in data.items() if k in SCHEMA[""]}, SCHEMA[""])
    if "mesh" not in data:
        ctx.fail("[mesh]", "required section missing (generator = \"box\" with size and cells, or path = \"file.mesh\")")
    if "material" not in data:
        ctx.fail("[material]", "required section missing (model, youngs_modulus, poisson_ratio, density)")
    mesh = _check_table(ctx, "mesh", data["mesh"], SCHEMA["mesh"])
    if (mesh["generator"] is None) == (mesh["path"] is None):
        ctx.fail("[mesh]", "give either generator = \"box\" (with size and cells) or path = \"file\", not "
                 + ("both" if mesh["generator"] else "neither"))
    if mesh["generator"] == "box":
        for k in ("size", "cells"):
            if mesh[k] is None:
                ctx.fail(f"[mesh].{k}", "required with generator = \"box\"")
        if mesh["element"] not in ELEMENTS_WITH_BOX:
            ctx.fail("[mesh].element", f"generator = \"box\" makes {', '.join(ELEMENTS_WITH_BOX)} meshes, not "
                     f"{mesh['element']!r} (read it from a file: path = \"...\")")
    elif any(data["mesh"].get(k) is not None for k in ("size", "cells", "origin")):
        ctx.fail("[mesh].path", "size/cells/origin only apply to generator = \"box\"")
    element = mesh["element"]
    tetra_keys = [k for k in ("max_edge_length", "max_radius_edge_ratio", "mesher", "target_tets") if mesh[k] is not None]
    if "embed_surface" in data["mesh"]:
        tetra_keys.append("embed_surface")
    surface_file = bool(mesh["path"]) and os.path.splitext(mesh["path"])[1].lower() in (".obj", ".off", ".ply", ".stl")
    usd_file = bool(mesh["path"]) and os.path.splitext(mesh["path"])[1].lower() in (".usd", ".usda", ".usdc")
    if mesh["prim"] is not None and not usd_file:
        ctx.fail("[mesh].prim", "only applies to USD files (path = \"file.usd/.usda/.usdc\")")
    if usd_file:
        if element not in ELEMENTS_FROM_TETS:
            ctx.fail("[mesh].element", f"a USD file holds tets (a TetMesh, or a Mesh tetrahedralised): use element = "
                     f"{_tet_types()}, not {element!r}")
        if mesh["inside_surface"]:
            ctx.fail("[mesh].inside_surface", "only applies to tet files with triangle cells, not to USD files")
        if "embed_surface" in data["mesh"]:
            ctx.fail("[mesh].embed_surface", "only applies to .obj/.off/.ply/.stl surface files (a USD file's render "
                     "surface is the tet mesh's boundary unless [surface] names one)")
    if mesh["path"] and not (surface_file or usd_file) and tetra_keys:
        # (load_mesh says the same for the options it gets; said here before any file is read)
        ctx.fail(f"[mesh].{tetra_keys[0]}", "only applies to surface files (.obj/.off/.ply/.stl, tetrahedralised on "
                 "load); this file is read as a volume mesh")
    if surface_file and mesh["target_tets"] is None and mesh["max_edge_length"] is None:
        mesh["target_tets"] = TARGET_TETS_DEFAULT
        mesh["target_tets_default"] = True  # only an upper bound: a coarser surface keeps its own resolution
    if mesh["generator"] == "box" and tetra_keys:
        ctx.fail(f"[mesh].{tetra_keys[0]}", "only applies to path = \"surface.obj/.off/.ply/.stl\" (tetrahedralised on load)")
    if mesh["path"] and os.path.splitext(mesh["path"])[1].lower() in (".obj", ".off", ".ply", ".stl"):
        if element not in ELEMENTS_FROM_TETS:
            ctx.fail("[mesh].element", f"a surface file is tetrahedralised: use element = {_tet_types()}, not {element!r}")
        if mesh["inside_surface"]:
            ctx.fail("[mesh].inside_surface", "only applies to tet files; a surface file is tetrahedralised as a whole")
    if mesh["inside_surface"] and element not in ELEMENTS_FROM_TETS:
        ctx.fail("[mesh].inside_surface", f"only applies to tetra meshes (element = {_tet_types()}), not {element!r}")
    material = _check_table(ctx, "material", data["material"], SCHEMA["material"])
    if material["volumetric_integration"] == "reduced":
        if element not in ELEMENTS_REDUCED_VOLUMETRIC:
            with_rule = " / ".join(f'"{n}"' for n in ELEMENTS_REDUCED_VOLUMETRIC)
            ctx.fail("[material].volumetric_integration", "'reduced' (selective reduced integration of the volumetric "
                     f"energy) is only available for element = {with_rule}; this scene uses {element!r} (use \"full\", or "
                     "element = \"tet10\" / \"hex27\", which do not lock)")
        if material["poisson_ratio"] < 0.0:
            ctx.fail("[material].volumetric_integration", "'reduced' needs poisson_ratio >= 0 (the one-point "
                     f"volumetric part must be non-negative); this scene uses {material['poisson_ratio']!r}")

    # integrator: type first, then its own keys
    raw_int = data.get("integrator", {})
    if not isinstance(raw_int, dict):
        ctx.fail("integrator", "expected an [integrator] table")
    itype = raw_int.get("type", SCHEMA["integrator"]["type"].default)
    if not isinstance(itype, str):
        ctx.fail("[integrator].type", f"expected a string, got {_typename(itype)} {itype!r}")
    if itype not in integrators:
        ctx.fail("[integrator].type", f"unknown integrator {itype!r}{_suggest(itype, integrators)}; "
                 f"available: {', '.join(sorted(integrators))}")
    entry = integrators[itype]
    int_schema = {"type": SCHEMA["integrator"]["type"], **entry.keys}
    integrator = _check_table(ctx, "integrator", raw_int, int_schema)
    def _elements_of(name):
        return getattr(integrators[name], "elements", None) or INTEGRATOR_ELEMENTS.get(name)

    allowed = _elements_of(itype)
    if allowed and element not in allowed:
        others = sorted(n for n in integrators if not _elements_of(n) or element in _elements_of(n))
        ctx.fail("[integrator].type", f"{itype!r} supports element {' / '.join(repr(a) for a in allowed)} only, "
                 f"the mesh uses {element!r} (integrators for {element}: {', '.join(others)})")

    output = _check_table(ctx, "output", data.get("output", {}), SCHEMA["output"])
    surface = _check_table(ctx, "surface", data["surface"], SCHEMA["surface"]) if "surface" in data else None
    if surface is None and surface_file and mesh["embed_surface"]:
        # the user's own surface at full resolution is what gets rendered; the tets only carry it
        surface = {"path": mesh["path"], "name": "surface", "from_mesh": True}
    subspace = _check_table(ctx, "subspace", data["subspace"], SCHEMA["subspace"]) if "subspace" in data else None
    contact = _check_table(ctx, "contact", data["contact"], SCHEMA["contact"]) if "contact" in data else None
    if contact is not None and subspace is not None:
        ctx.fail("[contact]", "reduced runs ([subspace]) do not handle contact")
    if subspace is not None and element not in ELEMENTS_LINEAR_TET:
        only = " / ".join(f'"{n}"' for n in ELEMENTS_LINEAR_TET)
        ctx.fail("[subspace]", f"reduced simulation supports element = {only} only; the mesh uses {element!r}")
    if subspace is not None and subspace["pod_modes"] and subspace["training"] == "random":
        ctx.fail("[subspace].pod_modes", "POD columns come from the full training run: set training = \"mixed\" or "
                 "\"snapshots\", or pod_modes = 0")

    arrays = {}
    for s in ARRAY_SECTIONS:
        entries = []
        for i, e in enumerate(data.get(s, [])):
            checked = _check_table(ctx, s, e, SCHEMA[s], index=i)
            if s == "collider":
                _check_collider(ctx, i, checked, e, itype, subspace)
            else:
                _check_selection(ctx, s, i, checked)
            entries.append(checked)
        arrays[s] = entries
    for i, h in enumerate(arrays["handle"]):
        label = _where_section("handle", i)
        if h["rotation_angle"] != 0.0 and h["rotation_axis"] is None:
            ctx.fail(f"{label}.rotation_axis", "required with rotation_angle")
        if h["rotation_axis"] is not None and math.sqrt(sum(c * c for c in h["rotation_axis"])) == 0.0:
            ctx.fail(f"{label}.rotation_axis", "must be a non-zero vector")

    if entry.dynamic:
        dt = integrator.get("dt")
        frame_time = 1.0 / output["fps"]
        if dt is None:
            integrator["dt"] = dt = frame_time
        sub = max(1, round(frame_time / dt))
        if abs(sub * dt - frame_time) > 1e-6 * frame_time:
            ctx.fail("[integrator].dt", f"dt = {dt!r} s must divide the frame time 1/fps = {frame_time!r} s "
                     f"(e.g. dt = {frame_time / sub!r})")
        integrator["substeps"] = int(sub)
    if contact is not None and itype not in ("backward_euler", "bdf2", "newmark"):
        ctx.fail("[contact]", f"contact needs a full-space dynamic integrator (backward_euler, bdf2, newmark), "
                              f"[integrator].type is {itype!r}")
    return SceneSpec(path=path, base_dir=ctx.base_dir, top=top, mesh=mesh, material=material,
                     integrator=integrator, output=output, surface=surface, subspace=subspace, contact=contact, **arrays)


def _body_label(i, name):
    return f"[[body]] #{i + 1}" + (f" {name!r}" if isinstance(name, str) and name else "")


def _parse_bodies(ctx, data, integrators) -> SceneSpec:
    """A scene of ``[[body]]`` tables: each body's sections checked as a single-body scene's (errors
    name the body), the shared sections once; the result's fixed / handle / force / traction are
    every body's entries in body order (their vertices are mapped to the global numbering when
    selected) and ``bodies`` holds each body's own spec."""
    import re

    raw = data["body"]
    if not isinstance(raw, list):
        ctx.fail("body", "write the bodies as an array of tables [[body]] (got a single [body] table)")
    if not raw:
        ctx.fail("[[body]]", "needs at least one body")
    mixed = [s for s in BODY_SECTIONS if s in data]
    if mixed:
        s = mixed[0]
        shown = f"[[{s}]]" if s in ARRAY_SECTIONS else f"[{s}]"
        ctx.fail(shown, f"a scene with [[body]] tables cannot also have a top-level {shown}: [[body]] and top-level "
                 f"{shown} are two ways to give the {s}; move it into a [[body]] table ([[body.{s}]] or [body.{s}])")
    if "subspace" in data:
        ctx.fail("[subspace]", "reduced runs take a one-body scene of the top-level form ([mesh], [material]); this "
                 "scene has [[body]] tables")
    itype = data.get("integrator", {}).get("type", SCHEMA["integrator"]["type"].default) \
        if isinstance(data.get("integrator", {}), dict) else None
    shared = {k: v for k, v in data.items() if k != "body"}
    names, bodies = [], []
    for i, b in enumerate(raw):
        label = _body_label(i, b.get("name") if isinstance(b, dict) else None)
        if not isinstance(b, dict):
            ctx.fail(label, f"expected a table, got {_typename(b)}")
        allowed = {**BODY_KEYS, **{s: None for s in BODY_SECTIONS}}
        for k in b:
            if k not in allowed:
                ctx.fail(f"{label}.{k}", f"unknown key{_suggest(k, allowed)}; known keys of a body: "
                         f"{', '.join(sorted(allowed))}")
        own = {}
        for k, key in BODY_KEYS.items():
            own[k] = _convert(ctx, f"{label}.{k}", key, b[k]) if k in b else key.default
        name = own["name"] or f"body{i + 1}"
        if not re.fullmatch(r"[A-Za-z_][A-Za-z0-9_]*", name):
            ctx.fail(f"{label}.name", f"must be a valid USD prim name (letters, digits, _; not starting with a digit), "
                     f"got {name!r}")
        if name in names:
            ctx.fail(f"{label}.name", f"{name!r} is already the name of [[body]] #{names.index(name) + 1}; names must be unique")
        names.append(name)
        for s in ("mesh", "material"):
            if s not in b:
                ctx.fail(f"{label}.{s}", f"required: each [[body]] has its own [body.{s}] table")
        sub = dict(shared, **{s: b[s] for s in BODY_SECTIONS if s in b})
        rigid = None
        if own["kind"] == "rigid":
            rigid = _check_rigid_body(ctx, label, b, own)
            # the mesh and [[force]] entries are checked as a soft body's, with a stand-in material
            sub["material"] = {"model": "stable_neo_hookean", "youngs_modulus": 1.0, "poisson_ratio": 0.3,
                               "density": rigid["density"]}
        else:
            for k in RIGID_ONLY_KEYS:
                if own[k] is not None:
                    ctx.fail(f"{label}.{k}", 'only a rigid body has it (kind = "rigid"); this body is soft')
        spec = parse_scene_dict(sub, path=ctx.path, base_dir=ctx.base_dir, integrators=integrators, _body=label)
        if rigid is not None:  # what describe / collider defaults read of a rigid body's material
            spec.material = {"model": None, "youngs_modulus": None, "poisson_ratio": None, "density": rigid["density"],
                             "mass_matrix": spec.material["mass_matrix"],
                             "volumetric_integration": spec.material["volumetric_integration"]}
        bodies.append({"name": name, "offset": own["offset"], "initial_velocity": own["initial_velocity"], "spec": spec,
                       "label": label, "kind": own["kind"], "rigid": rigid, "index": i})
    rigid_names = [b["name"] for b in bodies if b["kind"] == "rigid"]
    entry = integrators.get(itype) if isinstance(itype, str) else None
    if rigid_names and entry is not None and not getattr(entry, "dynamic", True):
        ctx.fail("[integrator].type", f"{itype!r} is a static solve, which cannot hold rigid body {rigid_names[0]!r} "
                 "(only inertia does); use backward_euler, bdf2 or newmark")
    # soft bodies first, then the rigid ones (the model's order); each keeps its name and label
    bodies = [b for b in bodies if b["kind"] == "soft"] + [b for b in bodies if b["kind"] == "rigid"]
    if len(bodies) > 1 and itype in SINGLE_BODY_INTEGRATORS:
        ctx.fail("[integrator].type", f"{itype!r} simulates one body; this scene has {len(bodies)} [[body]] tables "
                 "(use backward_euler, bdf2, newmark or static)")
    first = bodies[0]["spec"]
    merged = {s: [e for b in bodies for e in getattr(b["spec"], s)] for s in ("fixed", "handle", "force", "traction")}
    return SceneSpec(path=first.path, base_dir=first.base_dir, top=first.top, mesh=first.mesh, material=first.material,
                     integrator=first.integrator, output=first.output, surface=None, subspace=first.subspace,
                     collider=first.collider, contact=first.contact, extra=first.extra, bodies=bodies, **merged)


def _check_rigid_body(ctx, label, b, own) -> dict:
    """A rigid ``[[body]]``'s own checks: its material holds only a density (> 0), it has no fixed /
    handle / traction / surface sections. Returns {density, initial_angular_velocity, stiffness}."""
    for s, what in RIGID_REFUSED_SECTIONS.items():
        if s in b:
            shown = f"[[body.{s}]]" if s in ARRAY_SECTIONS else f"[body.{s}]"
            ctx.fail(f"{label}.{s}", f"a rigid body cannot have {shown} ({what}); give it a velocity, or make it "
                     'kind = "soft"')
    mat = b.get("material")
    if not isinstance(mat, dict):
        ctx.fail(f"{label}.material", "required: a rigid body's material is a table { density = ... } (kg/m^3)")
    for k in mat:
        if k not in RIGID_MATERIAL:
            ctx.fail(f"{label}.material.{k}", "a rigid body's material has only density (kg/m^3): it does not deform")
    if "density" not in mat:
        ctx.fail(f"{label}.material.density", "required: a rigid body's density (kg/m^3, > 0)")
    rho = _convert(ctx, f"{label}.material.density", RIGID_MATERIAL["density"], mat["density"])
    return {"density": rho, "stiffness": 1e8 if own["stiffness"] is None else own["stiffness"],
            "initial_angular_velocity": own["initial_angular_velocity"] or (0.0, 0.0, 0.0)}


def _check_collider(ctx, i, c, raw, itype, subspace):
    label = _where_section("collider", i)
    required, own = COLLIDER_TYPE_KEYS[c["type"]]
    for k in required:
        if c.get(k) is None:
            ctx.fail(f"{label}.{k}", f"required for type = {c['type']!r}")
    others = {k for t, (r, o) in COLLIDER_TYPE_KEYS.items() if t != c["type"] for k in r + o} - set(required + own)
    for k in sorted(others & set(raw)):
        ctx.fail(f"{label}.{k}", f"not a key of type = {c['type']!r} (its keys: {', '.join(required + own) or 'none'})")
    if c["type"] == "plane" and all(v == 0 for v in c["normal"]):
        ctx.fail(f"{label}.normal", "must be a non-zero vector")
    if c["type"] == "box" and not all(h > l for l, h in zip(c["box_min"], c["box_max"])):
        ctx.fail(f"{label}.box_max", "must exceed box_min on every axis")
    if c["rotation_angle"] != 0.0 and c["rotation_axis"] is None:
        ctx.fail(f"{label}.rotation_axis", "required with rotation_angle")
    if subspace is not None:
        ctx.fail(label, "reduced runs ([subspace]) do not handle colliders")
    if itype not in ("backward_euler", "bdf2", "newmark"):
        ctx.fail(label, f"colliders need a full-space dynamic integrator (backward_euler, bdf2, newmark), "
                        f"[integrator].type is {itype!r}")


#: the keys of a scene document that hold file paths (relative to the scene file), by section
SCENE_PATH_KEYS = {"mesh": ("path",), "surface": ("path",), "output": ("usd", "states", "stats", "vtu"),
                   "subspace": ("cache",), "fixed": ("indices_file",), "handle": ("indices_file",),
                   "force": ("indices_file",), "traction": ("indices_file",), "collider": ("path",)}


def rebase_scene_paths(doc: dict, src_dir: str, out_dir: str) -> dict:
    """Rewrite ``doc``'s relative file paths (``SCENE_PATH_KEYS``, also inside each ``[[body]]``),
    written relative to ``src_dir``, to be relative to ``out_dir`` (a scene written elsewhere
    keeps reading the same files). In place; returns ``doc``."""
    for sec, keys in SCENE_PATH_KEYS.items():
        items = doc.get(sec)
        for item in (items if isinstance(items, list) else [items] if isinstance(items, dict) else []):
            for k in keys:
                if isinstance(item.get(k), str) and not os.path.isabs(item[k]):
                    item[k] = os.path.relpath(os.path.join(src_dir, item[k]), out_dir)
    for body in doc.get("body") or []:
        if isinstance(body, dict):
            rebase_scene_paths(body, src_dir, out_dir)
    return doc


def read_toml(path, error: type[Exception], *, what: str) -> dict:
    """Read a TOML file; a missing file or a syntax error raises ``error`` naming the file."""
    if not os.path.isfile(path):
        raise error(f"{path}: {what} not found")
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as e:
        raise error(f"{path}: not valid TOML: {e}") from e


def parse_scene_file(path, *, integrators: dict | None = None) -> SceneSpec:
    """Read and validate a TOML scene file (nothing is built)."""
    path = os.fspath(path)
    data = read_toml(path, SceneError, what="scene file")
    return parse_scene_dict(data, path=os.path.abspath(path), integrators=integrators)
