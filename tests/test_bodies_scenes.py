"""[[body]] scenes (several bodies, each its own mesh, material, selections) and USD in and out: the
npz holds every body in body order with body_offsets, the USD one prim per body (and a TetMesh with
usd_volume), ParaView one block per body; a body's mesh may be a USD TetMesh or closed Mesh."""

import os

import meshio
import numpy as np
import pytest

from warpfem.io import read_pvd, read_usd_mesh_frames
from warpfem.mesh import MeshError, box_tet_mesh, load_mesh
from warpfem.scenes import SceneError, load_scene

BODY_SOFT = """
[[body]]
name = "soft"
[body.mesh]
generator = "box"
size = [0.4, 0.1, 0.1]
cells = [4, 1, 1]
[body.material]
model = "stable_neo_hookean"
youngs_modulus = 1e5
poisson_ratio = 0.3
[[body.fixed]]
box_min = [-1, -1, -1]
box_max = [0.0, 1, 1]
"""

BODY_STIFF = """
[[body]]
name = "stiff"
offset = [0.0, 0.5, 0.0]
[body.mesh]
generator = "box"
size = [0.4, 0.1, 0.1]
cells = [4, 1, 1]
element = "hex8"
[body.material]
model = "corotated"
youngs_modulus = 3e5
poisson_ratio = 0.2
density = 500
[[body.fixed]]
box_min = [-1, 0.4, -1]
box_max = [0.0, 1, 1]
"""

SHARED = """
gravity = [0.0, 0.0, -9.81]
[integrator]
type = "backward_euler"
tol = 1e-9
cg_tol = 1e-10
linear_solver = "pcg"
[output]
fps = 50
frames = 3
usd_volume = true
clip_frames = 0
"""


def _write(tmp_path, name, text):
    p = tmp_path / name
    p.write_text(text)
    return p


def _as_single(body_text):
    """A [[body]] table as the single-body scene of today's form ([mesh], [material], [[fixed]])."""
    return (body_text.replace("[[body]]\n", "").replace("[body.", "[").replace("[[body.", "[[")
            .replace('name = "soft"\n', "").replace('name = "stiff"\n', ""))


