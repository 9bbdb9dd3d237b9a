"""Scene files: validation messages, what gets built, traction integration, handle motion."""

import math
import textwrap

import numpy as np
import pytest

from warpfem.scenes import (INTEGRATORS, IntegratorType, SceneError, handle_targets, load_scene, register_integrator,
                            traction_forces)

BASE = """
gravity = [0.0, -9.81, 0.0]
[mesh]
generator = "box"
size = [1.0, 0.2, 0.2]
cells = [4, 1, 1]
[material]
model = "stable_neo_hookean"
youngs_modulus = 1e5
poisson_ratio = 0.3
density = 1000.0
[[fixed]]
box_min = [-1.0, -1.0, -1.0]
box_max = [0.0, 1.0, 1.0]
[integrator]
type = "backward_euler"
dt = 0.05
[output]
fps = 20
frames = 2
"""

CUBE_OBJ = """v 0.2 0.05 0.05
v 0.8 0.05 0.05
v 0.8 0.15 0.05
v 0.2 0.15 0.05
v 0.5 0.1 0.15
f 1 2 3
f 1 3 4
f 1 2 5
f 2 3 5
f 3 4 5
f 4 1 5
"""


def write(tmp_path, text, name="scene.toml"):
    p = tmp_path / name
    p.write_text(textwrap.dedent(text))
    return p


def rejects(tmp_path, text, *fragments):
    p = write(tmp_path, text)
    with pytest.raises(SceneError) as e:
        load_scene(p)
    msg = str(e.value)
    assert msg.startswith(str(p)), msg
    for f in fragments:
        assert f in msg, msg
    assert "\n" not in msg
    return msg


def test_unknown_key_with_suggestion(tmp_path):
    rejects(tmp_path, BASE.replace("youngs_modulus", "youngs_modulos"), "[material].youngs_modulos",
            "unknown key", "did you mean 'youngs_modulus'")
    rejects(tmp_path, BASE.replace("[output]", "[outptu]"), "outptu", "did you mean 'output'")
    rejects(tmp_path, BASE.replace('type = "backward_euler"', 'type = "backward_eular"'), "[integrator].type",
            "did you mean 'backward_euler'")
    rejects(tmp_path, BASE.replace("box_max", "box_mux"), "[[fixed]] #1.box_mux", "did you mean 'box_max'")
    # a key written in the wrong section says where it belongs
    rejects(tmp_path, BASE.replace("fps = 20", "fps = 20\ngravity = [0.0, 0.0, 0.0]"), "[output].gravity", "top level")


def test_wrong_types(tmp_path):
    rejects(tmp_path, BASE.replace("youngs_modulus = 1e5", 'youngs_modulus = "stiff"'), "[material].youngs_modulus",
            "expected a number", "'stiff'")
    rejects(tmp_path, BASE.replace("cells = [4, 1, 1]", "cells = [4, 1.5, 1]"), "[mesh].cells", "3 integers")
    rejects(tmp_path, BASE.replace("frames = 2", "frames = 2.0"), "[output].frames", "expected an integer")
    rejects(tmp_path, BASE.replace("gravity = [0.0, -9.81, 0.0]", "gravity = [0.0, -9.81]"), "gravity", "3 numbers")


@pytest.mark.parametrize("old,new,where,what", [
    ("poisson_ratio = 0.3", "poisson_ratio = 0.5", "[material].poisson_ratio", "0.5"),
    ("poisson_ratio = 0.3", "poisson_ratio = 0.7", "[material].poisson_ratio", "0.7"),
    ("youngs_modulus = 1e5", "youngs_modulus = 0.0", "[material].youngs_modulus", "must be > 0"),
    ("youngs_modulus = 1e5", "youngs_modulus = -3.0", "[material].youngs_modulus", "must be > 0"),
    ("dt = 0.05", "dt = 0.0", "[integrator].dt", "must be > 0"),
    ("dt = 0.05", "dt = -0.01", "[integrator].dt", "must be > 0"),
    ("density = 1000.0", "density = 0.0", "[material].density", "must be > 0"),
    ("dt = 0.05", "dt = 0.03", "[integrator].dt", "divide the frame time"),
])
def test_out_of_range(tmp_path, old, new, where, what):
    assert old in BASE
    rejects(tmp_path, BASE.replace(old, new), where, what)


