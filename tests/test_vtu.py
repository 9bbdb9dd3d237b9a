"""ParaView output ([output] vtu): the .pvd collection and its per-frame .vtu files, read back with
meshio and parsed as XML; element fields (J, von Mises) against hand-computed values; VTK node order
of the quadratic cells; an interrupted run leaves a valid collection."""

import os
import textwrap
import xml.etree.ElementTree as ET

import meshio
import numpy as np
import pytest

import warpfem as wf
from warpfem.io import VtuSeriesWriter, VtuWriterError, element_stress_fields, read_pvd
from warpfem.scenes import SceneError, load_scene

SCENE = """
gravity = [0.0, -9.81, 0.0]
[mesh]
generator = "box"
size = [1.0, 0.2, 0.2]
cells = [4, 1, 1]
element = "{element}"
[material]
model = "stable_neo_hookean"
youngs_modulus = 1e5
poisson_ratio = 0.3
[[fixed]]
box_min = [-1.0, -1.0, -1.0]
box_max = [0.0, 1.0, 1.0]
[integrator]
type = "backward_euler"
dt = 0.05
[output]
fps = 20
frames = 3
states = "{states}"
vtu = "{vtu}"
"""


def scene_file(tmp_path, element="tet4", text=SCENE):
    p = tmp_path / f"{element}.toml"
    p.write_text(textwrap.dedent(text.format(element=element, states=tmp_path / "s.npz", vtu=tmp_path / "o" / "run.pvd")))
    return p


def pvd_datasets(path):
    """(timestep, file) of every DataSet of a .pvd, parsed with ElementTree (what ParaView reads)."""
    root = ET.parse(path).getroot()
    assert root.tag == "VTKFile" and root.get("type") == "Collection"
    (coll,) = list(root)
    return [(float(d.get("timestep")), d.get("file")) for d in coll]


def tet_volumes(x, tets):
    p = x[tets]
    return np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0]) / 6.0


def test_scene_vtu_matches_states_and_independent_fields(tmp_path):
    """Frames 0..3 of a tet4 run: points/displacement equal the npz states, velocity the backward Euler
    (x_f - x_{f-1}) / dt (one step per frame), J the deformed / rest tet volume, von Mises the Cauchy
    stress of the material's P at F = Ds Dm^-1; rest frame: J = 1, von Mises = 0."""
    run = load_scene(scene_file(tmp_path)).build(device="cpu", precision="float64")
    run.run()
    pvd = tmp_path / "o" / "run.pvd"
    sets = pvd_datasets(pvd)
    assert [f for _, f in sets] == [f"run.vtu/frame_{i:06d}.vtu" for i in range(4)]
    st = np.load(tmp_path / "s.npz")
    assert [t for t, _ in sets] == pytest.approx(st["times"].tolist(), abs=1e-12)
    entries, meta = read_pvd(pvd)
    assert meta["complete"] is True and meta["frames"] == 4 and meta["version"] == wf.__version__
    assert sorted(os.listdir(tmp_path / "o" / "run.vtu")) == [f"frame_{i:06d}.vtu" for i in range(4)]  # no temporaries
    X, mat = st["rest"], run.model.material
    for f, (_, path) in enumerate(entries):
        m = meshio.read(path)
        assert m.points.shape == (20, 3) and [c.type for c in m.cells] == ["tetra"]
        tets = m.cells[0].data
        np.testing.assert_array_equal(tets, np.asarray(run.model.quadrature.elements).reshape(-1, 4))
        x = st["positions"][f]
        np.testing.assert_allclose(m.points, x, rtol=0, atol=1e-14)
        np.testing.assert_allclose(m.point_data["displacement"], x - X, rtol=0, atol=1e-14)
        v_expected = np.zeros_like(x) if f == 0 else (x - st["positions"][f - 1]) / 0.05
        np.testing.assert_allclose(m.point_data["velocity"], v_expected, rtol=0, atol=1e-9)
        J, vm = m.cell_data["J"][0], m.cell_data["von_mises"][0]
        np.testing.assert_allclose(J, tet_volumes(x, tets) / tet_volumes(X, tets), rtol=1e-12)
        Dm = np.stack([X[tets[:, i]] - X[tets[:, 0]] for i in (1, 2, 3)], axis=2)
        Ds = np.stack([x[tets[:, i]] - x[tets[:, 0]] for i in (1, 2, 3)], axis=2)
        F = Ds @ np.linalg.inv(Dm)
        sigma = mat.pk1(F) @ np.swapaxes(F, 1, 2) / np.linalg.det(F)[:, None, None]
        s = sigma - np.trace(sigma, axis1=1, axis2=2)[:, None, None] * np.eye(3) / 3
        np.testing.assert_allclose(vm, np.sqrt(1.5 * (s * s).sum(axis=(1, 2))), rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(m.cell_data["cauchy_stress"][0].reshape(-1, 3, 3), sigma, rtol=1e-9, atol=1e-9)
        if f == 0:
            np.testing.assert_array_equal(J, 1.0)
            assert np.abs(vm).max() < 1e-9
        else:
            assert vm.max() > 100.0  # it sags: Pa-scale bending stress in the clamped elements
    assert st["positions"][-1][:, 1].min() < -1e-3


# VTK parametric coordinates of the cell nodes (vtkQuadraticTetra, vtkTriQuadraticHexahedron), in [0, 1]
VTK_TET10 = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [.5, 0, 0], [.5, .5, 0], [0, .5, 0], [0, 0, .5],
                      [.5, 0, .5], [0, .5, .5]])