def test_two_body_scene_outputs_and_each_body_as_alone(tmp_path):
    scene = load_scene(_write(tmp_path, "two.toml", SHARED + BODY_SOFT + BODY_STIFF))
    text = scene.describe()
    assert "body 'soft'" in text and "body 'stiff'" in text and "vertices 20..39" in text and "hex8" in text
    summary = scene.summary()
    assert [b["name"] for b in summary["bodies"]] == ["soft", "stiff"] and summary["body_offsets"] == [0, 20, 40]
    run = scene.build()
    out = {k: str(tmp_path / f"two.{k}") for k in ("usda", "npz")}
    run.run(usd=out["usda"], states=out["npz"], vtu=str(tmp_path / "two.pvd"))
    d = np.load(out["npz"])
    assert d["body_offsets"].tolist() == [0, 20, 40] and d["body_names"].tolist() == ["soft", "stiff"]
    assert d["positions"].shape == (4, 40, 3)
    np.testing.assert_allclose(d["rest"][20:, 1].min(), 0.5)  # the offset
    # each body alone, as today's single-body scene: the same trajectory
    for text, lo, hi in ((BODY_SOFT, 0, 20), (BODY_STIFF, 20, 40)):
        single = _as_single(text)
        if "offset" in single:  # today's form has no offset: move the box instead
            single = single.replace("offset = [0.0, 0.5, 0.0]\n", "").replace('generator = "box"',
                                                                             'generator = "box"\norigin = [0.0, 0.5, 0.0]')
        s = load_scene(_write(tmp_path, "one.toml", SHARED + single))
        npz = str(tmp_path / "one.npz")
        s.build().run(states=npz, usd=str(tmp_path / "one.usda"))
        alone = np.load(npz)["positions"]
        from pxr import Usd, UsdGeom

        stage = Usd.Stage.Open(str(tmp_path / "one.usda"))  # usd_volume of a one-body scene: prim "volume"
        volume = UsdGeom.TetMesh(stage.GetPrimAtPath("/Root/volume"))
        np.testing.assert_allclose(np.array(volume.GetPointsAttr().Get(3)), alone[3], atol=1e-6)
        assert "body_offsets" not in np.load(npz)  # today's single-body npz unchanged
        assert np.abs(alone[-1] - alone[0]).max() > 1e-3  # it sags
        assert np.abs(d["positions"][:, lo:hi] - alone).max() < 1e-9
    # USD: one Mesh prim per body (its boundary) and a TetMesh beside it, both animated as the states
    from pxr import Usd, UsdGeom

    bm = [b.mesh() for b in scene.bodies]
    for name, m, lo in (("soft", bm[0], 0), ("stiff", bm[1], 20)):
        times, frames = read_usd_mesh_frames(out["usda"], name)
        assert times.tolist() == [0.0, 1.0, 2.0, 3.0]
        ids = np.unique(m.boundary_faces())
        np.testing.assert_allclose(frames[-1], d["positions"][-1, lo + ids], atol=1e-6)
        stage = Usd.Stage.Open(out["usda"])
        tet = UsdGeom.TetMesh(stage.GetPrimAtPath(f"/Root/{name}_volume"))
        assert tet and len(tet.GetTetVertexIndicesAttr().Get()) == len(m.corner_tets())
        for k in (0, 3):
            np.testing.assert_allclose(np.array(tet.GetPointsAttr().Get(k)), d["positions"][k, lo:lo + m.num_vertices],
                                       atol=1e-6)
    # USD's own outward faces of the Tet4 body's TetMesh are its boundary triangles
    stage = Usd.Stage.Open(out["usda"])
    tet = UsdGeom.TetMesh(stage.GetPrimAtPath("/Root/soft_volume"))
    faces = np.array(UsdGeom.TetMesh.ComputeSurfaceFaces(tet, Usd.TimeCode(0)))
    assert {tuple(np.roll(f, -int(np.argmin(f)))) for f in faces} == {tuple(np.roll(f, -int(np.argmin(f))))
                                                                    for f in bm[0].boundary_faces()}
    # ParaView: per frame one block per body, by name, with its own cell type and points
    entries, meta = read_pvd(tmp_path / "two.pvd")
    assert meta["bodies"] == ["soft", "stiff"] and meta["complete"] and len(entries) == 8
    text = (tmp_path / "two.pvd").read_text()
    assert 'part="1" name="stiff"' in text
    last = meshio.read(entries[-1][1])  # frame 3 of "stiff"
    assert last.cells[0].type == "hexahedron"
    np.testing.assert_allclose(last.points, d["positions"][-1, 20:], atol=1e-12)
    assert meshio.read(entries[0][1]).cells[0].type == "tetra"


def test_offset_and_initial_velocity_in_a_scene(tmp_path):
    text = (SHARED.replace("[0.0, 0.0, -9.81]", "[0.0, 0.0, 0.0]").replace("usd_volume = true", "")
            + BODY_SOFT.replace('name = "soft"', 'name = "soft"\ninitial_velocity = [0.5, 0.0, -1.0]').replace(
                "[[body.fixed]]\nbox_min = [-1, -1, -1]\nbox_max = [0.0, 1, 1]\n", "")
            + BODY_STIFF.replace("offset = [0.0, 0.5, 0.0]", "offset = [2.0, 0.5, 0.0]\ninitial_velocity = [0, 0, 2]")
            .replace("[[body.fixed]]\nbox_min = [-1, 0.4, -1]\nbox_max = [0.0, 1, 1]\n", ""))
    run = load_scene(_write(tmp_path, "fly.toml", text)).build()
    npz = str(tmp_path / "fly.npz")
    run.run(states=npz)
    d = np.load(npz)
    t = d["times"][-1]
    assert t == pytest.approx(0.06)
    box = box_tet_mesh(size=(0.4, 0.1, 0.1), cells=(4, 1, 1))
    np.testing.assert_allclose(d["rest"][20:].min(axis=0), [2.0, 0.5, 0.0])  # the offset moved the hex box
    np.testing.assert_allclose(d["rest"][:20], box.vertices)
    # free flight: every vertex moves by v t (to round-off), each body with its own velocity
    np.testing.assert_allclose(d["positions"][-1, :20], d["rest"][:20] + t * np.array([0.5, 0.0, -1.0]), atol=1e-12)
    np.testing.assert_allclose(d["positions"][-1, 20:], d["rest"][20:] + t * np.array([0.0, 0.0, 2.0]), atol=1e-12)


