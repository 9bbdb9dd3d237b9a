"""Rotation-aware handle lifting (``[subspace] rotation_lifting``): the interior follows a handle's
rigid motion with the rotation angle interpolated (no linear shear / candy wrapper at 90 degrees)."""


import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import warpfem as wf
from warpfem.cli import main
from warpfem.reduced import train_subspace
from warpfem.reduced.lifting import build_lifting, harmonic_weights, num_rotation_coords
from warpfem.reduced.subspace import load_subspace
from warpfem.scenes import SceneError, load_scene

from tiny_scenes import handle_toml, reduced_beam_toml, scene_positions


def _beam(clamped=True):
    mesh = wf.box_tet_mesh(size=(8.0, 1.0, 1.0), cells=(8, 1, 1))
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=1e6, poisson_ratio=0.3, density=100.0), gravity=(0, 0, 0))
    X = mesh.vertices
    clamp = wf.select_vertices_in_box(X, (-1, -1, -1), (1e-6, 2, 2)) if clamped else np.zeros(0, dtype=np.int64)
    handle = np.flatnonzero(X[:, 0] > 8 - 1e-6)
    if clamped:
        model.fix(clamp)
    model.fix(handle)
    return model, clamp, handle


def _rigid(X, c, omega, t):
    return c + (X - c) @ Rotation.from_rotvec(omega).as_matrix().T + t


def test_lifting_is_the_angle_interpolated_rigid_motion():
    model, clamp, handle = _beam()
    X = model.rest_positions
    c = X[handle].mean(0)
    omega, t = np.array([0.0, np.pi / 2, 0.0]), np.array([0.3, 0.0, 0.1])  # 90 degrees about y, + a shift
    w = harmonic_weights(model, handle, clamp)
    assert np.allclose(w, X[:, 0] / 8.0, atol=1e-12)  # a prism: the Laplace extension is linear in x
    # reference: each vertex turned by w * 90 degrees about the handle's centre, shifted by w t
    R_w = Rotation.from_rotvec(w[:, None] * omega).as_matrix()
    ref = c + np.einsum("nij,nj->ni", R_w, X - c) + w[:, None] * t
    errs = []
    for order in (5, 7, 9):
        lift = build_lifting(model, [(handle, "xyz")], rotation_order=order)
        assert lift.size == 9 + 9 + num_rotation_coords(order)  # flat handle: 3 x 3 affine + 9 rigid + series
        y = _rigid(X[handle], c, omega, t)
        x = X + (lift.L @ lift.coords_from_targets([y])).reshape(-1, 3)
        assert np.abs(x[handle] - y).max() <= 1e-12  # the handle exactly at its targets, at any order
        assert np.abs(x[clamp] - X[clamp]).max() == 0.0
        errs.append(np.abs(x - ref).max())
    # the series error falls like |omega|^(J+1) / (J+1)!: 90 degrees, r up to 8 m
    assert errs[0] < 0.05 and errs[1] < 3e-3 and errs[2] < 1e-4
    assert errs[2] < errs[1] / 10 < errs[0] / 100


def test_rigid_turn_of_a_body_held_only_by_the_handle_is_exact():
    model, _, handle = _beam(clamped=False)
    X = model.rest_positions
    lift = build_lifting(model, [(handle, "xyz")], rotation_order=3)
    for omega in ([0.0, np.pi / 2, 0.0], [0.3, 1.2, -0.5], [0.0, 0.0, 1e-6]):
        y = _rigid(X[handle], np.array([1.0, 0.2, 0.0]), np.array(omega), np.array([2.0, -1.0, 0.5]))
        x = X + (lift.L @ lift.coords_from_targets([y])).reshape(-1, 3)
        exact = _rigid(X, np.array([1.0, 0.2, 0.0]), np.array(omega), np.array([2.0, -1.0, 0.5]))
        assert np.abs(x - exact).max() <= 1e-12


