"""Scene files: validation messages, what gets built, traction integration, handle motion."""

import math
import os
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
        load_scene(p)  # paths to the shipped meshes resolve (relative to the scene file)
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


# ----------------------------------------------------------------------------- element types
@pytest.mark.parametrize("element,elements,vertices,k,q", [
    ("tet4", 24, 20, 4, 1),
    ("tet10", 24, 20 + 4 * 3 * 1 + 5 * 2 + 5 * 1 * 2 + 4 * 1 * 1 + 4 + 6 * 4 + 4, 10, 4),
    ("hex8", 4, 20, 8, 8),
    ("hex27", 4, 9 * 3 * 3, 27, 27),
])
def test_element_types_build_and_describe(tmp_path, element, elements, vertices, k, q):
    from warpfem.mesh import tet10_from_tet4
    from warpfem.mesh import box_tet_mesh

    if element == "tet10":  # vertices = corners + one mid-node per unique edge of the 24 tets
        vertices = tet10_from_tet4(box_tet_mesh(size=(1, .2, .2), cells=(4, 1, 1))).num_vertices
    scene = load_scene(write(tmp_path, BASE.replace('cells = [4, 1, 1]', f'cells = [4, 1, 1]\nelement = "{element}"')))
    text = scene.describe()
    assert f"element {element} (" in text and f"{elements} elements, {vertices} vertices, {3 * vertices} DOFs" in text
    assert f"{k} nodes per element, {q} quadrature point(s) per element, {elements * q} quadrature points" in text
    mesh = scene.mesh()
    assert mesh.num_elements == elements and mesh.num_vertices == vertices
    assert getattr(mesh, "element_type", "tet4") == element
    run = scene.build(device="cpu")
    assert run.model.quadrature.element_type == element and run.model.quadrature.num_points == elements * q
    # boundary render surface through every boundary node; its triangles enclose the beam's volume
    ids, tri = run.surface_vertex_ids, run.surface_faces
    Y = run.model.rest_positions[ids][tri]
    assert np.einsum("ij,ij->i", np.cross(Y[:, 1], Y[:, 2]), Y[:, 0]).sum() / 6.0 == pytest.approx(0.04, rel=1e-12)
    fixed = scene.selections()["fixed"][0]
    assert np.all(run.model.fixed[fixed]) and np.all(run.model.rest_positions[fixed, 0] == 0.0)


def test_element_rejections(tmp_path):
    hexed = BASE.replace('cells = [4, 1, 1]', 'cells = [4, 1, 1]\nelement = "hex8"')
    rejects(tmp_path, BASE.replace('cells = [4, 1, 1]', 'cells = [4, 1, 1]\nelement = "hex9"'), "[mesh].element",
            "must be one of", "did you mean 'hex8'")
    rejects(tmp_path, BASE.replace("density = 1000.0", 'density = 1000.0\nvolumetric_integration = "reduced"'),
            "[material].volumetric_integration", "only available for element = \"hex8\"", "'tet4'")
    rejects(tmp_path, hexed.replace("density = 1000.0", 'density = 1000.0\nvolumetric_integration = "reduced"')
            .replace("poisson_ratio = 0.3", "poisson_ratio = -0.2"),
            "[material].volumetric_integration", "needs poisson_ratio >= 0", "-0.2")
    rejects(tmp_path, hexed.replace('type = "backward_euler"', 'type = "stiffness_warping"'), "[integrator].type",
            "'stiffness_warping' supports element 'tet4' only", "'hex8'", "backward_euler")
    # a tet file cannot become a hex mesh: clear error at describe/build (the file is read then)
    from warpfem.mesh import box_tet_mesh, save_mesh

    save_mesh(box_tet_mesh(size=(1, .2, .2), cells=(2, 1, 1)), str(tmp_path / "beam.msh"))
    from_file = BASE.replace('generator = "box"\nsize = [1.0, 0.2, 0.2]\ncells = [4, 1, 1]', 'path = "beam.msh"')
    rejects(tmp_path, from_file.replace('path = "beam.msh"', 'path = "beam.msh"\nelement = "hex8"\ninside_surface = true'),
            "[mesh].inside_surface", "only applies to tetra meshes")
    scene = load_scene(write(tmp_path, from_file.replace('path = "beam.msh"', 'path = "beam.msh"\nelement = "hex8"')))
    with pytest.raises(SceneError, match=r"\[mesh\]\.element: .*beam\.msh holds cells .*tetra \(12\).*a tet mesh cannot "
                                         r"be turned into hex8 elements") as e:
        scene.describe()
    assert "\n" not in str(e.value)
    # the same file as tet10: converted (one mid-node per edge)
    scene = load_scene(write(tmp_path, from_file.replace('path = "beam.msh"', 'path = "beam.msh"\nelement = "tet10"')))
    assert scene.mesh().element_type == "tet10" and scene.mesh().num_elements == 12


