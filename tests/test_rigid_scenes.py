"""Rigid bodies in scene files (``kind = "rigid"`` [[body]] tables): one-line errors before any work,
soft bodies first whatever the file's order, and the outputs of a run: the states hold every body's
vertices (rigid ones at p + A X), the USD holds a rigid body's rest mesh under an Xform whose
4x4 transform moves it onto ``sim.vertex_positions`` (to 1e-6), the ParaView frames the same points,
and a run resumed from its checkpoint ends bit for bit as the uninterrupted one."""

from __future__ import annotations

import os

import numpy as np
import pytest

from warpfem.scenes import SceneError, load_scene

SOFT = """
[[body]]
name = "slab"
[body.mesh]
generator = "box"
size = [0.4, 0.05, 0.4]
cells = [2, 1, 2]
origin = [-0.2, 0.0, -0.2]
[body.material]
model = "stable_neo_hookean"
youngs_modulus = 1e5
poisson_ratio = 0.3
density = 500.0
"""

RIGID = """
[[body]]
name = "cube"
kind = "rigid"
offset = [0.0, 0.08, 0.0]
initial_angular_velocity = [0.0, 3.0, 1.0]
[body.mesh]
generator = "box"
size = [0.1, 0.1, 0.1]
cells = [1, 1, 1]
origin = [-0.05, 0.0, -0.05]
[body.material]
density = 500.0
"""

SHARED = """
name = "rigid_scene"
gravity = [0.0, -9.81, 0.0]
[[collider]]
type = "plane"
point = [0.0, -0.001, 0.0]
normal = [0.0, 1.0, 0.0]
[contact]
stiffness = 1000.0
[integrator]
type = "bdf2"
dt = 0.02
linear_solver = "direct"
[output]
fps = 25
frames = 3
usd = "out/s.usda"
states = "out/s.npz"
vtu = "out/s.pvd"
clip_frames = 2
usd_volume = true
"""

# an octahedron of "radius" 0.05 m: a closed outward surface
OCTA = """v 0.05 0 0
v -0.05 0 0
v 0 0.05 0
v 0 -0.05 0
v 0 0 0.05
v 0 0 -0.05
f 1 3 5
f 3 2 5
f 2 4 5
f 4 1 5
f 3 1 6
f 2 3 6
f 4 2 6
f 1 4 6
"""


def write(tmp_path, text, name="s.toml"):
    p = tmp_path / name
    p.write_text(text)
    return str(p)


@pytest.mark.parametrize("change, where, what", [
    (('kind = "rigid"', 'kind = "stiff"'), "[[body]] #1 'cube'.kind", "must be one of"),
    (("density = 500.0\n", "density = 0.0\n", 1), "'cube'.material.density", "must be > 0"),
    (("density = 500.0\n", "density = 500.0\nyoungs_modulus = 1e6\n", 1), "'cube'.material.youngs_modulus",
     "has only density"),
    (('[body.material]\ndensity = 500.0\n', '[body.material]\ndensity = 500.0\n[[body.fixed]]\n'
      'box_min = [-1.0, -1.0, -1.0]\nbox_max = [1.0, 1.0, 1.0]\n', 1), "'cube'.fixed", "cannot have [[body.fixed]]"),
    (('[body.material]\ndensity = 500.0\n', '[body.material]\ndensity = 500.0\n[[body.handle]]\n'
      'box_min = [-1.0, -1.0, -1.0]\nbox_max = [1.0, 1.0, 1.0]\n', 1), "'cube'.handle", "cannot have [[body.handle]]"),
    (('type = "bdf2"\ndt = 0.02', 'type = "static"'), "[integrator].type", "cannot hold rigid body 'cube'"),
])
def test_bad_rigid_bodies_are_one_line_errors(tmp_path, change, where, what):
    old, new, *count = change
    if old.startswith("type"):  # a static solve (no collider, no [contact]: they refuse it themselves)
        text = (SHARED + RIGID + SOFT).replace(old, new).replace(
            '[[collider]]\ntype = "plane"\npoint = [0.0, -0.001, 0.0]\nnormal = [0.0, 1.0, 0.0]\n', "").replace("[contact]\nstiffness = 1000.0\n", "")
    else:
        text = SHARED + RIGID.replace(old, new, *count) + SOFT
    with pytest.raises(SceneError) as e:
        load_scene(write(tmp_path, text))
    msg = str(e.value)
    assert "\n" not in msg and where in msg and what in msg, msg


