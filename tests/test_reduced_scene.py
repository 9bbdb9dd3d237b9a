"""Reduced scenes: `warpfem train` then `warpfem run` against full runs, kinematic handles (lifting),
render surface from W U, and the errors for missing / mismatched / stale caches."""

import os
import textwrap
import warnings

import numpy as np
import pytest

import warpfem as wf
from warpfem.cli import main
from warpfem.reduced.lifting import build_lifting
from warpfem.scenes import SceneError, load_scene

BEAM = """
name = "rbeam"
gravity = [0.0, 0.0, -9.81]
[mesh]
generator = "box"
size = [8.0, 1.0, 1.0]
cells = [8, 1, 1]
[material]
model = "stable_neo_hookean"
youngs_modulus = 1e7
poisson_ratio = 0.3
density = 100.0
[[fixed]]
box_min = [-1.0, -1.0, -1.0]
box_max = [1e-6, 2.0, 2.0]
{extra}
[integrator]
type = "{integrator}"
cg_tol = 1e-8
[output]
fps = 30
frames = 12
states = "{states}"
{surface}
[subspace]
modes = {modes}
modal_derivatives = true
cubature_tolerance = 0.01
max_cubature_points = 48
training = "{training}"
"""

HANDLE = """
[[handle]]
box_min = [8.0, -1.0, -1.0]
box_max = [9.0, 2.0, 2.0]
translation = [0.0, 0.0, 1.0]
"""

SURFACE_OBJ = "v 2.0 0.2 0.3\nv 7.5 0.5 0.5\nv 7.0 0.8 0.2\nv 4.0 0.1 0.9\nf 1 2 3\nf 1 2 4\nf 2 3 4\nf 3 1 4\n"


def _scene(tmp_path, name, *, modes=12, training="mixed", extra="", integrator="backward_euler", surface="",
           gravity=None, subspace=True):
    text = BEAM.format(extra=extra, integrator=integrator, states=f"{name}.npz", surface=surface, modes=modes,
                       training=training)
    if gravity is not None:
        text = text.replace("gravity = [0.0, 0.0, -9.81]", f"gravity = {gravity}")
    if not subspace:
        text = text[:text.index("[subspace]")]
    p = tmp_path / f"{name}.toml"
    p.write_text(textwrap.dedent(text))
    return str(p)


def _run_positions(path, frames=None):
    run = load_scene(path).build()
    xs = [run.sim.positions()]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for _ in range(frames or run.frames):
            run.step_frame()
            xs.append(run.sim.positions())
    return run, np.array(xs)


@pytest.fixture(scope="module")
def full_beam(tmp_path_factory):
    d = tmp_path_factory.mktemp("full")
    return _run_positions(_scene(d, "full", subspace=False))[1]