def test_hex8_reduced_integration_from_scene(tmp_path):
    """nu = 0.4999: the selectively integrated Hex8 beam (linear) sags far more than the locking
    fully integrated one, and describe reports 8 + 1 points per element."""
    text = BASE.replace('cells = [4, 1, 1]', 'cells = [8, 2, 2]\nelement = "hex8"').replace(
        'model = "stable_neo_hookean"', 'model = "linear"').replace("poisson_ratio = 0.3", "poisson_ratio = 0.4999").replace(
        'type = "backward_euler"\ndt = 0.05', 'type = "static"')
    sag = {}
    for vi in ("full", "reduced"):
        scene = load_scene(write(tmp_path, text.replace("density = 1000.0", f'density = 1000.0\nvolumetric_integration = "{vi}"'),
                                 name=f"{vi}.toml"))
        if vi == "reduced":
            assert "9 quadrature point(s) per element" in scene.describe()
        run = scene.build(device="cpu", precision="float64")
        run.run(frames=1)
        sag[vi] = -(run.sim.positions() - run.model.rest_positions)[:, 1].min()
    assert sag["reduced"] > 5.0 * sag["full"] > 0.0, sag


@pytest.mark.parametrize("element", ["tet10", "hex8", "hex27"])
def test_element_traction_is_consistent(tmp_path, element):
    from warpfem.scenes.scene import element_traction_forces

    t = np.array([10.0, -250.0, 3.0])
    scene = load_scene(write(tmp_path, BASE.replace('cells = [4, 1, 1]', f'cells = [4, 1, 1]\nelement = "{element}"') + f"""
[[traction]]
box_min = [-1.0, 0.2, -1.0]
box_max = [2.0, 1.0, 1.0]
force_per_area = {t.tolist()}
"""))
    (f, faces, area), = scene.tractions()
    assert area == pytest.approx(0.2, rel=1e-13) and len(faces) == (8 if element == "tet10" else 4)
    np.testing.assert_allclose(f.sum(axis=0), t * 0.2, rtol=1e-13)
    X = scene.mesh().vertices
    top = np.flatnonzero(np.abs(X[:, 1] - 0.2) < 1e-12)
    assert np.abs(f[np.setdiff1d(np.arange(len(X)), top)]).max() < 1e-14 * np.abs(t).max()
    # nodal shares of the face integral int N_a dA (face area a = 0.25 x 0.2 per element face)
    a = 0.05
    if element == "hex8":  # bilinear: A/4 per corner, corners shared by up to 4 faces
        shares = np.where((np.abs(X[top, 0]) < 1e-12) | (np.abs(X[top, 0] - 1.0) < 1e-12), 1, 2) * a / 4
        np.testing.assert_allclose(f[top], shares[:, None] * t[None, :], rtol=1e-12)
    elif element == "tet10":  # quadratic triangles: corners get 0, mid-edge nodes A/3 of each triangle
        corner = top[top < 20]
        assert np.abs(f[corner]).max() < 1e-12 * np.abs(t).max()
    else:  # biquadratic 9-node face: corner A/36, edge A/9, centre 4A/9
        centre = top[np.all(np.abs(X[top] - [0.125, 0.2, 0.1]) < 1e-12, axis=1)]
        np.testing.assert_allclose(f[centre[0]], 4 * a / 9 * t, rtol=1e-12)
        corner = top[np.all(np.abs(X[top] - [0.0, 0.2, 0.0]) < 1e-12, axis=1)]
        np.testing.assert_allclose(f[corner[0]], a / 36 * t, rtol=1e-12)
    # element_traction_forces agrees with the tet formula on a tet4 mesh
    from warpfem.mesh import box_tet_mesh

    m = box_tet_mesh(size=(1, .2, .2), cells=(4, 1, 1))
    f4, _, area4 = element_traction_forces(m, (-1, 0.2, -1), (2, 1, 1), t)
    f4_ref, _, _ = traction_forces(m.vertices, m.boundary_faces(), (-1, 0.2, -1), (2, 1, 1), t)
    np.testing.assert_allclose(f4, f4_ref, atol=1e-14)
    assert area4 == pytest.approx(0.2, rel=1e-13)