def test_body_scene_errors_name_the_body_and_key(tmp_path):
    def fails(text, *match):
        with pytest.raises(SceneError) as e:
            load_scene(_write(tmp_path, "bad.toml", text))
        for m in match:
            assert m in str(e.value), str(e.value)

    fails(SHARED + BODY_SOFT + "[mesh]\ngenerator = \"box\"\nsize = [1, 1, 1]\ncells = [1, 1, 1]\n",
          "bad.toml", "[[body]]", "top-level [mesh]")
    fails(SHARED + BODY_SOFT + BODY_STIFF.replace('name = "stiff"', 'name = "stiff"\nofset = [0, 0, 0]'),
          "[[body]] #2 'stiff'.ofset", "did you mean 'offset'")
    fails(SHARED + BODY_SOFT + BODY_STIFF.replace('element = "hex8"', 'elemnt = "hex8"'),
          "[[body]] #2 'stiff': [mesh].elemnt", "did you mean 'element'")
    fails(SHARED + BODY_SOFT + BODY_STIFF.replace('name = "stiff"', 'name = "soft"'),
          "[[body]] #2 'soft'.name", "already the name of [[body]] #1")
    fails(SHARED + BODY_SOFT + BODY_STIFF.replace("box_min = [-1, 0.4, -1]", "box_min = [-1, 0.4]"),
          "[[body]] #2 'stiff': [[fixed]] #1.box_min")
    fails(SHARED + BODY_SOFT.replace('name = "soft"', 'name = "2soft"'), "valid USD prim name")
    fails((SHARED + BODY_SOFT + BODY_STIFF).replace('type = "backward_euler"', 'type = "stiffness_warping"')
          .replace('element = "hex8"', "").replace("tol = 1e-9\n", "").replace('linear_solver = "pcg"\n', ""),
          "'stiffness_warping' simulates one body")
    fails(SHARED + BODY_SOFT + "[subspace]\nmodes = 4\n", "[subspace]: reduced runs take a one-body scene")
    fails("body = 3\n" + SHARED, "write the bodies as an array of tables [[body]]")
    fails(SHARED + BODY_SOFT + BODY_STIFF.replace("[body.material]", "[body.materal]"), "[[body]] #2 'stiff'.materal",
          "did you mean 'material'")
    # overlapping bodies at t = 0: the build refuses naming both and the first crossing
    scene = load_scene(_write(tmp_path, "overlap.toml", SHARED + BODY_SOFT + BODY_STIFF.replace(
        "offset = [0.0, 0.5, 0.0]", "offset = [0.13, 0.04, 0.03]").replace("box_min = [-1, 0.4, -1]\nbox_max = [0.0, 1, 1]",
                                                                  "box_min = [-1, -1, -1]\nbox_max = [0.14, 1, 1]")))
    with pytest.raises(SceneError, match=r"overlap.toml: \[\[body\]\]: bodies 'soft' and 'stiff' overlap at t = 0: "
                                         r"edge \[\d+, \d+\] of '(soft|stiff)' \(.*\) - \(.*\) crosses triangle"):
        scene.build()


def _usd_tetmesh(path, mesh, *, prim="/World/Beam", translate=None, extra_mesh=False):
    from pxr import Gf, Usd, UsdGeom, Vt

    stage = Usd.Stage.CreateNew(str(path))
    world = UsdGeom.Xform.Define(stage, "/World")
    if translate is not None:
        world.AddTranslateOp().Set(Gf.Vec3d(*translate))
    t = UsdGeom.TetMesh.Define(stage, prim)
    t.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(mesh.vertices.astype(np.float32)))
    t.GetTetVertexIndicesAttr().Set(Vt.Vec4iArray.FromNumpy(np.asarray(mesh.elements, dtype=np.int32)))
    if extra_mesh:
        m = UsdGeom.Mesh.Define(stage, "/World/Other")
        f = np.asarray(mesh.boundary_faces(), dtype=np.int32)
        m.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(mesh.vertices.astype(np.float32)))
        m.GetFaceVertexCountsAttr().Set(Vt.IntArray.FromNumpy(np.full(len(f), 3, dtype=np.int32)))
        m.GetFaceVertexIndicesAttr().Set(Vt.IntArray.FromNumpy(f.ravel()))
    UsdGeom.Xform.Define(stage, "/World/Empty")
    stage.GetRootLayer().Save()
    return str(path)


