"""Reduced (subspace) simulation with optimized cubature (An, Kim & James 2008,
"Optimizing cubature for efficient integration of subspace deformations"; the Cubica library).

    import warpfem as wf
    from warpfem.reduced import train_subspace, ReducedSimulator
    sub = train_subspace(model, modes=20, modal_derivatives=True, cubature_tolerance=0.05,
                         max_cubature_points=200, seed=0, cache="beam.subspace.npz")
    rsim = ReducedSimulator(model, sub, dt=1 / 60)
    rsim.step(); x = rsim.positions()

Scenes: a ``[subspace]`` section makes ``warpfem run`` reduced (``warpfem.reduced.scene``);
``warpfem train SCENE`` (``warpfem.reduced.cli``) fills the cache. Kinematic handles move through a
prescribed displacement field (``warpfem.reduced.lifting``).
"""

from typing import TYPE_CHECKING

if TYPE_CHECKING:  # the same names for type checkers and the API docs (read statically)
    from warpfem.reduced.basis import Basis, build_basis, linear_modes, mass_pca, modal_derivatives
    from warpfem.reduced.cubature import Cubature, relative_force_error, snapshot_poses, train_cubature, training_poses
    from warpfem.reduced.lifting import Lifting, build_lifting
    from warpfem.reduced.simulator import CubatureForces, ReducedSimulator
    from warpfem.reduced.subspace import (
        Subspace,
        SubspaceMismatch,
        format_report,
        load_subspace,
        mesh_hash,
        train_subspace,
    )

from warpfem.lazy import lazy_attributes  # noqa: E402

# name -> defining module, imported on first access (PEP 562): the command line imports
# warpfem.reduced.cli, and a plain scene's run never loads the reduced solver (scipy.optimize)
_LAZY = {
    **dict.fromkeys(['Basis', 'build_basis', 'linear_modes', 'mass_pca', 'modal_derivatives'], 'warpfem.reduced.basis'),
    **dict.fromkeys(['Cubature', 'relative_force_error', 'snapshot_poses', 'train_cubature', 'training_poses'], 'warpfem.reduced.cubature'),
    **dict.fromkeys(['Lifting', 'build_lifting'], 'warpfem.reduced.lifting'),
    **dict.fromkeys(['CubatureForces', 'ReducedSimulator'], 'warpfem.reduced.simulator'),
    **dict.fromkeys(['Subspace', 'SubspaceMismatch', 'format_report', 'load_subspace', 'mesh_hash', 'train_subspace'],
                    'warpfem.reduced.subspace'),
}

__all__ = [
    "Basis",
    "Cubature",
    "Lifting",
    "CubatureForces",
    "ReducedSimulator",
    "Subspace",
    "SubspaceMismatch",
    "build_basis",
    "build_lifting",
    "format_report",
    "linear_modes",
    "load_subspace",
    "mass_pca",
    "mesh_hash",
    "modal_derivatives",
    "relative_force_error",
    "snapshot_poses",
    "train_cubature",
    "train_subspace",
    "training_poses",
]


__getattr__, __dir__ = lazy_attributes(__name__, _LAZY)
