"""Registries that keep the layers apart: the scene integrator registry (a layer above scenes, the
subspace simulator, plugs in through it) and the material registry."""

import textwrap

import pytest

from warpfem.scenes import INTEGRATORS, SECTION_INTEGRATORS, IntegratorType, integrator_entry, load_scene, register_integrator

SCENE = """
name = "tiny"
[mesh]
generator = "box"
size = [2.0, 1.0, 1.0]
cells = [2, 1, 1]
[material]
model = "linear"
youngs_modulus = 1e5
poisson_ratio = 0.3
density = 100.0
[integrator]
type = "{integrator}"
[output]
frames = 2
{extra}
"""


def _scene(tmp_path, integrator="backward_euler", extra=""):
    p = tmp_path / "tiny.toml"
    p.write_text(textwrap.dedent(SCENE.format(integrator=integrator, extra=extra)))
    return load_scene(str(p))


def test_a_subspace_section_selects_the_registered_reduced_entry(tmp_path):
    plain = _scene(tmp_path, "bdf2")
    assert integrator_entry(plain) is INTEGRATORS["bdf2"]
    reduced = _scene(tmp_path, "bdf2", "[subspace]\nmodes = 4\n")
    entry = integrator_entry(reduced)
    assert entry is SECTION_INTEGRATORS["subspace"] and entry.section == "subspace"
    assert integrator_entry(reduced, full=True) is INTEGRATORS["bdf2"]  # the training run
    assert "subspace" not in INTEGRATORS  # not an [integrator].type value
    assert "r = 4" in reduced.describe()


def test_register_integrator_refuses_a_second_entry_for_a_section():
    entry = SECTION_INTEGRATORS["subspace"]
    with pytest.raises(ValueError, match=r"\[subspace\] is already registered"):
        register_integrator(IntegratorType("other", entry.build, section="subspace"))
    assert SECTION_INTEGRATORS["subspace"] is entry


def test_material_kinds_are_defined_once_in_the_registry():
    import warpfem.materials as M
    from warpfem.materials.registry import MATERIAL_TYPES, register_material

    kinds = {t.name: t.kind for t in MATERIAL_TYPES.values()}
    # stable ints (subspace caches store them) and one class per kind
    assert kinds == {"linear": 0, "stvk": 1, "corotated": 2, "stable_neo_hookean": 3, "stable_neo_hookean_log": 4}
    for name, t in MATERIAL_TYPES.items():
        assert t.cls.kind == t.kind and t.cls.name == name and M.MATERIALS[name] is t.cls
    assert (M.LINEAR, M.STVK, M.COROTATED, M.STABLE_NEO_HOOKEAN, M.STABLE_NEO_HOOKEAN_LOG) == (0, 1, 2, 3, 4)
    with pytest.raises(ValueError, match="kind 3 .* already used by 'stable_neo_hookean'"):
        register_material("other", kind=3, psi=None, pk1=None, eigen=None)(type("Other", (), {}))
    assert "other" not in MATERIAL_TYPES


def test_scene_material_models_come_from_the_registry(tmp_path):
    """The schema's [material].model choices are the registered materials: each one loads; an
    unknown name is refused with the valid ones listed."""
    from warpfem.materials.registry import MATERIAL_TYPES
    from warpfem.scenes import SceneError
    from warpfem.scenes.schema import SCHEMA

    assert tuple(SCHEMA["material"]["model"].choices) == tuple(MATERIAL_TYPES)
    assert len(MATERIAL_TYPES) >= 5
    for name in MATERIAL_TYPES:
        p = tmp_path / f"{name}.toml"
        p.write_text(textwrap.dedent(SCENE.format(integrator="backward_euler", extra="")).replace('"linear"', f'"{name}"'))
        scene = load_scene(str(p))
        assert scene.spec.material["model"] == name
    p = tmp_path / "unknown.toml"
    p.write_text(textwrap.dedent(SCENE.format(integrator="backward_euler", extra="")).replace('"linear"', '"neo_hooke"'))
    with pytest.raises(SceneError) as e:
        load_scene(str(p))
    msg = str(e.value)
    assert "[material].model" in msg and "'neo_hooke'" in msg
    for name in MATERIAL_TYPES:
        assert repr(name) in msg