def test_rigid_keys_on_a_soft_body_and_an_open_surface_are_refused(tmp_path):
    text = SHARED + SOFT.replace('name = "slab"\n', 'name = "slab"\ninitial_angular_velocity = [0.0, 1.0, 0.0]\n')
    with pytest.raises(SceneError, match=r"'slab'.initial_angular_velocity: only a rigid body has it"):
        load_scene(write(tmp_path, text))
    (tmp_path / "open.obj").write_text(OCTA.rsplit("f ", 1)[0])  # one triangle less: an open surface
    rigid = RIGID.replace('generator = "box"\nsize = [0.1, 0.1, 0.1]\ncells = [1, 1, 1]\norigin = [-0.05, 0.0, -0.05]',
                          'path = "open.obj"')
    scene = load_scene(write(tmp_path, SHARED + SOFT + rigid))
    with pytest.raises(SceneError) as e:
        scene.describe()
    msg = str(e.value)
    assert "\n" not in msg and "'cube': [mesh].path" in msg and "must be closed" in msg and "open" in msg, msg


def test_rigid_surface_file_and_rigid_first_in_the_file(tmp_path):
    """A rigid body from a closed .obj (not tetrahedralised: its triangles), listed before the soft
    one: the model has the soft body first; mass and centre of mass are the octahedron's."""
    (tmp_path / "octa.obj").write_text(OCTA)
    rigid = RIGID.replace('generator = "box"\nsize = [0.1, 0.1, 0.1]\ncells = [1, 1, 1]\norigin = [-0.05, 0.0, -0.05]',
                          'path = "octa.obj"').replace("[0.0, 0.08, 0.0]", "[0.0, 0.15, 0.0]")
    run = load_scene(write(tmp_path, SHARED + rigid + SOFT)).build(device="cpu")
    assert run.model.body_names == ["slab", "cube"]
    body = run.model.rigid.bodies[0]
    assert body.mass == pytest.approx(500.0 * 4.0 / 3.0 * 0.05 ** 3, rel=1e-12)  # V = 4/3 r^3
    np.testing.assert_allclose(body.center_of_mass, [0.0, 0.15, 0.0], atol=1e-15)
    assert len(body.local_positions) == 6 and run.model.body_offsets.tolist() == [0, 18, 24]
    text = run.scene.describe()
    assert "body 'cube' ([[body]] #1 'cube'): rigid, vertices 18..23: file" in text
    assert "24 vertices, 66 DOFs in all" in text  # 18 soft vertices and the rigid body's 4 nodes
    assert f"mass {body.mass:.6g} kg" in text and "8 surface triangles" in text
    # the memory estimate counts the rigid body (4 nodes, 6 embedded vertices), in the text and the JSON
    summary = run.scene.summary()
    mem = {b["name"]: b["estimated_device_memory_bytes"]["float64"] for b in summary["bodies"]}
    assert 0 < mem["cube"] < mem["slab"]
    total = summary["estimated_device_memory_bytes"]["float64"]
    assert total == mem["cube"] + mem["slab"] and f"(float64): {total / 1024:.1f} KiB" in text


