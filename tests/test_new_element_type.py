"""Adding an element type is one module under ``warpfem/mesh/element_types/`` plus a registry line.

The test writes such a module's class here (a 6-node linear prism, "wedge6", which warpfem does not
ship), registers it for the duration of the test, and checks that the mesh class, validation and
reorientation, boundary faces, both mass matrices, the quadrature precompute, the model, the Warp
kernels and point embedding all work with it unchanged, against exact values. A second check reads
the source: outside ``element_types/`` the core modules never compare against an element name.
"""

import ast
import os
import warnings

import numpy as np
import pytest

import warpfem as wf
from warpfem.mesh import VolumeMesh, consistent_mass, embed_points_in_elements, lumped_mass
from warpfem.mesh.element_types import ELEMENTS, register_element
from warpfem.mesh.element_types.base import TRI_RULE, ElementType, as_points

ROOT = os.path.join(os.path.dirname(os.path.dirname(os.path.abspath(__file__))), "warpfem")


class Wedge6(ElementType):
    """Linear prism on {xi, eta >= 0, xi + eta <= 1} x [-1, 1]: N = L_i(xi, eta) (1 -+ zeta) / 2,
    nodes 0..2 on zeta = -1 and 3..5 above them."""

    name = "wedge6_test"
    nodes_per_element = 6
    meshio_cell = "wedge6_test"
    reference_nodes = np.array([[0, 0, -1], [1, 0, -1], [0, 1, -1], [0, 0, 1], [1, 0, 1], [0, 1, 1]], dtype=np.float64)
    reference_volume = 1.0
    corner_nodes = np.arange(6, dtype=np.int64)
    corner_tets = np.array([[0, 1, 2, 3], [1, 2, 3, 4], [2, 3, 4, 5]], dtype=np.int64)
    lumping = "row-sum"
    rule_degree = {"stiffness": 3, "mass": 5}  # per variable in zeta; degree 4 on the triangle
    description = "linear prism, 6 nodes (test only)"

    def shape(self, xi):
        xi = as_points(xi)
        L = np.stack([1.0 - xi[:, 0] - xi[:, 1], xi[:, 0], xi[:, 1]], axis=1)  # (p, 3)
        dL = np.array([[-1.0, -1.0], [1.0, 0.0], [0.0, 1.0]])
        Z = np.stack([(1.0 - xi[:, 2]) / 2, (1.0 + xi[:, 2]) / 2], axis=1)  # (p, 2)
        dZ = np.array([-0.5, 0.5])
        N = np.concatenate([L * Z[:, :1], L * Z[:, 1:]], axis=1)
        dN = np.empty((len(xi), 6, 3))
        for layer in range(2):
            s = slice(3 * layer, 3 * layer + 3)
            dN[:, s, 0] = dL[None, :, 0] * Z[:, layer:layer + 1]
            dN[:, s, 1] = dL[None, :, 1] * Z[:, layer:layer + 1]
            dN[:, s, 2] = L * dZ[layer]
        return N, dN

    def _rule(self, purpose):
        tri_pts, tri_w = TRI_RULE  # degree 4 on the triangle
        g, gw = np.polynomial.legendre.leggauss(2 if purpose == "stiffness" else 3)  # Gauss in zeta
        pts = np.array([[s, t, z] for s, t in tri_pts for z in g])
        return pts, np.outer(tri_w, gw).ravel()

    def reflect(self, xi):
        return as_points(xi) * np.array([1.0, 1.0, -1.0])

    def face_triangles(self):
        return [(np.array([0, 2, 1]), np.array([[0, 2, 1]])), (np.array([3, 4, 5]), np.array([[3, 4, 5]])),
                (np.array([0, 1, 4, 3]), np.array([[0, 1, 4], [0, 4, 3]])),
                (np.array([0, 3, 5, 2]), np.array([[0, 3, 5], [0, 5, 2]])),
                (np.array([1, 2, 5, 4]), np.array([[1, 2, 5], [1, 5, 4]]))]


@pytest.fixture
def wedge():
    register_element(Wedge6)  # what the module's decorator does on import
    try:
        yield ELEMENTS[Wedge6.name]
    finally:
        ELEMENTS.pop(Wedge6.name)


def _wedge_box(cells=(2, 2, 2), size=(2.0, 1.0, 1.5), seed=None):
    """Each cell of the box grid split into two prisms along its 0-2 diagonal; with ``seed`` the
    interior nodes are jittered (prisms then are not affine: det J varies inside)."""
    hexes = wf.box_hex_mesh(size=size, cells=cells)
    c = hexes.elements  # hex8 corners, VTK order
    prisms = np.concatenate([c[:, [0, 1, 3, 4, 5, 7]], c[:, [2, 3, 1, 6, 7, 5]]])
    X = hexes.vertices.copy()
    if seed is not None:
        inner = np.all((X > 1e-9) & (X < np.asarray(size) - 1e-9), axis=1)
        X[inner] += np.random.default_rng(seed).uniform(-0.1, 0.1, (inner.sum(), 3)) * min(np.asarray(size) / cells)
    return X, prisms, float(np.prod(size))