VTK_HEX27 = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [0, 0, 1], [1, 0, 1], [1, 1, 1], [0, 1, 1],
                      [.5, 0, 0], [1, .5, 0], [.5, 1, 0], [0, .5, 0], [.5, 0, 1], [1, .5, 1], [.5, 1, 1], [0, .5, 1],
                      [0, 0, .5], [1, 0, .5], [1, 1, .5], [0, 1, .5], [0, .5, .5], [1, .5, .5], [.5, 0, .5],
                      [.5, 1, .5], [.5, .5, 0], [.5, .5, 1], [.5, .5, .5]])


def _quadratic_meshes():
    tet10 = wf.tet10_from_tet4(wf.box_tet_mesh(size=(1.0, 0.5, 0.3), cells=(2, 1, 1)))
    hex27 = wf.box_hex_mesh(size=(1.0, 0.5, 0.3), cells=(2, 1, 1), order=2)
    return {"tet10": (tet10, "tetra10"), "hex27": (hex27, "hexahedron27")}


@pytest.mark.parametrize("etype", ["tet10", "hex27"])
def test_quadratic_cells_read_back_in_vtk_node_order(tmp_path, etype):
    """Read back, each node of a tet10/hex27 cell sits where VTK's parametric coordinates of that node
    put it (affine map of the tet corners / trilinear map of the hex corners), and the corner
    volume is positive (VTK's orientation)."""
    mesh, vtk_type = _quadratic_meshes()[etype]
    k = 10 if etype == "tet10" else 27
    with VtuSeriesWriter(tmp_path / "q.pvd", cells=mesh.elements, element_type=etype) as w:
        w.write_frame(0.0, mesh.vertices)
    (_, path), = read_pvd(tmp_path / "q.pvd")[0]
    m = meshio.read(path)
    assert [c.type for c in m.cells] == [vtk_type]  # meshio names cells from the VTK type ids (24 / 29)
    cells = m.cells[0].data
    assert cells.shape == (mesh.num_elements, k)
    P = m.points[cells]  # (m, k, 3)
    if etype == "tet10":
        c = P[:, :4]
        expected = c[:, :1] + np.einsum("pj,mji->mpi", VTK_TET10, c[:, 1:] - c[:, :1])
        vol = np.einsum("ij,ij->i", np.cross(c[:, 1] - c[:, 0], c[:, 2] - c[:, 0]), c[:, 3] - c[:, 0])
    else:
        c = P[:, :8]
        r, s, t = VTK_HEX27.T
        N = np.stack([(1 - r) * (1 - s) * (1 - t), r * (1 - s) * (1 - t), r * s * (1 - t), (1 - r) * s * (1 - t),
                      (1 - r) * (1 - s) * t, r * (1 - s) * t, r * s * t, (1 - r) * s * t], axis=1)  # (27, 8)
        expected = np.einsum("pj,mji->mpi", N, c)
        vol = np.einsum("ij,ij->i", np.cross(c[:, 1] - c[:, 0], c[:, 3] - c[:, 0]), c[:, 4] - c[:, 0])
    np.testing.assert_allclose(P, expected, atol=1e-12)
    assert (vol > 0).all()


