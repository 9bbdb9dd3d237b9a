"""Surface files tetrahedralised on load: volume, sizing, bad surfaces, cache, scenes, missing extra."""

import math
import os
import sys
import textwrap

import numpy as np
import pytest

from warpfem.mesh import MeshError, MesherNotInstalled, check_surface, icosphere_surface, load_mesh, tet_volumes, tetrahedralize
import warpfem.mesh.tetrahedralization as T
from warpfem.mesh import tetrahedralize_file
from warpfem.mesh import boundary_faces

CUBE_V = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0],
                   [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1]], dtype=np.float64)
CUBE_F = np.array([[0, 2, 1], [0, 3, 2], [4, 5, 6], [4, 6, 7], [0, 1, 5], [0, 5, 4],
                   [1, 2, 6], [1, 6, 5], [2, 3, 7], [2, 7, 6], [3, 0, 4], [3, 4, 7]], dtype=np.int64)


@pytest.fixture(autouse=True)
def cache_in_tmp(tmp_path, monkeypatch):
    """Every test gets its own, empty tetrahedralisation cache (never the user's ~/.cache)."""
    monkeypatch.setenv("WARPFEM_CACHE_DIR", str(tmp_path / "cache"))
    return tmp_path / "cache" / "tetra"


@pytest.fixture
def tetgen():
    return pytest.importorskip("tetgen", reason="the mesh extra (pip install warpfem[mesh]) is not installed")


def icosphere(level=2):
    return icosphere_surface(1.0, level)


def enclosed_volume(V, F):
    """Divergence theorem: V = 1/6 sum over faces of x_a . (x_b x x_c) (outward faces)."""
    a, b, c = V[F[:, 0]], V[F[:, 1]], V[F[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def write_off(path, V, F):
    lines = ["OFF", f"{len(V)} {len(F)} 0"] + [" ".join(repr(float(c)) for c in v) for v in V]
    lines += [f"3 {a} {b} {c}" for a, b, c in F]
    path.write_text("\n".join(lines) + "\n")
    return path


def write_obj(path, V, F):
    lines = [f"v {float(x)!r} {float(y)!r} {float(z)!r}" for x, y, z in V] + [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in F]
    path.write_text("\n".join(lines) + "\n")
    return path


# ----------------------------------------------------------------------------- geometry
def test_sphere_volume_and_positive_tets(tetgen):
    V, F = icosphere(2)  # 162 vertices, 320 faces
    ref = enclosed_volume(V, F)
    assert 0.95 * 4 / 3 * math.pi < ref < 4 / 3 * math.pi  # an inscribed polyhedron
    mesh = tetrahedralize(V, F)
    vol = tet_volumes(mesh.vertices, mesh.tets)
    assert vol.min() > 0
    assert abs(vol.sum() - ref) < 1e-9 * ref  # TetGen keeps the surface: same volume to rounding
    # the boundary of the tets is the input surface (maybe with Steiner points on it): same area
    bf = boundary_faces(mesh)
    x = mesh.vertices
    area = 0.5 * np.linalg.norm(np.cross(x[bf[:, 1]] - x[bf[:, 0]], x[bf[:, 2]] - x[bf[:, 0]]), axis=1).sum()
    ref_area = 0.5 * np.linalg.norm(np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]]), axis=1).sum()
    assert abs(area - ref_area) < 1e-9 * ref_area
    info = mesh.tetrahedralization
    assert info.mesher == "tetgen" and info.num_tets == mesh.num_elements and info.surface_faces == 320