def test_a_registered_element_type_works_everywhere(wedge):
    X, prisms, V = _wedge_box(seed=4)
    mesh = VolumeMesh(X, prisms, "wedge6_test")
    assert mesh.element is wedge and mesh.nodes_per_element == 6
    assert mesh.total_volume() == pytest.approx(V, rel=1e-12)
    # boundary: closed, outward (divergence theorem gives the volume), watertight
    F = mesh.boundary_faces()
    a, b, c = X[F[:, 0]], X[F[:, 1]], X[F[:, 2]]
    assert np.einsum("ij,ij->", a, np.cross(b, c)) / 6 == pytest.approx(V, rel=1e-12)
    edges = np.sort(np.concatenate([F[:, [0, 1]], F[:, [1, 2]], F[:, [2, 0]]]), axis=1)
    assert (np.unique(edges, axis=0, return_counts=True)[1] == 2).all()
    # masses: total rho V; the consistent matrix integrates a linear field's kinetic energy exactly
    rho = 3.0
    m, M = lumped_mass(mesh, rho), consistent_mass(mesh, rho)
    assert m.min() > 0 and m.sum() == pytest.approx(rho * V, rel=1e-12)
    Xr = mesh.vertices
    v = Xr[:, 0] - 2 * Xr[:, 1] + Xr[:, 2]
    # int over [0,2]x[0,1]x[0,1.5] of (x - 2y + z)^2 = x^2 4 + 4y^2 4 + z^2 2.25 - 4xy 6 + 2xz 4.5 - 4yz 4.5
    assert v @ (M @ v) == pytest.approx(rho * 4.25, rel=1e-10)
    # model + Warp kernels: an affine deformation is an equilibrium (no force on interior nodes) and
    # stores psi V; the rule integrates it exactly
    model = wf.Model(mesh, wf.LinearElastic(youngs_modulus=10.0, poisson_ratio=0.3, density=rho), mass_matrix="consistent")
    assert model.quadrature.nodes_per_element == 6 and model.quadrature.num_points == 12 * mesh.num_elements
    np.testing.assert_allclose(model.lumped_mass, m, rtol=1e-13)
    sim = wf.Simulator(model, precision="float64")
    A = 1e-3 * np.array([[1, 0.2, 0.1], [0.3, -0.5, 0.4], [0, 0.1, 0.7]])
    x = Xr + Xr @ A.T
    eps = 0.5 * (A + A.T)
    mat = model.material
    psi = mat.mu_lame * np.sum(eps * eps) + 0.5 * mat.lam_lame * np.trace(eps) ** 2
    assert sim.elastic_energy(x) == pytest.approx(psi * V, rel=1e-10)
    interior = np.all((Xr > 1e-9) & (Xr < np.array([2.0, 1.0, 1.5]) - 1e-9), axis=1)
    f = sim.elastic_forces(x)
    assert interior.sum() == 1 and np.abs(f[interior]).max() < 1e-10 * np.abs(f).max()
    # embedding: points reproduced and carried by an affine motion
    pts = np.random.default_rng(1).uniform([0.1, 0.1, 0.1], [1.9, 0.9, 1.4], (30, 3))
    ids, w, _ = embed_points_in_elements(pts, mesh)
    np.testing.assert_allclose(np.einsum("pa,pai->pi", w, Xr[ids]), pts, atol=1e-12)
    np.testing.assert_allclose(np.einsum("pa,pai->pi", w, x[ids]), pts + pts @ A.T, atol=1e-12)


def test_a_registered_element_type_gets_the_common_validation(wedge):
    X, prisms, V = _wedge_box()
    flipped = prisms.copy()
    flipped[[1, 5]] = flipped[[1, 5]][:, [3, 4, 5, 0, 1, 2]]  # mirrored: det J < 0 everywhere
    with pytest.warns(UserWarning, match=r"reoriented 2 of 16 negatively oriented wedge6_test elements"):
        mesh = VolumeMesh(X, flipped, wedge)
    np.testing.assert_array_equal(mesh.reoriented_tets, [1, 5])
    np.testing.assert_array_equal(mesh.elements, prisms)
    with pytest.raises(wf.MeshError, match=r"2 negatively oriented wedge6_test elements: 1, 5"):
        VolumeMesh(X, flipped, wedge, reorient=False)
    bad = prisms.copy()
    bad[3, 2] = len(X) + 4
    with pytest.raises(wf.MeshError, match=rf"wedge6_test element 3 references vertex index {len(X) + 4} out of range"):
        VolumeMesh(X, bad, wedge)
    flat = X.copy()
    flat[:, 2] = 0.0  # every prism collapsed
    with pytest.raises(wf.MeshError, match=r"16 degenerate \(zero-volume\) wedge6_test elements"):
        VolumeMesh(flat, prisms, wedge)
    nan = X.copy()
    nan[7, 1] = np.nan
    with pytest.raises(wf.MeshError, match=r"vertex 7 has non-finite \(NaN\)"):
        VolumeMesh(nan, prisms, wedge)
    with pytest.raises(wf.MeshError, match=r"wedge6_test elements must have shape \(m, 6\)"):
        VolumeMesh(X, prisms[:, :4], wedge)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        VolumeMesh(X, prisms, wedge)  # a valid mesh: no warning
    with pytest.raises(wf.MeshError, match="unknown element type 'wedge7'"):
        VolumeMesh(X, prisms, "wedge7")