def _stretch_meshes():
    return {"tet4": wf.box_tet_mesh(size=(1.0, 0.5, 0.5), cells=(2, 1, 1)),
            "hex8": wf.box_hex_mesh(size=(1.0, 0.5, 0.5), cells=(2, 1, 1)), **{k: v[0] for k, v in _quadratic_meshes().items()}}


@pytest.mark.parametrize("etype", ["tet4", "tet10", "hex8", "hex27"])
def test_von_mises_and_J_under_uniaxial_stretch(tmp_path, etype):
    """Linear material, homogeneous F = diag(1 + e, 1 - nu e, 1 - nu e): the small strain is uniaxial
    stress, P = diag(E e, 0, 0), so Cauchy sigma_xx = E e (1 + e) / det F = E e / (1 - nu e)^2 and
    von Mises = |sigma_xx|, J = det F; every element, every element type (quadrature averages),
    and the same values read back from the .vtu."""
    E, nu, e = 2.0e5, 0.3, 0.04
    mesh = _stretch_meshes()[etype]
    model = wf.Model(mesh, wf.LinearElastic(youngs_modulus=E, poisson_ratio=nu, density=1000.0))
    sim = wf.Simulator(model, device="cpu", precision="float64")
    F = np.diag([1 + e, 1 - nu * e, 1 - nu * e])
    x = model.rest_positions @ F.T
    fields = element_stress_fields(sim, model, x)
    sxx = E * e / (1 - nu * e) ** 2
    m = mesh.num_elements
    np.testing.assert_allclose(fields["J"], np.full(m, np.linalg.det(F)), rtol=1e-13)
    np.testing.assert_allclose(fields["von_mises"], np.full(m, sxx), rtol=1e-11)
    sigma = np.zeros((3, 3))
    sigma[0, 0] = sxx
    np.testing.assert_allclose(fields["cauchy_stress"], np.broadcast_to(sigma, (m, 3, 3)), rtol=0, atol=1e-9 * sxx)
    at_rest = element_stress_fields(sim, model, model.rest_positions)
    np.testing.assert_array_equal(at_rest["J"], 1.0)
    assert np.abs(at_rest["von_mises"]).max() < 1e-9
    sim.set_positions(x)
    with VtuSeriesWriter(tmp_path / "u.pvd", cells=mesh.elements, element_type=etype) as w:
        f = element_stress_fields(sim, model)
        w.write_frame(0.0, x, point_data={"displacement": x - model.rest_positions},
                      cell_data={"von_mises": f["von_mises"]})
    back = meshio.read(read_pvd(tmp_path / "u.pvd")[0][0][1])
    np.testing.assert_allclose(back.cell_data["von_mises"][0], sxx, rtol=1e-11)
    np.testing.assert_allclose(back.point_data["displacement"], x - model.rest_positions, atol=1e-15)