def test_cube_max_edge_length_sets_the_size(tetgen):
    counts = {}
    for L in (0.5, 0.25):
        mesh = tetrahedralize(CUBE_V, CUBE_F, max_edge_length=L)
        vol = tet_volumes(mesh.vertices, mesh.tets)
        assert vol.min() > 0 and abs(vol.sum() - 1.0) < 1e-12
        x = mesh.vertices[mesh.tets]
        edges = np.concatenate([np.linalg.norm(x[:, j] - x[:, i], axis=1)
                                for i, j in ((0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3))])
        assert 0.7 * L < edges.mean() < 1.05 * L, (L, edges.mean())
        counts[L] = mesh.num_elements
    assert 5.0 < counts[0.25] / counts[0.5] < 11.0  # tets ~ L^-3 (8x per halving)
    # without max_edge_length the surface sets the size: the 8 corners, 6 tets at most a few more
    assert tetrahedralize(CUBE_V, CUBE_F).num_elements < 20
    # a max_edge_length that would make ~10^10 tets is refused before meshing
    with pytest.raises(MeshError, match="would give about .* tets"):
        tetrahedralize(CUBE_V, CUBE_F, max_edge_length=1e-3)


# ----------------------------------------------------------------------------- bad surfaces
def _two_cubes_sharing_an_edge():
    V = np.vstack([CUBE_V, CUBE_V + [1.0, 1.0, 0.0]])
    F = np.vstack([CUBE_F, CUBE_F + 8])
    Vu, inv = np.unique(V, axis=0, return_inverse=True)
    return Vu, inv.ravel()[F]


def _bad_surfaces():
    nan = CUBE_V.copy()
    nan[5, 1] = np.nan
    oob = CUBE_F.copy()
    oob[7, 2] = 8
    rep = CUBE_F.copy()
    rep[3] = [4, 6, 4]
    collinear_v = np.vstack([CUBE_V, [[0.5, 0.0, 0.0]]])  # a vertex on the edge (0, 1)
    # split face (0, 1, 5) at vertex 8: (0, 8, 5) + (8, 1, 5), and face (0, 2, 1) as (0, 2, 8) + (8, 2, 1),
    # plus a zero-area sliver (0, 8, 1) and its twin (0, 1, 8) closing the surface
    zero = np.vstack([[[0, 2, 8], [8, 2, 1]], CUBE_F[1:4], [[0, 8, 5], [8, 1, 5]], CUBE_F[5:]])
    zero = np.vstack([zero, [[0, 8, 1]], [[0, 1, 8]]])
    return {
        "open": (CUBE_V, CUBE_F[2:], ["open", "4 boundary edges", "edge (0, 1)"]),
        "non-manifold": (*_two_cubes_sharing_an_edge(), ["1 non-manifold edges", "edge (6, 7)", "more than two faces"]),
        "duplicated face": (CUBE_V, np.vstack([CUBE_F, CUBE_F[4:5]]), ["face 12", "duplicates face 4"]),
        "repeated vertex": (CUBE_V, rep, ["degenerate face 3", "repeats a vertex"]),
        "zero area": (collinear_v, zero, ["degenerate face", "zero area", "[0, 8, 1]"]),
        "self-intersecting": (np.vstack([CUBE_V, CUBE_V + [0.5, 0.3, 0.2]]), np.vstack([CUBE_F, CUBE_F + 8]),
                              ["intersects itself", "crossing face pairs"]),
        "nan": (nan, CUBE_F, ["vertex 5", "NaN"]),
        "index out of range": (CUBE_V, oob, ["face 7", "out of range [0, 8)"]),
        "too few vertices": (CUBE_V[:3], np.array([[0, 1, 2], [0, 2, 1]]), ["at least 4 vertices, got 3"]),
    }


@pytest.mark.parametrize("case", list(_bad_surfaces()))
def test_bad_surface_is_rejected_before_the_mesher(case, monkeypatch):
    V, F, words = _bad_surfaces()[case]

    def boom(*a, **k):
        raise AssertionError("the mesher must not run on a bad surface")

    monkeypatch.setattr(T, "_run_tetgen", boom)
    monkeypatch.setattr(T, "_run_tetwild", boom)
    with pytest.raises(MeshError) as e:
        tetrahedralize(V, F, mesher="tetgen", name="thing.obj")
    msg = str(e.value)
    assert msg.startswith("thing.obj: "), msg
    for w in words:
        assert w in msg, msg