def test_missing_files(tmp_path):
    mesh_scene = BASE.replace('generator = "box"\nsize = [1.0, 0.2, 0.2]\ncells = [4, 1, 1]', 'path = "nowhere/beam.mesh"')
    rejects(tmp_path, mesh_scene, "[mesh].path", "file not found", "nowhere/beam.mesh")
    rejects(tmp_path, BASE + '[surface]\npath = "render.obj"\n', "[surface].path", "file not found", "render.obj")
    with pytest.raises(SceneError, match="scene file not found"):
        load_scene(tmp_path / "no_such_scene.toml")
    rejects(tmp_path, BASE + "[[handle]]\nbox_min = [0.9, -1, -1]\n", "[[handle]] #1.box_max", "required")
    rejects(tmp_path, "gravity = [0, 0, 0\n", "not valid TOML")


def test_paths_resolve_relative_to_scene_file(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "s.obj").write_text(CUBE_OBJ)
    scene = load_scene(write(tmp_path, BASE + '[surface]\npath = "sub/s.obj"\n'))
    assert scene.spec.surface["path"] == str(tmp_path / "sub" / "s.obj")


def test_shipped_scenes_validate():
    from pathlib import Path

    root = Path(__file__).resolve().parents[1] / "examples" / "scenes"
    names = sorted(p.stem for p in root.glob("*.toml"))
    assert {"cantilever", "bunny", "octopus"} <= set(names)
    for p in root.glob("*.toml"):
        load_scene(p)  # paths to ../shared meshes resolve
    bunny = load_scene(root / "bunny.toml")
    assert bunny.spec.surface is not None and bunny.spec.mesh["inside_surface"]


def test_describe_counts_and_memory(tmp_path):
    text = load_scene(write(tmp_path, BASE)).describe()
    # 4x1x1 cells: 24 tets, 5*2*2 = 20 vertices
    assert "24 elements, 20 vertices, 60 DOFs" in text
    assert "fixed #1: 4 vertices" in text
    assert "estimated device memory (float64)" in text and "estimated device memory (float32)" in text
    assert "no embedding" in text


def test_no_surface_builds_no_embedding(tmp_path):
    run = load_scene(write(tmp_path, BASE)).build(device="cpu")
    assert run.skinner is None and run.embedding is None
    # render surface = tet boundary: every vertex of this 4x1x1 box is on the boundary
    # (2 triangles per boundary quad: 2 x (4x1 + 4x1 + 1x1) quads)
    assert run.num_surface_points == 20 and run.surface_faces.shape == (2 * 2 * (4 + 4 + 1), 3)
    assert np.array_equal(run.surface_points(), run.model.rest_positions[run.surface_vertex_ids])


def test_surface_is_embedded_and_follows_affine_motion(tmp_path):
    (tmp_path / "s.obj").write_text(CUBE_OBJ)
    run = load_scene(write(tmp_path, BASE + '[surface]\npath = "s.obj"\n')).build(device="cpu")
    assert run.skinner is not None and run.embedding.num_points == 5 and run.embedding.num_outside == 0
    A = np.array([[1.1, 0.2, 0.0], [0.0, 0.9, 0.1], [0.05, 0.0, 1.2]])
    c = np.array([0.3, -0.2, 0.1])
    run.sim.set_positions(run.model.rest_positions @ A.T + c)
    pts = np.array([[float(v) for v in line.split()[1:]] for line in CUBE_OBJ.splitlines() if line.startswith("v ")])
    np.testing.assert_allclose(run.surface_points(), pts @ A.T + c, atol=1e-12)


def test_traction_single_triangle_is_t_area_over_3():
    X = np.array([[0.0, 0, 0], [2.0, 0, 0], [0.0, 3.0, 0], [0.0, 0, 1.0]])
    faces = np.array([[0, 2, 1], [0, 1, 3]])
    t = np.array([1.5, -2.0, 4.0])
    f, sel, area = traction_forces(X, faces, (-1, -1, -0.1), (3, 4, 0.1), t)  # only face 0 (z = 0)
    assert sel.tolist() == [0] and area == pytest.approx(3.0, abs=1e-15)
    np.testing.assert_allclose(f[[0, 1, 2]], np.tile(t * 3.0 / 3.0, (3, 1)), rtol=0, atol=1e-15)
    assert np.all(f[3] == 0)


