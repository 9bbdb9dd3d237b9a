"""Tangled meshes (elements overlapping their neighbours) are refused with the elements, the vertex and
where; meshes (or connected parts) whose elements are all flipped are still reoriented."""

import re
import textwrap
import types
import warnings

import numpy as np
import pytest

import warpfem as wf
from warpfem.mesh import MeshError, VolumeMesh, box_hex_mesh, box_tet_mesh, tet10_from_tet4
from warpfem.mesh.element_types.tet4 import tet_volumes

# vertex (2, 2, 2) of a 4x4x4-cell unit box: interior, at (0.5, 0.5, 0.5); moved by PUSH it passes
# through faces of its star and 6 of its 24 tets invert (a generic direction: not along an edge)
VERTEX = 2 + 5 * (2 + 5 * 2)
PUSH = np.array([0.3, -0.2, 0.1])


def tangled_box():
    m = box_tet_mesh(cells=(4, 4, 4))
    x = np.array(m.vertices)
    t = np.array(m.tets)
    x[VERTEX] += PUSH
    inverted = np.flatnonzero(tet_volumes(x, t) < 0)
    assert inverted.size == 6 and (t[inverted] == VERTEX).any(axis=1).all()  # all in the vertex's star
    return x, t, inverted


def named_elements(msg):
    ids = re.search(r"overlap their neighbours \(.*?\): [\w ]+?s ([\d, ]+), around vertex", msg)
    assert ids, msg
    return [int(i) for i in ids.group(1).split(",")]


def test_pushed_vertex_is_refused_naming_tets_vertex_and_position():
    x, t, inverted = tangled_box()
    with pytest.raises(MeshError) as e:
        VolumeMesh(x, t)
    msg = str(e.value)
    assert msg.startswith("tangled mesh: 6 tets overlap their neighbours"), msg
    assert named_elements(msg) == inverted.tolist()
    assert f"around vertex {VERTEX} at (0.8, 0.3, 0.6)" in msg
    # reorient=False names the tangle too (not just "negatively oriented")
    with pytest.raises(MeshError, match="tangled mesh"):
        VolumeMesh(x, t, reorient=False)


def test_vertex_index_is_the_input_one_when_unreferenced_vertices_are_removed():
    x, t, inverted = tangled_box()
    x2 = np.concatenate([[[9.0, 9.0, 9.0]], x])  # an unreferenced vertex 0 shifts every index by one
    with pytest.raises(MeshError) as e:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            VolumeMesh(x2, t + 1)
    assert f"around vertex {VERTEX + 1} at" in str(e.value)
    assert named_elements(str(e.value)) == inverted.tolist()


def test_all_flipped_is_reoriented():
    ref = box_tet_mesh(cells=(3, 2, 2))
    t = np.array(ref.tets)[:, [0, 2, 1, 3]]  # every tet written with the other winding
    assert (tet_volumes(ref.vertices, t) < 0).all()
    with pytest.warns(UserWarning, match=rf"reoriented {len(t)} of {len(t)} negatively oriented tets"):
        m = VolumeMesh(ref.vertices, t)
    np.testing.assert_array_equal(m.vertices, ref.vertices)
    assert (m.rest_volumes() > 0).all()
    np.testing.assert_allclose(m.rest_volumes(), ref.rest_volumes(), rtol=1e-14)
    def faces(mesh):
        return sorted(map(tuple, np.sort(mesh.boundary_faces(), axis=1).tolist()))

    assert faces(m) == faces(ref)


def test_tangled_and_all_flipped_is_refused_naming_the_inverted_ones():
    """Written with the other winding *and* a vertex pushed: the tets that overlap are still the 6."""
    x, t, inverted = tangled_box()
    with pytest.raises(MeshError) as e:
        VolumeMesh(x, t[:, [0, 2, 1, 3]])
    assert named_elements(str(e.value)) == inverted.tolist()
    assert f"around vertex {VERTEX}" in str(e.value)