def test_stress_without_simulator_stresses():
    """Simulators without ``stresses()``: stiffness warping gives the corotational linear stress (equal
    to the linear one for a pure stretch, whose polar rotation is I, and unchanged by a rigid rotation
    on top); a simulator with positions only (e.g. reduced) gets the model's material at F."""
    E, nu, e = 2.0e5, 0.3, 0.04
    mesh = wf.box_tet_mesh(size=(1.0, 0.5, 0.5), cells=(2, 1, 1))
    model = wf.Model(mesh, wf.LinearElastic(youngs_modulus=E, poisson_ratio=nu, density=1000.0))
    F = np.diag([1 + e, 1 - nu * e, 1 - nu * e])
    x = model.rest_positions @ F.T
    sxx = E * e / (1 - nu * e) ** 2
    warping = wf.StiffnessWarpingSimulator(model, device="cpu", precision="float64")
    np.testing.assert_allclose(element_stress_fields(warping, model, x)["von_mises"], sxx, rtol=1e-10)
    c, s = np.cos(0.7), np.sin(0.7)
    R = np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])
    rotated = element_stress_fields(warping, model, x @ R.T)
    np.testing.assert_allclose(rotated["von_mises"], sxx, rtol=1e-9)
    np.testing.assert_allclose(rotated["J"], np.linalg.det(F), rtol=1e-12)

    class PositionsOnly:
        def positions(self):
            return x

    np.testing.assert_allclose(element_stress_fields(PositionsOnly(), model)["von_mises"], sxx, rtol=1e-11)


def test_interrupted_run_leaves_valid_collection(tmp_path, monkeypatch):
    """A step raising in frame 3 leaves run.pvd listing frames 0..2 (marked incomplete with the reason),
    every listed .vtu readable, no temporaries; a later complete run replaces stale frames."""
    run = load_scene(scene_file(tmp_path)).build(device="cpu", precision="float64")
    real_step, calls = run.sim.step, []

    def step():
        calls.append(1)
        if len(calls) == 3:
            raise RuntimeError("boom inside a step")
        return real_step()

    monkeypatch.setattr(run.sim, "step", step)
    with pytest.raises(RuntimeError, match="boom"):
        run.run()
    pvd = tmp_path / "o" / "run.pvd"
    sets = pvd_datasets(pvd)
    assert [f for _, f in sets] == [f"run.vtu/frame_{i:06d}.vtu" for i in range(3)]
    entries, meta = read_pvd(pvd)
    assert meta["complete"] is False and meta["frames"] == 3 and "RuntimeError: boom inside a step" in meta["reason"]
    for _, path in entries:
        assert meshio.read(path).points.shape == (20, 3)
    assert sorted(os.listdir(tmp_path / "o")) == ["run.pvd", "run.vtu"]
    assert sorted(os.listdir(tmp_path / "o" / "run.vtu")) == [f"frame_{i:06d}.vtu" for i in range(3)]
    # a new 1-frame run into the same collection: 2 frames listed, the stale third file removed
    run2 = load_scene(scene_file(tmp_path)).build(device="cpu", precision="float64")
    run2.run(frames=1)
    assert len(pvd_datasets(pvd)) == 2 and read_pvd(pvd)[1]["complete"] is True
    assert sorted(os.listdir(tmp_path / "o" / "run.vtu")) == [f"frame_{i:06d}.vtu" for i in range(2)]


def test_bad_vtu_paths_and_shapes(tmp_path):
    text = SCENE.replace('vtu = "{vtu}"', 'vtu = "out/run.vtu"')
    with pytest.raises(SceneError, match=r"\[output\]\.vtu.*must end in \.pvd"):
        load_scene(scene_file(tmp_path, text=text))
    with pytest.raises(VtuWriterError, match="must end in .pvd"):
        VtuSeriesWriter(tmp_path / "x.vtu", cells=[[0, 1, 2, 3]], element_type="tet4")
    with pytest.raises(VtuWriterError, match=r"shape \(m, 10\)"):
        VtuSeriesWriter(tmp_path / "x.pvd", cells=[[0, 1, 2, 3]], element_type="tet10")
    w = VtuSeriesWriter(tmp_path / "x.pvd", cells=[[0, 1, 2, 3]], element_type="tet4")
    with pytest.raises(VtuWriterError, match="point data 'velocity' has 3 rows, expected 4"):
        w.write_frame(0.0, np.eye(4, 3), point_data={"velocity": np.zeros((3, 3))})
    w.close()
    assert read_pvd(tmp_path / "x.pvd") == ([], {"complete": True, "frames": 0, "version": wf.__version__})