def test_traction_total_equals_force_per_area_times_area(tmp_path):
    t = [10.0, -250.0, 3.0]
    scene = load_scene(write(tmp_path, BASE + f"""
[[traction]]
box_min = [-1.0, 0.2, -1.0]
box_max = [2.0, 1.0, 1.0]
force_per_area = {t}
"""))
    (f, faces, area), = scene.tractions()
    assert area == pytest.approx(1.0 * 0.2, rel=1e-14)   # the face y = 0.2 of the 1 x 0.2 x 0.2 beam
    assert len(faces) == 4 * 1 * 2                       # 4x1 quads, 2 triangles each
    np.testing.assert_allclose(f.sum(axis=0), np.array(t) * 0.2, rtol=1e-13)
    # the model carries it (no other applied forces in BASE)
    run = scene.build(device="cpu")
    np.testing.assert_allclose(run.model.forces.sum(axis=0), np.array(t) * 0.2, rtol=1e-13)


def test_handle_targets_rotation_and_translation():
    rest = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    h = {"translation": (0.0, 0.0, 2.0), "rotation_axis": (0.0, 0.0, 5.0), "rotation_angle": 90.0, "rotation_center": None}
    x = handle_targets(rest, h, 0.5)  # 45 degrees about the centroid (origin), half the translation
    c = math.sqrt(0.5)
    np.testing.assert_allclose(x[0], [c, c, 1.0], atol=1e-15)
    np.testing.assert_allclose(handle_targets(rest, h, 1.0)[1], [-1.0, 0.0, 2.0], atol=1e-15)
    np.testing.assert_allclose(handle_targets(rest, h, 0.0), rest, atol=0)


def test_static_handle_reaches_target_exactly(tmp_path):
    scene = load_scene(write(tmp_path, BASE.replace('type = "backward_euler"\ndt = 0.05', 'type = "static"\nload_steps = 2') + """
[[handle]]
box_min = [1.0, -1.0, -1.0]
box_max = [2.0, 1.0, 1.0]
translation = [0.0, 0.05, 0.02]
rotation_axis = [1.0, 0.0, 0.0]
rotation_angle = 10.0
"""))
    run = scene.build(device="cpu", precision="float64")
    stats = run.run(frames=2)
    assert len(stats) == 2 and all(s.converged for s in stats)
    ids = scene.selections()["handle"][0]
    rest = run.model.rest_positions[ids]
    target = handle_targets(rest, scene.spec.handle[0], 1.0)
    np.testing.assert_array_equal(run.sim.positions()[ids], target)
    fixed = scene.selections()["fixed"][0]
    np.testing.assert_array_equal(run.sim.positions()[fixed], run.model.rest_positions[fixed])
    # the free end really moved with it (the beam bends, it does not tear)
    assert np.abs(run.sim.positions() - run.model.rest_positions).max() > 0.04


def test_static_needs_supports(tmp_path):
    text = BASE.replace('type = "backward_euler"\ndt = 0.05', 'type = "static"').replace('box_max = [0.0, 1.0, 1.0]', 'box_max = [0.0, 1.0, 1.0]\ncomponents = "y"')
    with pytest.raises(SceneError, match=r"\[integrator\].*free axes"):
        load_scene(write(tmp_path, text)).build(device="cpu")
    rejects(tmp_path, BASE.replace('type = "backward_euler"\ndt = 0.05', 'type = "static"\ndt = 0.1'), "[integrator].dt", "unknown key")


def test_integrator_registry_is_extensible(tmp_path):
    entry = IntegratorType("my_test_integrator", lambda scene, model, **kw: None,
                           keys={**INTEGRATORS["backward_euler"].keys, "stiffness_update": INTEGRATORS["backward_euler"].keys["max_iters"]}, dynamic=True)
    register_integrator(entry)
    try:
        text = BASE.replace('type = "backward_euler"', 'type = "my_test_integrator"\nstiffness_update = 3')
        assert load_scene(write(tmp_path, text)).spec.integrator["stiffness_update"] == 3
        rejects(tmp_path, text.replace("stiffness_update", "stiffness_updat"), "did you mean 'stiffness_update'")
        with pytest.raises(ValueError, match="already registered"):
            register_integrator(entry)
    finally:
        INTEGRATORS.pop("my_test_integrator")