def _usd_world_points(path, frame):
    """{Xform name: world points at ``frame``} of the rigid bodies of a USD file (the Xform's
    transform applied to its mesh's rest points, as a renderer does)."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    out = {}
    for prim in stage.Traverse():
        if prim.GetTypeName() == "Mesh" and prim.GetParent().GetTypeName() == "Xform" and prim.GetName() == "mesh":
            M = np.array(UsdGeom.Xformable(prim).ComputeLocalToWorldTransform(float(frame)))
            P = np.array(UsdGeom.Mesh(prim).GetPointsAttr().Get(float(frame)), dtype=np.float64)
            out[prim.GetParent().GetName()] = P @ M[:3, :3] + M[3, :3]
    return out


def _run(folder, *args):
    from warpfem.cli import main

    cwd = os.getcwd()
    os.chdir(folder)
    try:
        return main(["run", "s.toml", "--quiet", *args])
    finally:
        os.chdir(cwd)


def test_outputs_of_a_rigid_scene_and_resume(tmp_path):
    import meshio

    from warpfem.io import read_pvd

    text = SHARED + RIGID + SOFT  # rigid listed first
    a, b = tmp_path / "a", tmp_path / "b"
    for f in (a, b):
        f.mkdir()
        write(f, text)
    # the uninterrupted run, in process: its end state against the files
    run = load_scene(str(a / "s.toml")).build(device="cpu")
    cwd = os.getcwd()
    os.chdir(a)
    try:
        run.run(frames=5)
    finally:
        os.chdir(cwd)
    X = run.sim.vertex_positions()
    lo, hi = run.model.body_offsets[1:3]
    p, A = run.model.rigid.pose(run.sim.positions(), 0)
    assert np.abs(A.T @ A - np.eye(3)).max() < 1e-6 and np.abs(A - np.eye(3)).max() > 1e-2  # it turned
    with np.load(a / "out" / "s.npz") as z:
        assert z["body_names"].tolist() == ["slab", "cube"] and z["body_offsets"].tolist() == [0, 18, 26]
        assert z["positions"].shape == (6, 26, 3)
        np.testing.assert_array_equal(z["positions"][-1], X)
        # a rigid body's vertex distances are kept (the states hold p + A X, not the unknown)
        d = lambda x: np.linalg.norm(x[lo:hi, None] - x[None, lo:hi], axis=-1)  # noqa: E731
        assert np.abs(d(z["positions"][-1]) - d(z["positions"][0])).max() < 1e-6
    world = _usd_world_points(a / "out" / "s.usda", 5)
    ids = run.surfaces[1].vertex_ids
    assert set(world) == {"cube"} and np.abs(world["cube"] - X[ids]).max() < 1e-6
    assert np.abs(_usd_world_points(a / "out" / "s.usda", 2)["cube"] - X[ids]).max() > 1e-3  # animated
    entries, meta = read_pvd(a / "out" / "s.pvd")  # one block per body and frame
    assert meta["bodies"] == ["slab", "cube"] and entries[-1][1].endswith(os.path.join("cube.vtu", "frame_000005.vtu"))
    pts = meshio.read(entries[-1][1]).points
    assert np.abs(pts - X[lo:hi]).max() < 1e-12

    # 3 frames, then resumed to 5: the states equal the uninterrupted run's bit for bit
    assert _run(b, "--frames", "3") == 0
    assert _run(b, "--resume", "--frames", "5") == 0
    with np.load(a / "out" / "s.npz") as za, np.load(b / "out" / "s.npz") as zb:
        assert set(za.files) == set(zb.files)
        for key in za.files:
            np.testing.assert_array_equal(za[key], zb[key], err_msg=key)
    np.testing.assert_array_equal(_usd_world_points(b / "out" / "s.usda", 5)["cube"], world["cube"])
    from warpfem.cli import main
    from warpfem.io.usd import usd_validation_errors

    assert usd_validation_errors(str(b / "out" / "s.usda")) == []
    from pxr import Usd

    stage = Usd.Stage.Open(str(b / "out" / "s.usda"))
    prims = {str(p.GetPath()): p.GetTypeName() for p in stage.Traverse()}
    assert prims["/Root/cube"] == "Xform" and prims["/Root/cube/mesh"] == "Mesh"
    assert prims["/Root/slab_volume"] == "TetMesh" and "/Root/cube_volume" not in prims  # usd_volume: soft ones
    assert main(["compare", str(a / "out" / "s.npz"), str(b / "out" / "s.npz"), "--json", str(tmp_path / "c.json")]) == 0
    import json

    report = json.loads((tmp_path / "c.json").read_text())
    assert [(i["name"], i["max"]) for i in report["items"]] == [("positions", 0.0), ("slab", 0.0), ("cube", 0.0)]


EXAMPLES = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "examples", "scenes")


def _energy(run):
    """Kinetic + gravitational + elastic energy (J) of a built scene's current state (the unknown's
    mass matrix holds the rigid bodies' 4x4 blocks)."""
    m, sim = run.model, run.sim
    q, v = sim.positions(), sim.velocities()
    kinetic = 0.5 * sum(float(v[:, c] @ (m.mass @ v[:, c])) for c in range(3))
    gravity = -float(np.sum(m.gravity_mass[:, None] * q * m.gravity[None, :]))
    return kinetic + gravity + float(sim.elastic_energy())