def test_self_intersection_check_has_no_false_positive_on_shipped_surfaces(meshes_dir):
    for name in ("bunny.off", "decimated-knight.off"):
        V, F = T.read_surface(meshes_dir / name)
        check_surface(V, F)  # raises on any reported crossing
    # nested and disjoint closed cubes are valid (no crossing); interpenetrating ones are not
    check_surface(np.vstack([CUBE_V, 0.5 * CUBE_V + 0.25]), np.vstack([CUBE_F, CUBE_F + 8]))
    check_surface(np.vstack([CUBE_V, CUBE_V + [2.0, 0, 0]]), np.vstack([CUBE_F, CUBE_F + 8]))
    pairs = T._self_intersections(np.vstack([CUBE_V, CUBE_V + 0.5]), np.vstack([CUBE_F, CUBE_F + 8]), 3.0)
    assert len(pairs) > 0  # symmetric overlap: edges cross faces on their diagonals


def test_bad_file_names_the_file(tmp_path):
    V = CUBE_V.copy()
    V[2] = [np.nan, 0.0, 0.0]
    p = write_obj(tmp_path / "nan.obj", V, CUBE_F)
    with pytest.raises(MeshError, match=r"nan\.obj: vertex 2 has non-finite"):
        load_mesh(p)


def test_mesher_error_is_reraised_as_mesh_error(tetgen, tmp_path, monkeypatch):
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    V, F = np.vstack([CUBE_V, CUBE_V + 0.5]), np.vstack([CUBE_F, CUBE_F + 8])
    with pytest.raises(MeshError, match="TetGen failed: .*self-intersections.*mesher = 'tetwild'"):
        tetrahedralize(V, F, mesher="tetgen", check=False)
    assert os.getcwd() == str(work) and os.listdir(work) == []  # TetGen's _skipped.node/.face went elsewhere


# ----------------------------------------------------------------------------- cache
def test_second_load_is_a_cache_hit_and_options_miss(tetgen, meshes_dir, tmp_path, monkeypatch, cache_in_tmp):
    src = tmp_path / "knight.off"
    src.write_bytes((meshes_dir / "decimated-knight.off").read_bytes())
    first = load_mesh(src)
    assert not first.tetrahedralization.cache_hit
    files = sorted(os.listdir(cache_in_tmp))
    assert len(files) == 1 and files[0].startswith("knight-") and files[0].endswith(".npz")  # no temp file left

    def boom(*a, **k):
        raise AssertionError("re-meshed instead of reading the cache")

    monkeypatch.setattr(T, "_run_tetgen", boom)
    second = load_mesh(src)
    assert second.tetrahedralization.cache_hit and second.tetrahedralization.mesher == "tetgen"
    np.testing.assert_array_equal(second.vertices, first.vertices)
    np.testing.assert_array_equal(second.tets, first.tets)
    # a changed option or changed file bytes is a miss (reaches the mesher, which raises here)
    with pytest.raises(AssertionError, match="re-meshed"):
        load_mesh(src, max_radius_edge_ratio=1.5)
    with pytest.raises(AssertionError, match="re-meshed"):
        load_mesh(src, max_edge_length=0.05)
    src.write_bytes(src.read_bytes() + b"\n# edited\n")
    with pytest.raises(AssertionError, match="re-meshed"):
        load_mesh(src)
    with pytest.raises(AssertionError, match="re-meshed"):  # cache=False never reads it
        tetrahedralize_file(meshes_dir / "decimated-knight.off", cache=False)