def test_train_then_run_matches_full_run(tmp_path, capsys, full_beam, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = _scene(tmp_path, "beam")
    assert main(["run", path, "--quiet"]) == 2  # not trained yet
    err = capsys.readouterr().err
    assert "beam.subspace.npz" in err and "warpfem train" in err
    assert main(["train", path, "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "training poses: 110 (random+snapshots)" in out  # 100 random + 13 frames (rest + 12), every 4th validates
    assert "linear modal frequencies (Hz)" in out and "validation error" in out
    assert os.path.isfile(tmp_path / "beam.subspace.npz")
    assert main(["train", path, "--quiet"]) == 0 and "up to date" in capsys.readouterr().out
    assert main(["describe", path]) == 0
    desc = capsys.readouterr().out
    assert "reduced: [subspace] r = 12" in desc and "cubature points of 48 elements" in desc
    assert main(["run", path, "--quiet"]) == 0
    x_red = np.load(tmp_path / "beam.npz")["positions"]
    tip = np.flatnonzero(full_beam[0][:, 0] > 8 - 1e-6)
    tip_full, tip_red = full_beam[:, tip].mean(1), x_red[:, tip].mean(1)
    peak = np.linalg.norm(tip_full - tip_full[0], axis=1).max()
    err = np.linalg.norm(tip_red - tip_full, axis=1).max()
    assert peak > 0.15  # m: the tip really swings
    print("tip err / peak", err / peak)
    assert err <= 0.05 * peak  # stated: reduced tip within 5 % of the peak tip displacement


def test_handles_move_in_reduced_run_as_in_full_run(tmp_path):
    extra = HANDLE
    full = _scene(tmp_path, "hfull", extra=extra, subspace=False, gravity="[0.0, 0.0, 0.0]")
    red = _scene(tmp_path, "hred", extra=extra, modes=10, training="random", gravity="[0.0, 0.0, 0.0]")
    assert main(["train", red, "--quiet"]) == 0
    _, xf = _run_positions(full)
    run, xr = _run_positions(red)
    scene = load_scene(red)
    ids = scene.selections()["handle"][0]
    # handle vertices follow their targets exactly (the lifting reproduces an affine handle motion)
    assert np.allclose(xr[-1][ids] - xr[0][ids], [0.0, 0.0, 1.0], atol=1e-10)
    mid = np.flatnonzero(np.abs(xf[0][:, 0] - 4.0) < 1e-6)
    d_full = xf[:, mid].mean(1) - xf[0][mid].mean(0)
    d_red = xr[:, mid].mean(1) - xr[0][mid].mean(0)
    peak = np.linalg.norm(d_full, axis=1).max()
    assert peak > 0.2
    print("mid err / peak", np.linalg.norm(d_red - d_full, axis=1).max() / peak)
    assert np.linalg.norm(d_red - d_full, axis=1).max() <= 0.05 * peak  # stated: 5 % of the mid-span peak
    # a subspace trained for the handle refuses a scene without it, and vice versa
    with pytest.raises(SceneError, match="handle"):
        noh = _scene(tmp_path, "noh", modes=10, training="random", gravity="[0.0, 0.0, 0.0]")
        os.replace(tmp_path / "hred.subspace.npz", tmp_path / "noh.subspace.npz")
        load_scene(noh).build()


def test_lifting_is_the_static_extension_of_handle_motion():
    mesh = wf.box_tet_mesh(size=(4.0, 1.0, 1.0), cells=(4, 2, 2))
    model = wf.Model(mesh, wf.LinearElastic(youngs_modulus=1e6, poisson_ratio=0.3, density=10.0))
    clamp = wf.select_vertices_in_box(mesh.vertices, (-1, -1, -1), (1e-6, 2, 2))
    handle = wf.select_vertices_in_box(mesh.vertices, (4 - 1e-6, -1, -1), (5, 2, 2))
    model.fix(clamp)
    model.fix(handle)
    lift = build_lifting(model, [(handle, "xyz")])
    assert lift.size == 9  # a flat handle: affine functions 1, y, z (no x across it) x 3 components
    # a rotation + translation of the handle is reproduced exactly on its vertices
    from warpfem.scenes import handle_targets

    target = handle_targets(mesh.vertices[handle], {"translation": (0.1, -0.2, 0.3), "rotation_axis": (1, 0, 0),
                                                   "rotation_angle": 20.0}, 1.0)
    a = lift.group_coords(0, target)
    x = mesh.vertices + (lift.L @ a).reshape(-1, 3)
    assert np.abs(x[handle] - target).max() <= 1e-12
    assert np.abs(x[clamp] - mesh.vertices[clamp]).max() == 0.0
    # linear elasticity: the interior is in equilibrium (free forces ~ 0 vs reaction forces)
    sim = wf.Simulator(model)
    f = sim.elastic_forces(x)
    free = ~model.fixed.any(axis=1)
    assert np.abs(f[free]).max() <= 1e-9 * np.abs(f[handle]).max()
    # snapshot projection recovers [q; a] of a pose in the subspace exactly
    from warpfem.reduced import linear_modes
    from warpfem.reduced.cubature import snapshot_poses

    U, _, _ = linear_modes(model, 5, sim=sim)
    q0 = np.array([0.1, -0.05, 0.02, 0.01, -0.03])
    z = snapshot_poses(U, model, [x + (U @ q0).reshape(-1, 3)], lifting=lift, sim=sim)[0]
    assert np.allclose(z, np.concatenate([q0, a]), rtol=0, atol=1e-12 * np.abs(a).max())


def test_render_surface_from_precomputed_basis(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "s.obj").write_text(SURFACE_OBJ)
    path = _scene(tmp_path, "surf", modes=8, training="random", surface='[surface]\npath = "s.obj"')
    assert main(["train", path, "--quiet"]) == 0
    run = load_scene(path).build()
    assert run.skinner is None  # no full-mesh skinning: the reduced simulator maps the surface itself
    for _ in range(3):
        run.step_frame()
    pts = run.surface_points()
    ref = run.embedding.apply(run.sim.positions())
    assert np.abs(pts - ref).max() <= 1e-12 * np.abs(ref).max()
    assert np.abs(pts - run.embedding.apply(run.model.rest_positions)).max() > 1e-3  # it moved


def test_reduced_scene_errors(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    # [subspace] needs backward Euler
    st = _scene(tmp_path, "st", integrator="static", training="random")
    with pytest.raises(SceneError, match="backward_euler"):
        load_scene(st).build()
    assert main(["train", st, "--quiet"]) == 2 and "backward_euler" in capsys.readouterr().err
    # nothing to train without [subspace]
    plain = _scene(tmp_path, "plain", subspace=False)
    assert main(["train", plain, "--quiet"]) == 2 and "no [subspace]" in capsys.readouterr().err
    # a cache for another material / other settings is refused, naming the file and what differs
    a = _scene(tmp_path, "a", modes=6, training="random")
    assert main(["train", a, "--quiet"]) == 0
    capsys.readouterr()
    text = open(a).read()
    open(a, "w").write(text.replace("youngs_modulus = 1e7", "youngs_modulus = 2e7"))
    with pytest.raises(SceneError, match=r"a\.subspace\.npz.*youngs_modulus.*warpfem train"):
        load_scene(a).build()
    open(a, "w").write(text.replace("modes = 6", "modes = 7"))
    with pytest.raises(SceneError, match=r"modes: cache 6 vs scene 7"):
        load_scene(a).build()
    open(a, "w").write(text)
    run = load_scene(a).build()
    with pytest.raises(ValueError, match="without kinematic handles"):
        run.sim.set_targets([0], [[0.0, 0.0, 0.0]])
