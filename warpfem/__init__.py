"""warpfem: deformable-body finite elements with NVIDIA Warp kernels (CPU and CUDA).

Public API (one import path per symbol)::

    import warpfem as wf
    mesh = wf.box_tet_mesh(size=(10, 1, 1), cells=(20, 2, 2))
    material = wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0)
    model = wf.Model(mesh, material, gravity=(0.0, 0.0, -9.81))
    model.fix(wf.select_vertices_in_box(mesh, (-1, -1, -1), (1e-6, 2, 2)))
    sim = wf.Simulator(model, device="cpu", precision="float64", dt=1 / 60)
    stats = sim.step()
    sim.add_collider(wf.Plane(point=(0, -1, 0), normal=(0, 1, 0), friction=0.3))  # contact (docs/contact.md)

Warp's start-up banner and ``Module ... load`` lines are off once warpfem is imported (warnings are
not); ``WARPFEM_VERBOSE=1`` shows them (:mod:`warpfem.device`).
"""

from warpfem.device import configure_warp as _configure_warp

_configure_warp()  # quiet unless WARPFEM_VERBOSE; before any warpfem module can initialise Warp

from typing import TYPE_CHECKING  # noqa: E402

if TYPE_CHECKING:  # the same names for type checkers and the API docs (mkdocstrings reads them statically)
    from warpfem.materials import (
        Corotated,
        LinearElastic,
        StableNeoHookean,
        StableNeoHookeanLog,
        StVenantKirchhoff,
        make_material,
    )
    from warpfem.mesh import (ElementMesh, MeshError, TetMesh, VolumeMesh, box_hex_mesh, box_tet_mesh,
                              embed_points_in_elements, load_element_mesh, load_mesh, save_element_mesh, save_mesh,
                              select_vertices_in_box, tet10_from_tet4)
    from warpfem.model import Body, Model
    from warpfem.rigid import RigidBody
    from warpfem.integrators import BDF2, BackwardEuler, Integrator, Newmark
    from warpfem.simulator import Simulator
    from warpfem.solvers.nonlinear import NewtonOptions, SolveFailed, SolveStats
    from warpfem.solvers.stiffness_warping import StiffnessWarpingSimulator
    from warpfem.solvers.state import Control, State
    from warpfem.solvers.forms import Form
    from warpfem.contact import Box, Capsule, CollisionError, MeshCollider, Plane, Sphere
    from warpfem.io.checkpoint import CheckpointError, load_state, save_state
    from warpfem.threads import ThreadsError, get_threads, set_threads

from warpfem.lazy import lazy_attributes  # noqa: E402

# name -> the module that defines it. Imported on first access (PEP 562), so ``import warpfem`` costs
# Warp's import and little more; a scene loads only the solvers, contact and I/O modules it uses.
_LAZY = {
    **dict.fromkeys(["Corotated", "LinearElastic", "StableNeoHookean", "StableNeoHookeanLog", "StVenantKirchhoff",
                     "make_material"], "warpfem.materials"),
    **dict.fromkeys(["ElementMesh", "MeshError", "TetMesh", "VolumeMesh", "box_hex_mesh", "box_tet_mesh",
                     "embed_points_in_elements", "load_element_mesh", "load_mesh", "save_element_mesh", "save_mesh",
                     "select_vertices_in_box", "tet10_from_tet4"], "warpfem.mesh"),
    **dict.fromkeys(["Body", "Model"], "warpfem.model"),
    "RigidBody": "warpfem.rigid",
    **dict.fromkeys(["BDF2", "BackwardEuler", "Integrator", "Newmark"], "warpfem.integrators"),
    "Simulator": "warpfem.simulator",
    **dict.fromkeys(["NewtonOptions", "SolveFailed", "SolveStats"], "warpfem.solvers.nonlinear"),
    "StiffnessWarpingSimulator": "warpfem.solvers.stiffness_warping",
    **dict.fromkeys(["Control", "State"], "warpfem.solvers.state"),
    "Form": "warpfem.solvers.forms",
    **dict.fromkeys(["Box", "Capsule", "CollisionError", "MeshCollider", "Plane", "Sphere"], "warpfem.contact"),
    **dict.fromkeys(["save_state", "load_state", "CheckpointError"], "warpfem.io.checkpoint"),
    **dict.fromkeys(["set_threads", "get_threads", "ThreadsError"], "warpfem.threads"),
}


__getattr__, __dir__ = lazy_attributes(__name__, _LAZY)


__version__ = "0.1.0"

__all__ = [
    "BDF2",
    "BackwardEuler",
    "Integrator",
    "Newmark",
    "ElementMesh",
    "box_hex_mesh",
    "embed_points_in_elements",
    "load_element_mesh",
    "save_element_mesh",
    "tet10_from_tet4",
    "Corotated",
    "LinearElastic",
    "MeshError",
    "Model",
    "Body",
    "RigidBody",
    "NewtonOptions",
    "Simulator",
    "State",
    "Control",
    "Form",
    "SolveFailed",
    "SolveStats",
    "StVenantKirchhoff",
    "StableNeoHookean",
    "StableNeoHookeanLog",
    "StiffnessWarpingSimulator",
    "TetMesh",
    "VolumeMesh",
    "box_tet_mesh",
    "load_mesh",
    "make_material",
    "save_mesh",
    "select_vertices_in_box",
    "__version__",
    "Plane",
    "Sphere",
    "Box",
    "Capsule",
    "MeshCollider",
    "CollisionError",
    "save_state",
    "load_state",
    "CheckpointError",
    "set_threads",
    "get_threads",
    "ThreadsError",
]