# -- nothing outside element_types switches on the type name -------------------------------------------
CORE = ("mesh", "elements", "model.py", "kernels", "io", "skinning", "simulator.py", "solvers", "contact", "reduced",
        "scenes", "tradeoff", "cli.py")
FRONT_ENDS = ()  # the scene front ends ask the element objects too (box_mesh, from_tet4, is_linear_tet)


def _core_files():
    for part in CORE:
        p = os.path.join(ROOT, part)
        if p.endswith(".py"):
            yield p
            continue
        for d, _, files in os.walk(p):
            if os.path.basename(d) == "element_types":
                continue
            yield from (os.path.join(d, f) for f in files
                        if f.endswith(".py") and os.path.relpath(os.path.join(d, f), ROOT) not in FRONT_ENDS)


def test_core_modules_do_not_switch_on_element_names():
    """Comparisons (==, !=, in) or dict keys with a registered element name, in the core modules,
    would mean a new element type needs edits there; they ask the element object instead."""
    names = set(ELEMENTS)
    found = []
    for path in _core_files():
        tree = ast.parse(open(path, encoding="utf-8").read(), filename=path)
        for node in ast.walk(tree):
            consts = []
            if isinstance(node, ast.Compare):
                for side in [node.left, *node.comparators]:
                    consts += [side] + (list(side.elts) if isinstance(side, (ast.Tuple, ast.List, ast.Set)) else [])
            elif isinstance(node, ast.Dict):
                consts = [k for k in node.keys if k is not None]
            for c in consts:
                if isinstance(c, ast.Constant) and c.value in names:
                    found.append(f"{os.path.relpath(path, ROOT)}:{node.lineno}: {c.value!r}")
    assert not found, "element-name switches outside element_types:\n" + "\n".join(found)


def test_scene_elements_come_from_the_element_objects(tmp_path):
    """[mesh].element lists every registered type, and what a scene can build with each comes from
    the object: a box for types with ``box_mesh``, a tet file or surface for types with ``from_tet4``."""
    from warpfem.scenes import SceneError, load_scene
    from warpfem.scenes.schema import ELEMENTS as SCENE_ELEMENTS, ELEMENTS_FROM_TETS, ELEMENTS_WITH_BOX

    builtin = ("tet4", "tet10", "hex8", "hex27")
    assert all(n in SCENE_ELEMENTS and SCENE_ELEMENTS[n] == ELEMENTS[n].description for n in builtin)
    assert ELEMENTS_WITH_BOX[:4] == builtin and ELEMENTS_FROM_TETS[:2] == ("tet4", "tet10")
    scene = """
[mesh]
generator = "box"
size = [1.0, 0.25, 0.25]
cells = [2, 1, 1]
element = "{el}"
[material]
model = "linear"
youngs_modulus = 1.0e5
poisson_ratio = 0.3
density = 1000.0
"""
    counts = {}
    for el in builtin:
        p = tmp_path / f"{el}.toml"
        p.write_text(scene.format(el=el))
        mesh = load_scene(str(p)).mesh()
        assert mesh.element is ELEMENTS[el]
        counts[el] = (mesh.num_vertices, mesh.num_elements)
    # 2x1x1 cells: tets 6 per cell on a 3x2x2 grid (+ 1 mid-node per unique edge), hexes 1 per cell
    assert counts == {"tet4": (12, 12), "tet10": (12 + 33, 12), "hex8": (12, 2), "hex27": (45, 2)}
    surface = tmp_path / "tri.off"
    surface.write_text("OFF\n4 4 0\n0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n")
    p = tmp_path / "hex_surface.toml"
    p.write_text(scene.replace('generator = "box"\nsize = [1.0, 0.25, 0.25]\ncells = [2, 1, 1]', 'path = "tri.off"').format(el="hex8"))
    with pytest.raises(SceneError, match=r'\[mesh\]\.element.*"tet4" or "tet10", not \'hex8\''):
        load_scene(str(p))
