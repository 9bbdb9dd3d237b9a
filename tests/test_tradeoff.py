"""warpfem.tradeoff: Pareto frontier, errors against the reference, JSON round trip, CLI errors."""

import json
import math

import numpy as np
import pytest

from warpfem.tradeoff import (GridError, StudyResult, TradeoffConfig, TradeoffGrid, builtin_grid, format_table,
                              load_grid, load_study, pareto_front, run_study)

from tiny_scenes import tiny_beam_toml  # noqa: E402

BEAM = tiny_beam_toml("tiny_beam", cells=6, frames=3)


@pytest.fixture(scope="module")
def beam_path(tmp_path_factory):
    p = tmp_path_factory.mktemp("tradeoff") / "beam.toml"
    p.write_text(BEAM)
    return str(p)


def _ref():
    return TradeoffConfig(name="reference", precision="float64", tol=1e-10, max_iters=100, cg_tol=1e-10,
                          max_cg_iters=20000, substeps=4)


@pytest.fixture(scope="module")
def study(beam_path):
    ref = _ref()
    same = TradeoffConfig(**{**ref.as_dict(), "name": "same as reference", "subspace": None})
    loose = TradeoffConfig(name="f32 loose", precision="float32", tol=1e-3, cg_tol=1e-2, substeps=4)
    coarse = TradeoffConfig(name="one step", precision="float64", tol=1e-10, cg_tol=1e-10, max_cg_iters=20000, substeps=1)
    bogus = TradeoffConfig(name="bogus integrator", integrator="no_such_integrator")
    grid = TradeoffGrid(configs=[same, loose, coarse, bogus], reference=ref, frames=3)
    return run_study(beam_path, grid, device="cpu", quantity="tip")


# ----------------------------------------------------------------------------- Pareto
def test_pareto_front_hand_made_points():
    t = [1.0, 2.0, 3.0, 4.0, 2.0, math.nan, 0.5, 5.0]
    e = [5.0, 3.0, 4.0, 1.0, 3.0, 0.1, math.inf, 1.0]
    # (3, 4) dominated by (2, 3); (5, 1) dominated by (4, 1); nan / inf never on the front;
    # the duplicate (2, 3) points do not dominate each other
    assert pareto_front(t, e) == [0, 1, 4, 3]
    assert pareto_front([1.0], [1.0]) == [0]
    assert pareto_front([], []) == []
    with pytest.raises(ValueError):
        pareto_front([1.0, 2.0], [1.0])


# ----------------------------------------------------------------------------- errors
def test_reference_against_itself_has_zero_error(study):
    by = {r.name: r for r in study.results}
    for r in (study.reference, by["same as reference"]):
        assert r.status == "ok"
        assert r.rms_error <= 1e-14 and r.tip_error <= 1e-14 and r.surface_error <= 1e-14
        assert r.energy_error <= 1e-12
    assert study.tip["peak_displacement_m"] > 1e-3  # the beam does move


def test_loose_float32_error_positive_and_bounded(study):
    by = {r.name: r for r in study.results}
    loose, coarse = by["f32 loose"], by["one step"]
    assert loose.status == "ok" and coarse.status == "ok"
    # tolerance / precision error at the reference's time step: nonzero, small
    assert 0.0 < loose.rms_error < 1e-3
    assert 0.0 < loose.tip_error < 0.05
    # the time-step error of 1 step per frame (4x the reference's dt) dominates the tolerances
    assert coarse.tip_error > 10 * loose.tip_error
    assert coarse.rms_error > 10 * loose.rms_error
    # backward Euler with a 4x larger step dissipates more energy than the reference
    assert coarse.energy_drift < study.reference.energy_drift
    assert coarse.newton_per_step >= 1 and coarse.cg_per_step > 0


def test_unavailable_variant_is_skipped_with_a_note(study):
    bogus = {r.name: r for r in study.results}["bogus integrator"]
    assert bogus.status == "skipped"
    assert "not available" in bogus.note and "no_such_integrator" in bogus.note
    assert "bogus integrator" in format_table(study)


def test_frontier_is_the_non_dominated_set(study):
    ok = study.ok_results()
    idx = pareto_front([r.seconds_per_sim_second for r in ok], [r.tip_error for r in ok])
    assert sorted(study.frontier) == sorted(ok[i].name for i in idx)
    assert all(r.on_frontier == (r.name in study.frontier) for r in ok)


def test_json_round_trip(study, tmp_path):
    p = tmp_path / "study.json"
    study.to_json(p)
    data = json.loads(p.read_text())  # strict JSON: no NaN
    assert data["schema"] == "warpfem.tradeoff/1"
    assert {"seconds_per_sim_second", "newton_per_step", "cg_per_step", "rms_error", "tip_error", "energy_error",
            "energy_drift", "status", "config"} <= set(data["results"][0])
    back = load_study(p)
    assert back.to_dict() == study.to_dict()
    # no path of this machine: the scene (in the temporary folder here) is recorded by its file name
    assert data["scene"] == "<tmp>/beam.toml" and str(tmp_path.parent.parent) not in p.read_text()
    assert [r.name for r in back.results] == [r.name for r in study.results]
    data["schema"] = "something else"
    with pytest.raises(ValueError, match="schema"):
        StudyResult.from_dict(data)


def test_tip_point_matches_the_tip_vertex(beam_path, study):
    grid = TradeoffGrid(configs=[TradeoffConfig(name="f32 loose", precision="float32", tol=1e-3, cg_tol=1e-2, substeps=4)],
                        reference=_ref(), frames=3)
    s2 = run_study(beam_path, grid, tip_point=tuple(study.tip["point"]))
    assert s2.tip["peak_displacement_m"] == pytest.approx(study.tip["peak_displacement_m"], rel=1e-12)
    assert s2.results[0].tip_error == pytest.approx({r.name: r for r in study.results}["f32 loose"].tip_error, rel=1e-9)