def test_two_components_one_flipped_is_accepted():
    a = box_tet_mesh(cells=(2, 2, 2))
    b = box_tet_mesh(cells=(2, 2, 2), origin=(2.0, 0.0, 0.0))
    x = np.concatenate([a.vertices, b.vertices])
    t = np.concatenate([a.tets, (np.array(b.tets) + a.num_vertices)[:, [1, 0, 2, 3]]])
    with pytest.warns(UserWarning, match=rf"reoriented {b.num_tets} of {len(t)} negatively oriented tets"):
        m = VolumeMesh(x, t)
    np.testing.assert_array_equal(m.reoriented_tets, np.arange(a.num_tets, len(t)))
    assert m.total_volume() == pytest.approx(2.0)


def test_single_tets_written_mirrored_are_still_reoriented():
    """Mixed windings, every tet where it should be: no overlap (each flip flips the face order too)."""
    ref = box_tet_mesh(cells=(2, 2, 2))
    t = np.array(ref.tets)
    t[::3] = t[::3][:, [1, 0, 2, 3]]
    with pytest.warns(UserWarning, match="reoriented"):
        m = VolumeMesh(ref.vertices, t)
    np.testing.assert_allclose(m.rest_volumes(), ref.rest_volumes(), rtol=1e-14)


def test_two_positive_tets_on_the_same_side_of_their_face():
    """Both positively oriented but on the same side of the shared face: they overlap."""
    x = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.2, 0.2, 0.5]], dtype=float)
    t = np.array([[0, 1, 2, 3], [0, 1, 2, 4]])
    assert (tet_volumes(x, t) > 0).all()
    with pytest.raises(MeshError) as e:
        VolumeMesh(x, t)
    assert "1 shared face(s) with both tets on the same side" in str(e.value)
    # the apex 4 of tet 1 lies inside tet 0: named
    assert named_elements(str(e.value)) == [1] and "around vertex 4 at (0.2, 0.2, 0.5)" in str(e.value)
    # the same two on opposite sides: fine
    x[4] = [0.2, 0.2, -0.5]
    VolumeMesh(x, np.array([[0, 1, 2, 3], [0, 2, 1, 4]]))


def test_face_shared_by_three_tets():
    x = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, -1], [0.1, 0.1, 0.5]], dtype=float)
    t = np.array([[0, 1, 2, 3], [0, 2, 1, 4], [0, 1, 2, 5]])
    with pytest.raises(MeshError, match=r"1 face\(s\) shared by more than two tets \(first: tets 0, 1, 2\)"):
        VolumeMesh(x, t)


def test_tet10_tangle():
    x, t, inverted = tangled_box()
    with pytest.raises(MeshError) as e:
        tet10_from_tet4(types.SimpleNamespace(vertices=x, elements=t), name="pushed")
    msg = str(e.value)
    assert msg.startswith("pushed: tangled mesh: 6 tet10 elements overlap their neighbours"), msg
    assert named_elements(msg) == inverted.tolist()
    assert f"around vertex {VERTEX} at" in msg
    # all flipped (the mirror image of each element): reoriented
    ref = tet10_from_tet4(box_tet_mesh(cells=(2, 1, 1)))
    perm = ref.element.mirror_permutation
    with pytest.warns(UserWarning, match=r"reoriented 12 of 12"):
        m = VolumeMesh(ref.vertices, np.array(ref.elements)[:, perm], "tet10")
    np.testing.assert_allclose(m.rest_volumes(), ref.rest_volumes(), rtol=1e-14)


