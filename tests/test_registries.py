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


def test_kernel_parameters_are_named_apart_from_lame():
    """Stable neo-Hookean passes reparametrised (mu, lambda) to the kernels (Smith, de Goes & Kim
    2018, "Stable neo-Hookean flesh simulation": mu' = mu, lambda' = lambda + mu)."""
    from warpfem.materials import StableNeoHookean

    m = StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1.0)
    assert m.kernel_mu == pytest.approx(m.mu_lame) and m.kernel_lam == pytest.approx(m.lam_lame + m.mu_lame)
    assert (m.mu, m.lam) == (m.kernel_mu, m.kernel_lam)  # the aliases
