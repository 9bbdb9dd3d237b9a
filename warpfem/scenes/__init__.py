"""TOML scene files: schema and validation, building, running frames with USD / npz / stats output.

    from warpfem.scenes import load_scene
    scene = load_scene("examples/scenes/cantilever.toml")   # validated; nothing built yet
    print(scene.describe())                                 # counts and memory, no kernels
    run = scene.build(device="cpu", precision="float64")
    run.run(usd="out/cantilever.usda")

Integrator types live in the registry ``INTEGRATORS`` (name -> :class:`IntegratorType`); other
modules add theirs with :func:`register_integrator` (their ``[integrator]`` keys are validated
from the ``keys`` they declare). See docs/scenes.md for the file format.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

from warpfem.model import static_supports_error

from .schema import ELEMENTS, INTEGRATOR_KEYS, SCHEMA, Key, SceneError, SceneSpec, parse_scene_dict, parse_scene_file

__all__ = ["SceneError", "SceneSpec", "Key", "SCHEMA", "ELEMENTS", "INTEGRATOR_KEYS", "IntegratorType",
           "INTEGRATORS", "SECTION_INTEGRATORS", "INTEGRATOR_MODULES", "integrator_entry", "register_integrator", "load_scene", "Scene", "SceneRun", "FrameStats",
           "parse_scene_file", "parse_scene_dict", "traction_forces", "handle_targets", "estimate_device_memory"]


@dataclass
class IntegratorType:
    """A scene integrator.

    name: the ``[integrator].type`` value.
    build: ``build(scene, model, *, device, precision) -> sim``; ``sim`` offers what
        :class:`~warpfem.scenes.SceneRun` uses: ``x`` (device positions), ``positions()``,
        ``set_targets(ids, positions)``, ``sync_model()``, and ``step()`` + ``dt`` + ``time``
        (dynamic) or is driven by ``static_solve`` (quasi-static).
    keys: the ``[integrator]`` keys it accepts besides ``type`` (name -> :class:`Key`).
    dynamic: True for time stepping (dt, substeps per frame); False for quasi-static frames.
    builds: short descriptions of what it allocates (shown by ``warpfem describe``).
    static_solve: ``static_solve(sim, integrator_options) -> SolveStats`` (quasi-static types).
    section: when set, the entry is not an ``[integrator].type`` but builds the simulator of every
        scene that has this section (e.g. ``"subspace"``: the reduced simulator), using the scene's
        ``[integrator]`` settings; ``Scene.build(full=True)`` skips it.
    describe: ``describe(scene) -> str``, extra lines for ``warpfem describe`` (section entries).
    """

    name: str
    build: Callable
    keys: dict = field(default_factory=dict)
    dynamic: bool = True
    builds: tuple = ()
    static_solve: Callable | None = None
    section: str | None = None
    describe: Callable | None = None


INTEGRATORS: dict[str, IntegratorType] = {}
SECTION_INTEGRATORS: dict[str, IntegratorType] = {}  # scene section -> the entry that builds its simulator

# Modules (above this package in the layers) that register integrator types when imported; loaded
# on first use by integrator_entry, so scenes never import them itself.
INTEGRATOR_MODULES = ["warpfem.reduced.scene"]
# The scene sections such a module registers an integrator for: it is loaded for a scene that has
# one of them (or whose [integrator].type is not registered yet), so a plain scene does not import
# the reduced package (scipy.optimize, ...) at start-up. A module without an entry loads always.
INTEGRATOR_MODULE_SECTIONS: dict[str, tuple] = {"warpfem.reduced.scene": ("subspace",)}
_loaded_modules: set = set()


def _needed_by(name: str, scene) -> bool:
    sections = INTEGRATOR_MODULE_SECTIONS.get(name)
    if scene is None or sections is None:
        return True
    spec = getattr(scene, "spec", None)
    if any(getattr(spec, s, None) is not None for s in sections):
        return True
    return getattr(scene, "integrator_type", None) not in INTEGRATORS


def _load_integrator_modules(scene=None) -> None:
    import importlib

    for name in INTEGRATOR_MODULES:
        if name in _loaded_modules or not _needed_by(name, scene):
            continue
        try:
            importlib.import_module(name)
        except ModuleNotFoundError as e:
            if not (e.name and name.startswith(e.name)):  # a real missing dependency inside it: report
                raise
        _loaded_modules.add(name)


def integrator_entry(scene, *, full: bool = False) -> IntegratorType:
    """The registry entry that builds ``scene``'s simulator: the one registered for a section the
    scene has (``[subspace]``), else (or with ``full=True``) its ``[integrator].type``."""
    _load_integrator_modules(scene)
    if not full:
        for section, entry in SECTION_INTEGRATORS.items():
            if getattr(scene.spec, section, None) is not None:
                return entry
    return INTEGRATORS[scene.integrator_type]


def section_entries(scene) -> list:
    """The section entries that apply to ``scene`` (for describe / summary)."""
    _load_integrator_modules(scene)
    return [e for s, e in SECTION_INTEGRATORS.items() if getattr(scene.spec, s, None) is not None]


def register_integrator(entry: IntegratorType, *, replace: bool = False) -> IntegratorType:
    """Add an integrator type to the scene registry (``replace=True`` to override a name)."""
    if not isinstance(entry, IntegratorType):
        raise TypeError(f"expected an IntegratorType, got {type(entry).__name__}")
    if entry.section is not None:
        if entry.section in SECTION_INTEGRATORS and not replace:
            raise ValueError(f"an integrator for [{entry.section}] is already registered (pass replace=True)")
        SECTION_INTEGRATORS[entry.section] = entry
        return entry
    if entry.name in INTEGRATORS and not replace:
        raise ValueError(f"integrator {entry.name!r} is already registered (pass replace=True)")
    if "type" in entry.keys:
        raise ValueError("integrator keys must not redefine 'type'")
    if not entry.dynamic and entry.static_solve is None:
        raise ValueError(f"quasi-static integrator {entry.name!r} needs a static_solve")
    INTEGRATORS[entry.name] = entry
    return entry


_NEWTON = ("tol", "atol", "cg_tol", "max_iters", "max_cg_iters", "project_hessian", "hessian_projection")


def _simulator(model, opts, *, device, precision, dt, dynamic, integrator="backward_euler"):
    from warpfem.simulator import Simulator

    kw = {k: opts[k] for k in _NEWTON if opts[k] is not None}  # max_iters not given: the simulator's default
    damping = {}
    if dynamic:
        damping = {"damping_mass": opts["damping_mass"], "damping_stiffness": opts["damping_stiffness"]}
    return Simulator(model, device=device, precision=precision, dt=dt, require_convergence=opts["require_convergence"],
                     integrator=integrator, linear_solver=opts.get("linear_solver", "auto"), **damping, **kw)


def _build_backward_euler(scene, model, *, device, precision):
    o = scene.spec.integrator
    return _simulator(model, o, device=device, precision=precision, dt=o["dt"], dynamic=True,
                      integrator=o.get("type", "backward_euler"))


def _build_static(scene, model, *, device, precision):
    problem = static_supports_error(model, "[[fixed]] or [[handle]]")
    if problem:
        raise ValueError(problem)
    return _simulator(model, scene.spec.integrator, device=device, precision=precision, dt=1.0, dynamic=False)


def _static_solve(sim, opts):
    return sim.solve_static(load_steps=opts["load_steps"])


_DYNAMIC_KEYS = {k: v for k, v in INTEGRATOR_KEYS.items() if k != "load_steps"}
_STATIC_KEYS = {k: v for k, v in INTEGRATOR_KEYS.items() if k not in ("dt", "damping_mass", "damping_stiffness")}

register_integrator(IntegratorType(
    "backward_euler", _build_backward_euler, keys=_DYNAMIC_KEYS, dynamic=True,
    builds=("mass matrix", "Hessian (Newton; linear solver below)", "positions/velocities")))
register_integrator(IntegratorType(
    "bdf2", _build_backward_euler, keys=_DYNAMIC_KEYS, dynamic=True,
    builds=("mass matrix", "Hessian (Newton; linear solver below)", "positions/velocities + previous step's")))
register_integrator(IntegratorType(
    "newmark", _build_backward_euler, keys=_DYNAMIC_KEYS, dynamic=True,
    builds=("mass matrix", "Hessian (Newton; linear solver below)", "positions/velocities/accelerations")))
register_integrator(IntegratorType(
    "static", _build_static, keys=_STATIC_KEYS, dynamic=False, static_solve=_static_solve,
    builds=("Hessian (Newton; linear solver below)", "positions")))



def _build_stiffness_warping(scene, model, *, device, precision):
    from warpfem.solvers.stiffness_warping import StiffnessWarpingSimulator

    o = scene.spec.integrator
    return StiffnessWarpingSimulator(model, device=device, precision=precision, dt=o["dt"], rotation=o["rotation"],
                                     cg_tol=o["cg_tol"], max_cg_iters=o["max_cg_iters"], damping_mass=o["damping_mass"],
                                     damping_stiffness=o["damping_stiffness"],
                                     require_convergence=o["require_convergence"], integrator=o["scheme"],
                                     linear_solver=o.get("linear_solver", "auto"))


_WARPING_KEYS = {k: INTEGRATOR_KEYS[k] for k in ("dt", "max_cg_iters", "damping_mass", "damping_stiffness",
                                                 "require_convergence", "linear_solver")}
_WARPING_KEYS["cg_tol"] = Key("float", default=1e-6, check=INTEGRATOR_KEYS["cg_tol"].check,
                              doc="relative PCG tolerance of the one linear solve per step")
_WARPING_KEYS["rotation"] = Key("choice", default="polar", choices=("polar", "qr"),
                                doc="element rotation: polar decomposition or Gram-Schmidt (OpenTissue)")
_WARPING_KEYS["scheme"] = Key("choice", default="backward_euler", choices=("backward_euler", "bdf2", "newmark"),
                              doc="time scheme of the one linear solve per step (docs/integrators.md)")
register_integrator(IntegratorType(
    "stiffness_warping", _build_stiffness_warping, keys=_WARPING_KEYS, dynamic=True,
    builds=("mass matrix", "warped stiffness K' (one linear solve per step; linear solver below)", "per-tet 12x12 K_e",
            "positions/velocities")))

from .scene import FrameStats, Scene, SceneRun, estimate_device_memory, handle_targets, load_scene, traction_forces  # noqa: E402