def _usd_surface(path, vertices, faces, prim="/Box"):
    from pxr import Usd, UsdGeom, Vt

    stage = Usd.Stage.CreateNew(str(path))
    m = UsdGeom.Mesh.Define(stage, prim)
    m.GetPointsAttr().Set(Vt.Vec3fArray.FromNumpy(np.asarray(vertices, dtype=np.float32)))
    f = np.asarray(faces, dtype=np.int32)
    m.GetFaceVertexCountsAttr().Set(Vt.IntArray.FromNumpy(np.full(len(f), f.shape[1], dtype=np.int32)))
    m.GetFaceVertexIndicesAttr().Set(Vt.IntArray.FromNumpy(f.ravel()))
    stage.GetRootLayer().Save()
    return str(path)


def test_usd_tetmesh_and_closed_mesh_input(tmp_path):
    box = box_tet_mesh(size=(0.4, 0.1, 0.1), cells=(4, 1, 1))
    path = _usd_tetmesh(tmp_path / "beam.usda", box, translate=(1.0, 2.0, 3.0))
    m = load_mesh(path)  # the only TetMesh / Mesh prim; the Xform's translation applied
    np.testing.assert_allclose(m.vertices, box.vertices + (1.0, 2.0, 3.0), atol=1e-6)
    np.testing.assert_array_equal(m.elements, box.elements)
    # in a scene, with its prim named, as one of two bodies
    scene_text = (SHARED.replace("usd_volume = true", "") + BODY_SOFT
                  + f'[[body]]\nname = "usd_beam"\n[body.mesh]\npath = "{os.path.basename(path)}"\nprim = "/World/Beam"\n'
                  + "[body.material]\nmodel = \"linear\"\nyoungs_modulus = 1e5\npoisson_ratio = 0.3\n")
    scene = load_scene(_write(tmp_path, "usd_in.toml", scene_text))
    assert scene.mesh().num_vertices == 40 and "file " + path in scene.describe()
    # Tet10 elements from a USD TetMesh: mid-edge nodes added (as for tet files)
    tet10 = load_scene(_write(tmp_path, "usd10.toml", scene_text.replace('prim = "/World/Beam"',
                                                                          'prim = "/World/Beam"\nelement = "tet10"')))
    bm = tet10.bodies[1].mesh()
    assert bm.element_type == "tet10" and bm.total_volume() == pytest.approx(0.004, rel=1e-6)
    # a closed Mesh prim is tetrahedralised (TetGen): the box's volume exactly
    faces = box.boundary_faces()
    surf = _usd_surface(tmp_path / "box.usda", box.vertices, faces)
    tm = load_mesh(surf)
    assert tm.total_volume() == pytest.approx(0.004, rel=1e-6)
    # quads are fanned into triangles
    quad_box = _usd_surface(tmp_path / "quads.usda", [[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1],
                                                      [1, 1, 1], [0, 1, 1]],
                            [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]])
    assert load_mesh(quad_box).total_volume() == pytest.approx(1.0, rel=1e-9)