def test_non_rigid_handle_motion_stays_exact_on_the_handle_and_partial_handles_stay_linear():
    model, clamp, handle = _beam()
    X = model.rest_positions
    lift = build_lifting(model, [(handle, "xyz")], rotation_order=4)
    y = X[handle] @ np.array([[1.2, 0.1, 0.0], [0.0, 0.9, 0.3], [0.2, 0.0, 1.1]]).T + 0.4  # sheared + scaled
    x = X + (lift.L @ lift.coords_from_targets([y])).reshape(-1, 3)
    assert np.abs(x[handle] - y).max() <= 1e-12
    # a handle that prescribes only z keeps the linear (elastic extension) lifting
    mesh = wf.box_tet_mesh(size=(8.0, 1.0, 1.0), cells=(8, 1, 1))
    m2 = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=1e6, poisson_ratio=0.3, density=100.0))
    m2.fix(clamp)
    m2.fix(handle, "z")
    a = build_lifting(m2, [(handle, "z")], rotation_order=7)
    b = build_lifting(m2, [(handle, "z")])
    assert a.size == b.size and np.array_equal(a.L, b.L)
    with pytest.raises(ValueError, match="rotation_order"):
        build_lifting(model, [(handle, "xyz")], rotation_order=1)


def test_rotation_lifting_is_saved_loaded_and_part_of_the_settings(tmp_path):
    model, clamp, handle = _beam()
    sub = train_subspace(model, modes=4, modal_derivatives=False, cubature_tolerance=0.5, num_training_poses=4,
                         num_validation_poses=2, handles=[(handle, "xyz")], rotation_lifting=5,
                         cache=tmp_path / "s.npz")
    assert sub.settings["rotation_lifting"] == 5 and sub.lifting.size == 18 + num_rotation_coords(5)
    back = load_subspace(tmp_path / "s.npz", model, handles=[(handle, "xyz")])
    assert np.array_equal(back.lifting.L, sub.lifting.L)
    y = _rigid(model.rest_positions[handle], np.zeros(3), np.array([0.4, -0.2, 1.0]), np.ones(3))
    assert np.allclose(back.lifting.group_coords(0, y), sub.lifting.group_coords(0, y), rtol=0, atol=1e-14)




def _run(path):
    return scene_positions(path)[1]


def test_ninety_degree_twist_needs_the_rotation_aware_lifting(tmp_path, monkeypatch):
    """The free end of a clamped beam twisted by 90 degrees (Newmark on both sides, 10 modal
    columns, no POD columns): the linear lifting collapses the middle of the beam (measured ~ 90 %
    of the corner's peak displacement off the full run), the rotation-aware lifting follows it
    (measured ~ 2 %)."""
    monkeypatch.chdir(tmp_path)

    def write(name, sub=""):
        p = tmp_path / f"{name}.toml"
        p.write_text(reduced_beam_toml(name, handle=handle_toml((1.0, 0.0, 0.0), 90.0), integrator="newmark", subspace=sub))
        return str(p)

    xf = _run(write("full"))
    X = xf[0]
    disp = np.linalg.norm(xf - X, axis=2)
    tip = int(np.argmax(disp.max(0) * (X[:, 0] < 8 - 1e-6)))  # the free vertex that moved most
    peak = disp[:, tip].max()
    assert peak > 0.3  # m: a corner at 3/4 span swings round
    errs = {}
    for rl in (0, 7):
        sub = (f'[subspace]\nmodes = 10\ntraining = "random"\nmax_cubature_points = 48\nrotation_lifting = {rl}\n')
        path = write(f"r{rl}", sub)
        assert main(["train", path, "--quiet"]) == 0
        xr = _run(path)
        errs[rl] = np.linalg.norm(xr[:, tip] - xf[:, tip], axis=1).max() / peak
    print("twist 90 degrees, tip error / peak (linear, rotation-aware):", errs)
    assert errs[0] > 0.3
    assert errs[7] < 0.06
    assert "rotation-aware handle lifting (order 7)" in load_scene(path).describe()
    text = open(path).read()
    open(path, "w").write(text.replace("rotation_lifting = 7", "rotation_lifting = 5"))
    with pytest.raises(SceneError, match=r"rotation_lifting: cache 7 vs scene 5"):
        load_scene(path).build()
