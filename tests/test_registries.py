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


_DISPATCH_HASH_SCRIPT = r"""
import dataclasses, json
from typing import Any
import warp as wp
wp.config.quiet = True
import warpfem.materials.dispatch as D
from warpfem.materials import registry as R
from warpfem.kernels import fem, subspace
from warpfem.materials.evaluate import evaluate_material_kernel

MODULES = ("warpfem.kernels.fem", "warpfem.kernels.subspace", "warpfem.materials.evaluate")
# evaluate's generic kernel enters its module hash once instantiated (as its first launch does)
wp.overload(evaluate_material_kernel, {"F": wp.array(dtype=wp.mat33d), "mu": wp.float64, "lam": wp.float64,
                                       "psi": wp.array(dtype=wp.float64), "P": wp.array(dtype=wp.mat33d),
                                       "H": wp.array3d(dtype=wp.float64), "Hp": wp.array3d(dtype=wp.float64)})
ORIGINAL = dict(R.MATERIAL_TYPES)


def hashes():
    D._psi_chain, D._pk1_chain, D._eigen_s_chain, D._eigen_f_chain = D._build()
    return [wp.get_module(m).hash_module().hex() for m in MODULES]


@wp.func
def linear_psi(F: Any, mu: Any, lam: Any):  # the key of the registered linear psi, another body
    return F.dtype(2.0) * mu * wp.ddot(F, F)


def edit(change):
    R.MATERIAL_TYPES.clear()
    R.MATERIAL_TYPES.update(ORIGINAL)
    t = dict(R.MATERIAL_TYPES)
    if change == "swap_psi":  # kind 0 evaluates another material's energy
        R.MATERIAL_TYPES["linear"] = dataclasses.replace(t["linear"], psi=t["stvk"].psi)
    elif change == "swap_kinds":
        R.MATERIAL_TYPES["stvk"] = dataclasses.replace(t["stvk"], kind=t["corotated"].kind)
        R.MATERIAL_TYPES["corotated"] = dataclasses.replace(t["corotated"], kind=t["stvk"].kind)
    elif change == "order":
        R.MATERIAL_TYPES.clear()
        R.MATERIAL_TYPES.update(dict(reversed(list(ORIGINAL.items()))))
    elif change == "drop":
        del R.MATERIAL_TYPES["stable_neo_hookean_log"]
    elif change == "body":
        assert t["linear"].psi.key == linear_psi.key
        R.MATERIAL_TYPES["linear"] = dataclasses.replace(t["linear"], psi=linear_psi)
    return hashes()


out = {"keys": [D._psi_chain.key, D._pk1_chain.key], "original": hashes()}
for change in ("swap_psi", "swap_kinds", "order", "drop", "body", "restored"):
    out[change] = edit(change)
print(json.dumps(out))
"""


def test_the_generated_material_dispatch_enters_the_kernel_module_hash(tmp_path):
    """Warp reuses a compiled module from its kernel cache (~/.cache/warp) when the module hash
    matches, so every change of the registry's dispatch (which function a kind calls, the kinds,
    their order, the set of materials, a material function's body under the same name) must change
    the hash of each module that compiles the dispatch, and the same registry must give the same
    hash again. Run in a subprocess: the registry is edited and the dispatch rebuilt."""
    import json
    import os
    import subprocess
    import sys

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    env = dict(os.environ, PYTHONPATH=root + os.pathsep + os.environ.get("PYTHONPATH", ""))
    script = tmp_path / "dispatch_hash.py"  # a file: Warp reads the source of the func it defines
    script.write_text(_DISPATCH_HASH_SCRIPT)
    res = subprocess.run([sys.executable, str(script)], cwd=root, env=env, capture_output=True, text=True, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    # the generated links are named after their material and kind (readable in the generated C++)
    assert out["keys"] == ["material_psi__stable_neo_hookean_k3", "material_pk1__stable_neo_hookean_k3"]
    assert out["restored"] == out["original"]
    changes = ("swap_psi", "swap_kinds", "order", "drop", "body")
    for i, module in enumerate(("kernels.fem", "kernels.subspace", "materials.evaluate")):
        seen = [out["original"][i]] + [out[c][i] for c in changes]
        assert len(set(seen)) == len(seen), f"warpfem.{module}: a registry change left the module hash unchanged"


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

    from warpfem.mesh.element_types import ELEMENTS

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
