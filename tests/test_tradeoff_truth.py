"""The study's converged reference: a refined higher-order mesh and a time-step ladder; every
error split into discretisation and solver/step parts; mesh files fall back, flagged."""

import math

import numpy as np
import pytest

from warpfem.tradeoff import GridError, TradeoffConfig, TradeoffGrid, TruthSpec, load_grid, run_study
from warpfem.tradeoff.study import format_table

from tiny_scenes import tiny_beam_toml  # noqa: E402

BEAM = tiny_beam_toml("thin_beam", cells=4, frames=2)

REF = TradeoffConfig(name="reference", tol=1e-9, cg_tol=1e-9, max_iters=100, max_cg_iters=20000, substeps=2)


@pytest.fixture(scope="module")
def beam_path(tmp_path_factory):
    p = tmp_path_factory.mktemp("truth") / "beam.toml"
    p.write_text(BEAM)
    return str(p)


@pytest.fixture(scope="module")
def study(beam_path):
    tight = TradeoffConfig(**{**REF.as_dict(), "name": "tight tet4", "subspace": None})
    tet10 = TradeoffConfig(**{**REF.as_dict(), "name": "tight tet10", "element": "tet10", "subspace": None})
    truth_mesh = TradeoffConfig(**{**REF.as_dict(), "name": "on the reference mesh", "element": "tet10", "refine": 2,
                                   "substeps": 4, "subspace": None})
    coarse = TradeoffConfig(name="scene settings")
    grid = TradeoffGrid(configs=[tight, tet10, truth_mesh, coarse], reference=REF, frames=2,
                        truth=TruthSpec(refine=2, substeps=4))
    return run_study(beam_path, grid)


def test_reference_ladder_and_space_check(study):
    t = study.truth
    assert t["kind"] == "converged" and not t["flag"]
    assert t["time"]["substeps"] == [4, 2, 1]
    assert 0.6 < t["time"]["observed_order_tip"] < 1.4  # backward Euler: first order in dt
    # the extrapolated reference is more accurate than the difference of its two finest steps
    assert t["time"]["estimated_error_tip"] < t["time"]["difference_tip"][0]
    assert 0 < t["space"]["difference_tip"] < 0.2
    assert study.reference.config["element"] == "tet10" and study.reference.config["refine"] == 2
    assert "reference: converged" in format_table(study)


def test_locking_tet4_has_the_larger_discretisation_error(study):
    by = {r.name: r for r in study.results}
    t4, t10 = by["tight tet4"], by["tight tet10"]
    # one Tet4 cell through the thickness locks; the quadratic element does not
    assert t4.discretisation_tip_error > 3 * t10.discretisation_tip_error
    assert t4.discretisation_rms_error > 3 * t10.discretisation_rms_error
    # at 2 substeps per frame the time-step error is the larger part of both totals: ranking
    # elements by the total alone would hide the locking (this is what the split is for)
    assert t10.solver_tip_error > t10.discretisation_tip_error


def test_split_bounds_the_total(study):
    for r in study.ok_results():
        for q in ("tip", "rms"):
            total, d, s = getattr(r, f"{q}_error"), getattr(r, f"discretisation_{q}_error"), getattr(r, f"solver_{q}_error")
            assert total <= d + s + 1e-12, (r.name, q)  # triangle / Minkowski inequality
            assert total >= abs(d - s) - 1e-12, (r.name, q)


def test_run_on_the_reference_mesh_has_no_discretisation_error(study):
    r = {r.name: r for r in study.results}["on the reference mesh"]
    assert r.discretisation_tip_error == 0.0 and r.discretisation_rms_error == 0.0
    assert r.solver_tip_error == pytest.approx(r.tip_error, rel=1e-12)
    # it is the reference's own finest step: its error is the extrapolation's correction
    assert r.tip_error == pytest.approx(study.reference.tip_error, rel=1e-9)
    assert r.tip_error > 0


def test_coarse_step_error_is_mostly_time_step(study):
    r = {r.name: r for r in study.results}["scene settings"]  # one step per frame
    assert r.solver_tip_error > r.discretisation_tip_error > 0


def test_mesh_file_falls_back_flagged(tmp_path):
    import meshio

    from warpfem.tradeoff.study import scene_document, variant_scene

    box = tmp_path / "box.toml"
    box.write_text(BEAM)
    mesh = variant_scene(scene_document(box), str(box), TradeoffConfig(name="x")).mesh()
    meshio.write(tmp_path / "beam.vtu", meshio.Mesh(np.asarray(mesh.vertices), [("tetra", np.asarray(mesh.elements))]))
    scene = tmp_path / "file.toml"
    scene.write_text(BEAM.replace('generator = "box"\nsize = [1.0, 0.2, 0.2]\ncells = [4, 1, 1]', 'path = "beam.vtu"'))
    grid = TradeoffGrid(configs=[TradeoffConfig(name="scene settings")], reference=REF, frames=1,
                        truth=TruthSpec(refine=2, substeps=2))
    s = run_study(str(scene), grid)
    assert "cannot be refined" in s.truth["flag"] and s.truth["kind"] != "converged"
    assert s.reference.config["element"] == "tet4" and s.reference.config["refine"] is None
    r = s.results[0]
    assert r.status == "ok" and r.tip_error > 0
    assert math.isnan(r.discretisation_tip_error) and math.isnan(r.solver_tip_error)
    assert "cannot be refined" in format_table(s)


def test_grid_file_truth_table(tmp_path):
    p = tmp_path / "g.toml"
    p.write_text('[truth]\nrefine = 3\nsubsteps = 16\nelement = "hex27"\n[[config]]\nname = "a"\n')
    g = load_grid(p)
    assert g.truth == TruthSpec(element="hex27", refine=3, substeps=16)
    p.write_text('truth = false\n[[config]]\nname = "a"\n')
    assert load_grid(p).truth is None
    p.write_text('[[config]]\nname = "a"\n')
    assert load_grid(p).truth == TruthSpec()  # grid files default to the converged reference
    for bad, what in (('[truth]\nrefine = 0\n', "refine"), ('[truth]\nelement = "tet20"\n', "element"),
                      ('[truth]\nsize = 2\n', "size"), ('truth = 3\n', "truth")):
        p.write_text(bad + '[[config]]\nname = "a"\n')
        with pytest.raises(GridError, match=what):
            load_grid(p)