def test_corrupt_cache_entry_is_remeshed(tetgen, tmp_path, cache_in_tmp, caplog):
    p = write_off(tmp_path / "cube.off", CUBE_V, CUBE_F)
    a = load_mesh(p)
    (entry,) = cache_in_tmp.iterdir()
    entry.write_bytes(b"not an npz")
    with caplog.at_level("WARNING"):
        b = load_mesh(p)
    assert not b.tetrahedralization.cache_hit and "ignoring unreadable" in caplog.text
    np.testing.assert_array_equal(a.tets, b.tets)
    assert load_mesh(p).tetrahedralization.cache_hit  # rewritten


# ----------------------------------------------------------------------------- missing extra
def test_missing_mesher_names_the_extra(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "tetgen", None)  # import tetgen -> ImportError
    monkeypatch.setitem(sys.modules, "wildmeshing", None)
    with pytest.raises(MesherNotInstalled) as e:
        tetrahedralize(CUBE_V, CUBE_F, mesher="tetgen")
    assert "pip install 'warpfem[mesh]'" in str(e.value) and isinstance(e.value, ImportError)
    with pytest.raises(MesherNotInstalled, match=r"warpfem\[tetwild\]"):
        tetrahedralize(CUBE_V, CUBE_F, mesher="tetwild")
    with pytest.raises(MesherNotInstalled, match=r"warpfem\[mesh\]"):  # auto with neither installed: TetGen's extra
        tetrahedralize(CUBE_V, CUBE_F)
    # through a scene: a SceneError naming [mesh] and the extra
    from warpfem.scenes import SceneError, load_scene

    write_off(tmp_path / "cube.off", CUBE_V, CUBE_F)
    scene = load_scene(_scene(tmp_path, 'path = "cube.off"'))
    with pytest.raises(SceneError, match=r"\[mesh\]: .*pip install 'warpfem\[mesh\]'"):
        scene.describe()


# ----------------------------------------------------------------------------- scenes
def _scene(tmp_path, mesh, *, fixed_y=0.1, extra=""):
    text = f"""
    gravity = [0.0, -9.81, 0.0]
    [mesh]
    {mesh}
    [material]
    model = "stable_neo_hookean"
    youngs_modulus = 2e4
    poisson_ratio = 0.3
    density = 800.0
    [[fixed]]
    box_min = [-10.0, -10.0, -10.0]
    box_max = [10.0, {fixed_y}, 10.0]
    [integrator]
    type = "backward_euler"
    dt = 0.05
    [output]
    fps = 20
    frames = 2
    {extra}
    """
    p = tmp_path / "scene.toml"
    p.write_text(textwrap.dedent(text))
    return p


def test_knight_scene_tetrahedralises_describes_and_steps(tetgen, meshes_dir, tmp_path):
    from warpfem.scenes import load_scene

    knight = (meshes_dir / "decimated-knight.off").as_posix()
    scene = load_scene(_scene(tmp_path, f'path = "{knight}"'))
    text = scene.describe()
    mesh = scene.mesh()
    assert f"by tetgen (tetgen " in text and f": {mesh.num_elements} tets" in text and "tetrahedralised" in text
    V, F = T.read_surface(knight)
    volume = enclosed_volume(V, F)
    run = scene.build(device="cpu")
    assert run.model.total_mass == pytest.approx(800.0 * volume, rel=1e-4)  # TetGen keeps the surface
    x0 = run.sim.positions().copy()
    fixed = np.flatnonzero(mesh.vertices[:, 1] <= 0.1)
    for _ in range(2):
        run.step_frame()
    x = run.sim.positions()
    assert np.isfinite(x).all()
    np.testing.assert_allclose(x[fixed], x0[fixed], atol=1e-12)
    assert x[:, 1].mean() < x0[:, 1].mean() - 1e-6  # sags under gravity
    assert "cache hit" in load_scene(_scene(tmp_path, f'path = "{knight}"')).describe()


