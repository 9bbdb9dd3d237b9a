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