# ----------------------------------------------------------------------------- grids
def test_grid_file(tmp_path):
    p = tmp_path / "g.toml"
    p.write_text('frames = 2\ntip_point = [1.0, 0.2, 0.2]\n[reference]\nsubsteps = 6\n'
                 '[axes]\nprecision = ["float32", "float64"]\ntol = [1e-3, 1e-5, 1e-7]\n'
                 '[[config]]\nname = "mine"\ncg_tol = 0.01\n[config.subspace]\nmodes = 10\n')
    g = load_grid(p)
    assert len(g.configs) == 7 and g.frames == 2 and g.tip_point == (1.0, 0.2, 0.2)
    assert g.reference.substeps == 6 and g.reference.precision == "float64"
    assert g.configs[-1].subspace_dict() == {"modes": 10}
    p.write_text('base = "quick"\nexclude = ["f32"]\n')
    assert "f32" not in [c.name for c in load_grid(p).configs]
    assert len(load_grid(p).configs) == len(builtin_grid("quick").configs) - 1
    for bad, what in (('colour = 1\n', "colour"), ('[[config]]\ntol = 2.0\n', "tol"),
                      ('[[config]]\nprecision = "float16"\n', "precision"), ('[[config]]\nsubsteps = 0\n', "substeps"),
                      ('base = "medium"\n', "medium"), ('[[config]]\ntoll = 1e-3\n', "toll")):
        p.write_text(bad)
        with pytest.raises(GridError, match=what):
            load_grid(p)


def test_cli_exit_codes(beam_path, tmp_path, capsys):
    from warpfem.cli import main

    assert main(["tradeoff", str(tmp_path / "missing.toml")]) == 2
    assert "not found" in capsys.readouterr().err
    bad_scene = tmp_path / "bad.toml"
    bad_scene.write_text(BEAM.replace("youngs_modulus", "youngs_modulu"))
    assert main(["tradeoff", str(bad_scene)]) == 2
    assert "youngs_modulu" in capsys.readouterr().err
    bad_grid = tmp_path / "grid.toml"
    bad_grid.write_text("[axes]\ntol = [5.0]\n")
    assert main(["tradeoff", beam_path, "--grid", str(bad_grid)]) == 2
    assert "tol" in capsys.readouterr().err
    assert main(["tradeoff", beam_path, "--grid", "nosuchgrid"]) == 2
    assert main(["tradeoff", beam_path, "--frames", "0"]) == 2
    assert main(["tradeoff", beam_path, "--json", "out.txt"]) == 2
    assert main(["tradeoff", beam_path, "--skip", "no such config"]) == 2
    assert main(["tradeoff", beam_path, "--list"]) == 0
    assert "f32" in capsys.readouterr().out.split()


def test_pareto_plot(study, tmp_path, monkeypatch):
    import sys

    from warpfem.tradeoff import plot_pareto

    monkeypatch.setitem(sys.modules, "matplotlib", None)  # as if not installed: a clear message
    with pytest.raises(ImportError, match=r"warpfem\[plot\]"):
        plot_pareto(study, tmp_path / "x.png")
    monkeypatch.undo()
    pytest.importorskip("matplotlib")
    out = plot_pareto(study, tmp_path / "front.png")
    png = open(out, "rb").read()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 10_000


def test_element_variant_compared_through_its_shape_functions(beam_path):
    """A variant with another vertex set (Tet10: + edge mid-nodes) is sampled at the reference's
    vertices through its own elements; identical settings on the same element give zero error."""
    ref = TradeoffConfig(name="reference", tol=1e-9, cg_tol=1e-9, max_cg_iters=20000, substeps=2)
    t10 = TradeoffConfig(**{**ref.as_dict(), "name": "tet10", "element": "tet10", "subspace": None})
    s = run_study(beam_path, TradeoffGrid(configs=[t10], reference=ref, frames=1))
    r = s.results[0]
    assert r.status == "ok", r.note
    assert r.settings["element"] == "tet10" and r.settings["vertices"] > 28
    # Tet4 on one cell through the thickness locks: the quadratic element differs, by a bounded amount
    assert 1e-3 < r.tip_error < 0.5 and 0 < r.rms_error < 0.05
    s10 = run_study(beam_path, TradeoffGrid(configs=[t10], reference=TradeoffConfig(**{**t10.as_dict(), "name": "reference", "subspace": None}), frames=1))
    assert s10.results[0].rms_error <= 1e-14 and s10.results[0].tip_error <= 1e-14


def test_set_quantity_recomputes_the_frontier(study, tmp_path):
    from warpfem.tradeoff import set_quantity

    s = load_study(study.to_json(tmp_path / "s.json"))
    set_quantity(s, "rms")
    ok = s.ok_results()
    idx = pareto_front([r.seconds_per_sim_second for r in ok], [r.rms_error for r in ok])
    assert s.quantity == "rms" and sorted(s.frontier) == sorted(ok[i].name for i in idx)
    assert sum(r.on_frontier for r in s.results) == len(idx)
    with pytest.raises(GridError):
        set_quantity(s, "colour")


def test_recorded_settings_hold_no_machine_path(tmp_path):
    """A reduced variant's subspace cache lives in a temporary folder: the result records it portably."""
    from warpfem.tradeoff.runner import _recorded_subspace

    rec = _recorded_subspace({"modes": 20, "cache": str(tmp_path / "run" / "subspace_modes20.npz")})
    assert rec == {"modes": 20, "cache": "<tmp>/subspace_modes20.npz"}
    assert _recorded_subspace(None) is None