def test_kernel_parameters_are_named_apart_from_lame():
    """Stable neo-Hookean passes reparametrised (mu, lambda) to the kernels (Smith, de Goes & Kim
    2018, "Stable neo-Hookean flesh simulation": mu' = mu, lambda' = lambda + mu)."""
    from warpfem.materials import StableNeoHookean

    m = StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1.0)
    assert m.kernel_mu == pytest.approx(m.mu_lame) and m.kernel_lam == pytest.approx(m.lam_lame + m.mu_lame)
    assert not hasattr(m, "mu") and not hasattr(m, "lam")  # no name that hides which of the two it is


def test_every_element_type_object_is_consistent():
    """Invariants every registered element type must satisfy (so a new one is checked too):
    Kronecker property at its nodes, partition of unity, reference gradients against central
    differences, rules summing to the reference volume, corner sub-tets filling the element with
    positive volume, outward faces whose nodes lie on them."""
    import numpy as np

    from warpfem.elements import ELEMENTS

    rng = np.random.default_rng(3)
    assert set(ELEMENTS) >= {"tet4", "tet10", "hex8", "hex27"}
    for name, e in ELEMENTS.items():
        k = e.nodes_per_element
        N, _ = e.shape(e.reference_nodes)
        np.testing.assert_allclose(N, np.eye(k), atol=1e-13, err_msg=name)
        xi = rng.uniform(0.05, 0.2, (5, 3)) if e.reference_volume < 1 else rng.uniform(-0.9, 0.9, (5, 3))
        N, dN = e.shape(xi)
        np.testing.assert_allclose(N.sum(axis=1), 1.0, atol=1e-13, err_msg=name)
        h = 1e-6
        for d in range(3):
            dx = np.zeros(3)
            dx[d] = h
            fd = (e.shape(xi + dx)[0] - e.shape(xi - dx)[0]) / (2 * h)
            np.testing.assert_allclose(dN[:, :, d], fd, atol=1e-8, err_msg=name)
        for purpose in e.rule_degree:
            assert e.rule(purpose)[1].sum() == pytest.approx(e.reference_volume, rel=1e-12), (name, purpose)
        P = e.reference_nodes[e.corner_tets]  # (s, 4, 3)
        vols = np.linalg.det(np.stack([P[:, i] - P[:, 0] for i in (1, 2, 3)], axis=2)) / 6
        assert np.all(vols > 0) and vols.sum() == pytest.approx(e.reference_volume, rel=1e-12), name
        centre = e.reference_nodes[e.corner_nodes].mean(axis=0)
        for on, corners, origin, T, pts, wts in e.faces():
            normal = np.cross(T[0], T[1])
            assert normal @ (origin - centre) > 0, name  # outward
            assert np.allclose((e.reference_nodes[on] - origin) @ normal, 0.0), name  # nodes on the face plane


def test_simulator_public_hooks_match_the_assembled_stiffness():
    """The hooks benchmarks use (pattern, assemble_stiffness, new_vector, num_points) give the same
    matrix as stiffness_matrix(), and assembling twice into the same values doubles it."""
    import numpy as np

    import warpfem as wf

    mesh = wf.box_tet_mesh(size=(2.0, 1.0, 1.0), cells=(2, 1, 1))
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=100.0))
    sim = wf.Simulator(model, device="cpu", precision="float64")
    x = mesh.vertices * np.array([1.1, 0.95, 1.0])
    xa = sim.new_vector(x)
    K = sim.stiffness_matrix(x).toarray()
    vals = sim.assemble_stiffness(xa)
    np.testing.assert_allclose(sim.pattern.to_scipy(vals).toarray(), K, rtol=1e-12, atol=1e-9 * np.abs(K).max())
    sim.assemble_stiffness(xa, vals)
    np.testing.assert_allclose(sim.pattern.to_scipy(vals).toarray(), 2 * K, rtol=1e-12, atol=1e-9 * np.abs(K).max())
    assert sim.num_points == mesh.num_tets and sim.linear_solver is not None