def test_scene_keys_are_validated(tmp_path):
    from warpfem.scenes import SceneError, load_scene

    write_off(tmp_path / "cube.off", CUBE_V, CUBE_F)

    def rejects(mesh, *words):
        with pytest.raises(SceneError) as e:
            load_scene(_scene(tmp_path, mesh))
        for w in words:
            assert w in str(e.value), str(e.value)

    rejects('path = "cube.off"\nmax_edge_lenght = 0.1', "[mesh].max_edge_lenght", "did you mean 'max_edge_length'")
    rejects('path = "cube.off"\nmax_edge_length = -0.1', "[mesh].max_edge_length", "must be > 0")
    rejects('path = "cube.off"\nmax_radius_edge_ratio = 1.0', "[mesh].max_radius_edge_ratio", "must be >= 1.1")
    rejects('path = "cube.off"\nmesher = "tetgn"', "[mesh].mesher", "did you mean 'tetgen'")
    rejects('generator = "box"\nsize = [1, 1, 1]\ncells = [1, 1, 1]\nmax_edge_length = 0.1', "[mesh].max_edge_length",
            "only applies to path")
    rejects('path = "cube.off"\nelement = "hex8"', "[mesh].element", "surface file is tetrahedralised")
    rejects('path = "cube.off"\ninside_surface = true', "[mesh].inside_surface", "tet files")
    ok = load_scene(_scene(tmp_path, 'path = "cube.off"\nmax_edge_length = 0.25\nmesher = "tetgen"'))
    assert ok.spec.mesh["max_edge_length"] == 0.25 and ok.spec.mesh["mesher"] == "tetgen"


def test_volume_files_unchanged_and_refuse_surface_options(meshes_dir):
    mesh = load_mesh(meshes_dir / "octopus-low.mesh")
    assert mesh.num_elements == 1140 and not hasattr(mesh, "tetrahedralization")
    with pytest.raises(MeshError, match="max_edge_length only apply to surface files"):
        load_mesh(meshes_dir / "octopus-low.mesh", max_edge_length=0.1)


def test_scene_options_reach_the_mesher(tetgen, tmp_path):
    from warpfem.scenes import load_scene

    write_off(tmp_path / "cube.off", CUBE_V * 0.2, CUBE_F)
    coarse = load_scene(_scene(tmp_path, 'path = "cube.off"', fixed_y=0.01)).mesh()
    fine = load_scene(_scene(tmp_path, 'path = "cube.off"\nmax_edge_length = 0.05', fixed_y=0.01)).mesh()
    assert fine.tetrahedralization.options["max_edge_length"] == 0.05
    assert fine.num_elements > 10 * coarse.num_elements
    assert abs(tet_volumes(fine.vertices, fine.tets).sum() - 0.008) < 1e-14


def test_python_options_are_validated():
    for kw, words in (({"max_edge_length": -0.1}, "max_edge_length must be a finite number > 0"),
                      ({"max_edge_length": float("nan")}, "max_edge_length must be a finite number > 0"),
                      ({"max_radius_edge_ratio": 1.0}, "max_radius_edge_ratio must be a number >= 1.1"),
                      ({"mesher": "gmsh"}, "mesher must be one of 'auto', 'tetgen', 'tetwild'")):
        with pytest.raises(MeshError, match=words):
            tetrahedralize(CUBE_V, CUBE_F, **kw)


def test_self_intersection_between_faces_sharing_a_vertex():
    # a closed tetrahedron-like fan whose apex face folds through the opposite face: faces (0, 1, 2) and
    # (0, 3, 4) share vertex 0, and edge (3, 4) pierces face (0, 1, 2)
    V = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0], [0.5, 0.5, -1], [0.5, 0.5, 1]], dtype=np.float64)
    F = np.array([[0, 1, 2], [0, 3, 4]])
    pairs = T._self_intersections(V, F, 3.0)
    assert pairs.tolist() == [[0, 1]]
    V2 = V.copy()
    V2[3, 2] = 0.5  # the edge lifted above face 0 (both faces meet only at vertex 0): no crossing
    assert len(T._self_intersections(V2, F, 3.0)) == 0