def _intersecting_frames(run, frames):
    ipctk = pytest.importorskip("ipctk")
    F = np.asarray(run.model.mesh.boundary_faces(), dtype=np.int64)
    cm = ipctk.CollisionMesh(np.asarray(run.model.vertex_rest_positions, dtype=np.float64), ipctk.edges(F), F)
    return [k for k, x in enumerate(frames) if ipctk.has_intersections(cm, np.asfortranarray(x))]


def test_rigid_ball_cushion_example_bounces_lower_than_it_fell():
    """The shipped scene with the ball 5 cm above the cushion (a few frames): it lands, is thrown
    back up to below its drop height, the energy never exceeds the start's, no intersection."""
    from warpfem.scenes.schema import parse_scene_dict, read_toml

    doc = read_toml(os.path.join(EXAMPLES, "rigid_ball_cushion.toml"), SceneError, what="scene")
    doc["body"][1]["offset"] = [0.02, 0.231, 0.0]  # 5 cm drop
    doc["integrator"]["dt"] = 1.0 / 60.0
    from warpfem.scenes.scene import Scene

    scene = Scene(parse_scene_dict(doc, path=os.path.join(EXAMPLES, "rigid_ball_cushion.toml")))
    run = scene.build(device="cpu")
    lo, hi = run.model.body_offsets[1:3]
    e0, heights, frames, energies = _energy(run), [], [run.sim.vertex_positions()], []
    for _ in range(8):  # lands at frame 4, highest at frame 7 (0.2015 m: 60 % of the fall back)
        fs = run.step_frame(total_frames=8)
        assert fs.converged
        x = run.sim.vertex_positions()
        frames.append(x)
        heights.append(float(run.model.rigid.pose(run.sim.positions(), 0)[0][1]))
        energies.append(_energy(run))
    low = int(np.argmin(heights))
    assert 0 < low < 6 and heights[low] < 0.231 - 0.05  # landed (the cushion pressed in)
    peak = max(heights[low:])
    assert heights[low] + 0.01 < peak < 0.231, (heights, peak)  # thrown back up, to below the drop height
    # energy: the cushion starts within the floor's contact distance, whose barrier (not counted here)
    # gives back a little at the start; bounded by a tenth of the drop's energy, and the impact dissipates
    drop = run.model.rigid.bodies[0].mass * 9.81 * 0.05
    assert max(energies) <= e0 + 0.1 * drop and energies[-1] < e0 - 0.2 * drop, (e0, drop, energies)
    assert _intersecting_frames(run, frames) == []


def test_rigid_toys_box_example_stays_in_its_box():
    """The shipped scene's first frames: bodies land in the box (inside its walls), rigid blocks stay
    rigid (A^T A = I within 1e-4), the energy never exceeds the start's, no intersection."""
    run = load_scene(os.path.join(EXAMPLES, "rigid_toys_box.toml")).build(device="cpu")
    assert run.model.body_names == ["toy_a", "toy_b", "block_a", "block_b"]
    e0, frames, energies = _energy(run), [run.sim.vertex_positions()], []
    for _ in range(6):
        assert run.step_frame(total_frames=6).converged
        frames.append(run.sim.vertex_positions())
        energies.append(_energy(run))
    x = frames[-1]
    assert x[:, 1].min() > 0.0 and np.abs(x[:, [0, 2]]).max() < 0.2
    assert x[run.model.body_offsets[2]:run.model.body_offsets[3], 1].min() < 0.01  # block_a is on the floor
    for r in range(2):
        A = run.model.rigid.pose(run.sim.positions(), r)[1]
        assert np.abs(A.T @ A - np.eye(3)).max() < 1e-4
    assert max(energies) <= e0 + 1e-6 * abs(e0), (e0, energies)
    assert _intersecting_frames(run, frames) == []