@pytest.mark.parametrize("element", ["tet10", "hex8"])
def test_surface_embeds_in_higher_order_elements(tmp_path, element):
    (tmp_path / "s.obj").write_text(CUBE_OBJ)
    text = BASE.replace('cells = [4, 1, 1]', f'cells = [4, 1, 1]\nelement = "{element}"') + '[surface]\npath = "s.obj"\n'
    scene = load_scene(write(tmp_path, text))
    k = {"tet10": 10, "hex8": 8}[element]
    assert f"embedded in the {element} elements ({k} shape functions per vertex)" in scene.describe()
    run = scene.build(device="cpu")
    assert run.embedding.weights.shape == (5, k) and run.skinner.weights_per_point == k
    A = np.array([[1.1, 0.2, 0.0], [0.0, 0.9, 0.1], [0.05, 0.0, 1.2]])
    c = np.array([0.3, -0.2, 0.1])
    run.sim.set_positions(run.model.rest_positions @ A.T + c)
    pts = np.array([[float(v) for v in line.split()[1:]] for line in CUBE_OBJ.splitlines() if line.startswith("v ")])
    np.testing.assert_allclose(run.surface_points(), pts @ A.T + c, atol=1e-12)


def test_states_npz_streams_and_matches_run(tmp_path):
    states = tmp_path / "o" / "s.npz"
    text = BASE.replace("frames = 2", f'frames = 3\nstates = "{states}"\nclip_frames = 2\nusd = "{tmp_path / "o" / "s.usda"}"')
    run = load_scene(write(tmp_path, text)).build(device="cpu")
    run.run()
    d = np.load(states)
    assert d["positions"].shape == (4, 20, 3) and d["times"] == pytest.approx([0.0, 0.05, 0.1, 0.15])
    np.testing.assert_array_equal(d["positions"][-1], run.sim.positions())
    # no temporaries left; the checkpoint (for --resume) stays
    assert sorted(os.listdir(tmp_path / "o")) == ["s.checkpoint.npz", "s.clips", "s.npz", "s.stats.jsonl", "s.usda"]
    assert sorted(os.listdir(tmp_path / "o" / "s.clips")) == ["clip_000000.usdc", "clip_000001.usdc", "manifest.usda"]


def test_rebase_scene_paths_covers_bodies_tractions_and_colliders():
    """A scene written to another folder (fit --out, tune's winner) keeps reading the same files:
    relative paths re-anchored, absolute ones and non-path keys kept."""
    import os

    from warpfem.scenes.schema import rebase_scene_paths

    src, out = os.path.join("a", "scenes"), os.path.join("a", "results", "fits")
    absolute = os.path.abspath("bowl.obj")
    doc = {"mesh": {"path": "../meshes/m.obj", "cells": [1, 1, 1]},
           "traction": [{"indices_file": "ids.txt"}], "collider": [{"type": "mesh", "path": absolute}],
           "body": [{"mesh": {"path": "ball.obj"}, "fixed": [{"indices_file": "fix.txt"}]}]}
    rebase_scene_paths(doc, src, out)
    expect = lambda p: os.path.relpath(os.path.join(src, p), out)  # noqa: E731
    assert doc["mesh"]["path"] == expect("../meshes/m.obj") == os.path.join("..", "..", "meshes", "m.obj")
    assert doc["traction"][0]["indices_file"] == expect("ids.txt")
    assert doc["collider"][0]["path"] == absolute and doc["mesh"]["cells"] == [1, 1, 1]
    assert doc["body"][0]["mesh"]["path"] == expect("ball.obj")
    assert doc["body"][0]["fixed"][0]["indices_file"] == expect("fix.txt")