def test_usd_input_errors_name_file_and_prim(tmp_path):
    box = box_tet_mesh(size=(0.4, 0.1, 0.1), cells=(2, 1, 1))
    two = _usd_tetmesh(tmp_path / "two.usda", box, extra_mesh=True)
    with pytest.raises(MeshError, match=r"two.usda: 2 mesh prims \(/World/Beam \(TetMesh\), /World/Other \(Mesh\)\)"):
        load_mesh(two)
    with pytest.raises(MeshError, match=r"two.usda: no prim '/World/Nope'; TetMesh / Mesh prims in the file: /World/Beam"):
        load_mesh(two, prim="/World/Nope")
    with pytest.raises(MeshError, match=r"prim '/World/Empty' is a Xform, not a UsdGeom.TetMesh"):
        load_mesh(two, prim="/World/Empty")
    assert load_mesh(two, prim="/World/Beam").num_elements == box.num_elements
    # an open surface: one triangle missing
    faces = box.boundary_faces()
    opened = _usd_surface(tmp_path / "open.usda", box.vertices, faces[1:])
    with pytest.raises(MeshError, match=r"open.usda:/Box: the surface is open: 3 boundary edges"):
        load_mesh(opened, mesher="tetgen")  # (mesher "auto", as for other surface files: TetWild, with a warning)
    empty = _usd_surface(tmp_path / "empty.usda", np.zeros((0, 3)), np.zeros((0, 3)))
    with pytest.raises(MeshError, match=r"empty.usda: prim '/Box': has no points"):
        load_mesh(empty)
    # scenes: prim only with USD files; USD files hold tets
    base = SHARED.replace("usd_volume = true", "") + "[material]\nmodel = \"linear\"\nyoungs_modulus = 1\npoisson_ratio = 0.3\n"
    with pytest.raises(SceneError, match=r"\[mesh\].prim: only applies to USD files"):
        load_scene(_write(tmp_path, "p.toml", base + '[mesh]\ngenerator = "box"\nsize = [1, 1, 1]\ncells = [1, 1, 1]\n'
                          'prim = "/A"\n'))
    with pytest.raises(SceneError, match=r"\[mesh\].element: a USD file holds tets"):
        load_scene(_write(tmp_path, "h.toml", base + '[mesh]\npath = "two.usda"\nelement = "hex8"\n'))
    with pytest.raises(SceneError, match=r"\[mesh\]: .*two.usda: 2 mesh prims"):
        load_scene(_write(tmp_path, "m.toml", base + '[mesh]\npath = "two.usda"\n')).mesh()


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_body_render_surface_embedded_and_moved_by_the_offset(tmp_path, precision):
    """A body's [body.surface] file is in the body's own frame (moved by its offset) and embedded in
    its own elements: its USD prim follows the body (here the surface is the box's boundary, so its
    points are the boundary nodes' positions)."""
    from warpfem.mesh import box_hex_mesh

    hexa = box_hex_mesh(size=(0.4, 0.1, 0.1), cells=(4, 1, 1))
    faces = np.asarray(hexa.boundary_faces())
    ids = np.unique(faces)
    remap = np.full(hexa.num_vertices, -1)
    remap[ids] = np.arange(ids.size)
    meshio.write(str(tmp_path / "skin.obj"), meshio.Mesh(hexa.vertices[ids], [("triangle", remap[faces])]))
    text = (SHARED.replace("usd_volume = true", "") + BODY_SOFT
            + BODY_STIFF.replace("[[body.fixed]]", '[body.surface]\npath = "skin.obj"\n[[body.fixed]]'))
    run = load_scene(_write(tmp_path, "skin.toml", text)).build(precision=precision)
    usd, npz = str(tmp_path / "skin.usda"), str(tmp_path / "skin.npz")
    run.run(usd=usd, states=npz)
    d = np.load(npz)
    times, frames = read_usd_mesh_frames(usd, "stiff")
    assert len(frames) == 4
    np.testing.assert_allclose(frames[0], hexa.vertices[ids] + (0.0, 0.5, 0.0), atol=1e-6)
    np.testing.assert_allclose(frames[-1], d["positions"][-1, 20 + ids], atol=2e-6 if precision == "float32" else 1e-9)
    assert np.abs(frames[-1] - frames[0]).max() > 1e-3


def test_a_one_body_scene_is_the_one_body_case_of_a_body_scene(tmp_path):
    """A scene of the top-level form is its own one body: built and run on the same path as one
    [[body]] table, the same model and trajectory bit for bit; only the output names differ by form
    (prims "boundary" / "volume", no body_offsets in the states file, against the body's name)."""
    table = load_scene(_write(tmp_path, "table.toml", SHARED + BODY_SOFT))
    single = load_scene(_write(tmp_path, "single.toml", SHARED + _as_single(BODY_SOFT)))
    assert single.bodies == [single] and len(table.bodies) == 1 and table.bodies[0] is not table
    runs = {}
    for name, scene in (("table", table), ("single", single)):
        run = scene.build()
        assert run.model.num_bodies == 1 and run.model.mesh is scene.mesh() and run.model.quadrature is not None
        run.run(frames=2, states=str(tmp_path / f"{name}.npz"), checkpoint_every=0)
        runs[name] = (run, np.load(tmp_path / f"{name}.npz"))
    (rt, dt), (rs, ds) = runs["table"], runs["single"]
    assert np.array_equal(dt["positions"], ds["positions"]) and dt["positions"].shape == (3, 20, 3)
    assert set(dt.files) - set(ds.files) == {"body_offsets", "body_names"} and dt["body_names"].tolist() == ["soft"]
    assert [s[0] for s in rt.usd_surfaces()] == ["soft"] and [s[0] for s in rs.usd_surfaces()] == ["boundary"]
    assert [v[0] for v in rt.usd_volumes()] == ["soft_volume"] and [v[0] for v in rs.usd_volumes()] == ["volume"]
    assert np.array_equal(rt.surface_faces, rs.surface_faces) and np.array_equal(rt.surface_vertex_ids, rs.surface_vertex_ids)