def test_hex8_overlap_and_flipped():
    # hex 1 shares hex 0's top face but lies below it, inside hex 0: both positive
    x = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1],
                  [0, 0, 0.5], [1, 0, 0.5], [1, 1, 0.5], [0, 1, 0.5]], dtype=float)
    h = np.array([[0, 1, 2, 3, 4, 5, 6, 7], [8, 9, 10, 11, 4, 5, 6, 7]])
    with pytest.raises(MeshError) as e:
        VolumeMesh(x, h, "hex8")
    assert "1 shared face(s) with both hex8 elements on the same side" in str(e.value)
    # a grid of hexes all written mirrored: reoriented
    ref = box_hex_mesh(cells=(2, 2, 1))
    perm = ref.element.mirror_permutation
    with pytest.warns(UserWarning, match=r"reoriented 4 of 4"):
        m = VolumeMesh(ref.vertices, np.array(ref.elements)[:, perm], "hex8")
    np.testing.assert_allclose(m.rest_volumes(), ref.rest_volumes(), rtol=1e-14)
    # ... and one of them mirrored only (mixed windings, no overlap)
    el = np.array(ref.elements)
    el[1] = el[1][perm]
    with pytest.warns(UserWarning, match=r"reoriented 1 of 4"):
        VolumeMesh(ref.vertices, el, "hex8")


def test_hex27_all_flipped_is_reoriented():
    ref = box_hex_mesh(cells=(2, 1, 1), order=2)
    perm = ref.element.mirror_permutation
    with pytest.warns(UserWarning, match=r"reoriented 2 of 2"):
        m = VolumeMesh(ref.vertices, np.array(ref.elements)[:, perm], "hex27")
    np.testing.assert_allclose(m.rest_volumes(), ref.rest_volumes(), rtol=1e-14)


@pytest.mark.parametrize("suffix", [".mesh", ".msh", ".vtu"])
def test_tangled_file_is_refused_with_its_name(tmp_path, suffix):
    import meshio

    x, t, inverted = tangled_box()
    p = tmp_path / f"tangled{suffix}"
    meshio.write(str(p), meshio.Mesh(x, [("tetra", t)]), **({"file_format": "gmsh22", "binary": False}
                                                           if suffix == ".msh" else {}))
    with pytest.raises(MeshError) as e:
        wf.load_mesh(p)
    msg = str(e.value)
    assert msg.startswith(f"{p}: tangled mesh: 6 tets overlap their neighbours"), msg
    assert named_elements(msg) == inverted.tolist() and f"around vertex {VERTEX}" in msg
    # the same file with every tet flipped and no pushed vertex: loads (reoriented)
    x0 = np.array(box_tet_mesh(cells=(4, 4, 4)).vertices)
    q = tmp_path / f"flipped{suffix}"
    meshio.write(str(q), meshio.Mesh(x0, [("tetra", t[:, [0, 2, 1, 3]])]), **({"file_format": "gmsh22", "binary": False}
                                                                            if suffix == ".msh" else {}))
    with pytest.warns(UserWarning, match=rf"reoriented {len(t)} of {len(t)}"):
        m = wf.load_mesh(q)
    assert m.total_volume() == pytest.approx(1.0)


def test_tangled_scene_mesh_is_refused(tmp_path, capsys):
    import meshio

    from warpfem.scenes import SceneError, load_scene

    x, t, inverted = tangled_box()
    meshio.write(str(tmp_path / "tangled.mesh"), meshio.Mesh(x, [("tetra", t)]))
    scene = tmp_path / "scene.toml"
    scene.write_text(textwrap.dedent("""
        [mesh]
        path = "tangled.mesh"
        [material]
        model = "stable_neo_hookean"
        youngs_modulus = 1e5
        poisson_ratio = 0.3
        density = 1000.0
        [integrator]
        type = "backward_euler"
        dt = 0.05
        [output]
        fps = 20
        frames = 1
        """))
    with pytest.raises(SceneError) as e:
        load_scene(scene).mesh()
    msg = str(e.value)
    assert msg.startswith(f"{scene}: [mesh]: {tmp_path / 'tangled.mesh'}: tangled mesh: 6 tets overlap"), msg
    assert named_elements(msg) == inverted.tolist() and f"around vertex {VERTEX}" in msg
    # the command line: one error line, exit code 2
    from warpfem.cli import main

    assert main(["describe", str(scene)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "tangled mesh: 6 tets overlap" in err, err
