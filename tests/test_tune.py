"""warpfem tune on the cantilever: the configuration chosen for an error budget meets it when its
written scene file is rerun, a looser budget never picks a costlier configuration, and the search
space follows the registries (integrators, elements, optional linear_solver)."""

import math
import os
try:
    import tomllib
except ModuleNotFoundError:  # Python 3.10
    import tomli as tomllib

import pytest

from tiny_scenes import tiny_beam_toml
from warpfem.tradeoff import TradeoffConfig, TruthSpec, scene_document
from warpfem.tradeoff.grid import _cfg, _REFERENCE
from warpfem.tradeoff.study import finish_reference, make_job, plan_reference, run_job
from warpfem.tradeoff.tune import rerun_error, search_space, toml_dumps, tune, write_scene

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CANTILEVER = os.path.join(ROOT, "examples", "scenes", "cantilever.toml")
FRAMES = 3
# small space (the default one is larger): both registered dynamic integrators, two elements
AXES = {"element": ["tet4", "tet10"], "substeps": [1, 2, 4], "tol": [1e-3], "cg_tol": [1e-2],
        "precision": ["float32", "float64"]}
TRUTH = TruthSpec(refine=1, substeps=8)  # Tet10 on the scene's cells (within 0.2 % of Timoshenko), dt ladder 8/4/2


@pytest.fixture(scope="module")
def reference():
    """The converged reference, computed once and shared by both searches."""
    from warpfem.scenes import load_scene

    doc = scene_document(CANTILEVER)
    base = load_scene(CANTILEVER)
    cands, _ = search_space(doc, CANTILEVER, AXES)
    plan = plan_reference(doc, CANTILEVER, base, _cfg(**_REFERENCE, substeps=4), TRUTH, cands)
    outs = [run_job(make_job(doc, CANTILEVER, c, device="cpu", frames=FRAMES, plan=plan)) for c in plan["jobs"]]
    return finish_reference(plan, outs, frames=FRAMES)


@pytest.fixture(scope="module")
def results(reference):
    # cost = work: the deterministic proxy (Newton / CG iterations x element work), so that the
    # comparison between the two budgets does not depend on the load of this shared machine
    return {e: tune(CANTILEVER, e, frames=FRAMES, axes=AXES, reference=reference, cost="work") for e in (0.25, 0.06)}


def test_reference_is_converged_in_time(reference):
    t = reference.info["time"]
    assert t["substeps"] == [8, 4, 2]
    assert 0.7 < t["observed_order_tip"] < 1.3  # backward Euler: first order in dt
    assert t["estimated_error_tip"] < 0.01  # the Richardson reference, well below the budgets tested


@pytest.mark.parametrize("budget", [0.25, 0.06])
def test_chosen_configuration_meets_its_budget_when_rerun(results, reference, budget, tmp_path):
    r = results[budget]
    assert r.winner is not None, r.notes
    assert r.winner["error"] <= budget
    path = write_scene(r, tmp_path / "tuned.toml")
    with open(path, "rb") as f:
        doc = tomllib.load(f)  # a valid TOML scene with the chosen settings
    cfg = r.winner_config()
    assert doc["integrator"]["type"] == (cfg.integrator or "backward_euler")
    assert doc["mesh"]["element"] == (cfg.element or "tet4")
    assert doc["integrator"]["dt"] == pytest.approx(1.0 / (48 * (cfg.substeps or 1)))
    err = rerun_error(path, reference, precision=cfg.precision)
    assert err <= budget
    assert err == pytest.approx(r.winner["error"], rel=1e-3, abs=1e-6)  # the same run, read back from the file


def test_looser_budget_is_not_costlier(results):
    loose, tight = results[0.25], results[0.06]
    assert loose.winner["config"] == tight.winner["config"] or loose.winner["work"] <= tight.winner["work"]
    assert loose.winner["error"] <= 0.25 and tight.winner["error"] <= 0.06
    # the tight budget needs smaller steps than one per frame (backward Euler's error is O(dt))
    assert (TradeoffConfig.from_dict(tight.winner["config"]).substeps or 1) >= 2
    for r in (loose, tight):  # every runner-up that met the budget costs at least as much as the winner
        for x in r.runners_up:
            if x["status"] == "ok" and x["error"] <= r.max_error:
                assert x["work"] >= r.winner["work"]
        # no whole grid: fewer run-frames than every candidate over every frame
        assert r.search["frame_runs"] < r.search["whole_grid_frame_runs"]


def test_recorded_paths_are_repository_relative(results, tmp_path):
    """A TuneResult's JSON names the scene relative to the repository (no path of this machine), and
    one read back from that JSON still finds the scene file to write the winner."""
    import json

    from warpfem.tradeoff.tune import TuneResult

    r = results[0.25]
    assert r.scene == "examples/scenes/cantilever.toml" and r.scene_file() == CANTILEVER
    assert ROOT not in json.dumps(r.to_dict())
    back = TuneResult(**json.loads(json.dumps(r.to_dict())))
    assert back.scene_file() == CANTILEVER
    write_scene(back, tmp_path / "again.toml")
    assert back.scene_out == "<tmp>/again.toml"
    with open(tmp_path / "again.toml", "rb") as f:
        assert tomllib.load(f)["mesh"]["element"] == (back.winner_config().element or "tet4")


def test_search_space_follows_the_registries(monkeypatch):
    import warpfem.scenes.schema as schema
    from warpfem.scenes import INTEGRATORS, Key

    doc = scene_document(CANTILEVER)
    cands, dropped = search_space(doc, CANTILEVER, {"substeps": [1], "tol": [1e-3], "cg_tol": [1e-2], "precision": ["float64"]},
                                  space="full")
    integrators = {c.integrator for c in cands}
    assert integrators == {n for n, e in INTEGRATORS.items() if e.dynamic}
    # stiffness warping takes Tet4 only: its other elements are rejected by the scene layer
    assert {c.element for c in cands if c.integrator == "stiffness_warping"} == {"tet4"}
    assert {c.element for c in cands if c.integrator == "backward_euler"} == {"tet4", "tet10", "hex8", "hex27"}
    assert any("warping" in name and "tet10" in name for name, _ in dropped)
    if "linear_solver" in schema.INTEGRATOR_KEYS:  # the axis is on: every choice for the integrators that take it
        choices = set(schema.INTEGRATOR_KEYS["linear_solver"].choices)
        assert {c.linear_solver for c in cands if c.integrator == "backward_euler"} == choices
    else:
        assert all(c.linear_solver is None for c in cands)
    # a schema with [integrator] linear_solver turns the axis on, for the integrators that take it
    if "linear_solver" not in schema.INTEGRATOR_KEYS:
        monkeypatch.setitem(schema.INTEGRATOR_KEYS, "linear_solver",
                            Key("choice", default="auto", choices=("auto", "pcg", "direct")))
        be = INTEGRATORS["backward_euler"]
        monkeypatch.setitem(be.keys, "linear_solver", schema.INTEGRATOR_KEYS["linear_solver"])
    cands2, _ = search_space(doc, CANTILEVER, {"substeps": [1], "tol": [1e-3], "cg_tol": [1e-2], "precision": ["float64"],
                                               "element": ["tet4"]}, space="full")
    solvers = {c.linear_solver for c in cands2 if c.integrator == "backward_euler"}
    assert solvers == set(schema.INTEGRATOR_KEYS["linear_solver"].choices)


def test_toml_writer_round_trip():
    doc = scene_document(CANTILEVER)
    back = tomllib.loads(toml_dumps(doc))
    assert back == doc


def test_bad_budget_and_cli_errors(tmp_path, capsys):
    from warpfem.cli import main
    from warpfem.tradeoff import GridError

    with pytest.raises(GridError, match="max error"):
        tune(CANTILEVER, 0.0)
    with pytest.raises(GridError, match="quantity"):
        tune(CANTILEVER, 0.1, quantity="energy")
    assert main(["tune", CANTILEVER, "--max-error", "-1"]) == 2
    assert "--max-error" in capsys.readouterr().err
    assert main(["tune", str(tmp_path / "missing.toml"), "--max-error", "0.1"]) == 2
    bad = tmp_path / "space.toml"
    bad.write_text("colour = [1]\n")
    assert main(["tune", CANTILEVER, "--max-error", "0.1", "--space", str(bad)]) == 2
    assert "colour" in capsys.readouterr().err
    assert main(["tune", CANTILEVER, "--max-error", "0.1", "--out", "x.txt"]) == 2
    assert math.isfinite(0.1)


def test_default_space_is_small_and_full_space_is_on_request():
    """A plain `warpfem tune` searches the registered dynamic integrators on the scene's element and
    its higher-order partner, 1/2/4 substeps, float64 (21 candidates on the cantilever: minutes);
    `--space full` is the old space (1,600 candidates on the cantilever)."""
    from warpfem.scenes import INTEGRATORS
    from warpfem.tradeoff.tune import space_axes

    doc = scene_document(CANTILEVER)
    cands, _ = search_space(doc, CANTILEVER)
    assert len(cands) == 21
    assert {c.element for c in cands} == {"tet4", "tet10"} and {c.substeps for c in cands} == {1, 2, 4}
    assert {c.precision for c in cands} == {"float64"} and {c.linear_solver for c in cands} == {None}
    assert {c.integrator for c in cands} == {n for n, e in INTEGRATORS.items() if e.dynamic}
    assert space_axes("default", {"mesh": {"element": "hex8"}})["element"] == ["hex8", "hex27"]
    full, _ = search_space(doc, CANTILEVER, space="full")
    assert len(full) >= 1600 and {c.element for c in full} == {"tet4", "tet10", "hex8", "hex27"}


def test_run_count_up_front_and_progress_per_stage(tmp_path):
    from warpfem.tradeoff.tune import format_plan, plan_runs

    # the cantilever's default search at 48 frames: 7 reference runs, 21 + 7 prefix runs, 3 full runs
    plan = plan_runs(21, 48, reference_runs=7)
    assert plan["stages"] == [("reference", 48, 7), ("prefix", 6, 21), ("prefix", 12, 7), ("full", 48, 3)]
    assert plan["runs"] == 38 and plan["run_frames"] == 7 * 48 + 21 * 6 + 7 * 12 + 3 * 48
    assert format_plan(plan).startswith("search plan: 21 candidates; at most 38 runs (690 run-frames): 7 reference")
    # a real (tiny) search: the plan line comes before any run, every run logs its stage's progress
    path = tmp_path / "tiny.toml"
    path.write_text(tiny_beam_toml("tiny", cells=2, frames=2))
    cands = [_cfg(integrator="backward_euler", substeps=s, tol=1e-3) for s in (1, 2)]
    lines = []
    res = tune(str(path), 0.5, candidates=cands, truth=None, keep=1, cost="work", log=lines.append)
    first_run = next(i for i, ln in enumerate(lines) if "1/" in ln)
    plan_line = next(i for i, ln in enumerate(lines) if ln.startswith("search plan: 2 candidates; at most"))
    assert plan_line < first_run
    planned = int(lines[plan_line].split("at most ")[1].split(" runs")[0])
    done = res.search["candidates_run"]
    assert done["reference"] + done["prefix"] + done["full"] <= planned == res.search["planned"]["runs"]
    progress = [ln for ln in lines if "ETA" in ln]
    assert len(progress) == done["reference"] + done["prefix"] + done["full"]
    assert any(ln.strip().startswith("prefix of 1 frame(s) 2/2:") for ln in progress)
    from warpfem.cli import main

    assert main(["tune", CANTILEVER, "--max-error", "0.1", "--space", "fulll"]) == 2  # neither a space nor a .toml


def test_stage_eta_weighs_the_runs_left(monkeypatch):
    """The reference stage starts with its costliest run: the ETA scales the time per unit of
    estimated cost (steps x element nodes x refine^3), not per run."""
    import warpfem.tradeoff.tune as tune_mod

    clock = iter([100.0, 108.0, 110.0])
    monkeypatch.setattr(tune_mod.time, "perf_counter", lambda: next(clock))
    ref = _cfg(element="tet10", refine=2, substeps=8)
    assert tune_mod._run_weight(ref, {"mesh": {"element": "tet4"}}) == 8 * 10 * 8
    lines = []
    stage = tune_mod._Stage(lines.append, "reference", [8.0, 4.0, 2.0, 2.0])
    stage.done(0, "finest")  # 8 s for 8 of 16 units: 8 s left
    stage.done(1, "next")  # 10 s for 12 units: 3.33 s left
    assert lines[0] == "reference: 4 run(s)"
    assert lines[1].endswith("1/4: finest  elapsed 0:00:08  ETA 0:00:08")
    assert lines[2].endswith("2/4: next  elapsed 0:00:10  ETA 0:00:03")


CUBE_OBJ = "\n".join(["v 0 0 0", "v 1 0 0", "v 1 1 0", "v 0 1 0", "v 0 0 1", "v 1 0 1", "v 1 1 1", "v 0 1 1",
                      "f 1 3 2", "f 1 4 3", "f 5 6 7", "f 5 7 8", "f 1 2 6", "f 1 6 5", "f 2 3 7", "f 2 7 6",
                      "f 3 4 8", "f 3 8 7", "f 4 1 5", "f 4 5 8"]) + "\n"


def _cube_scene(folder):
    """A tiny scene read from a surface file (tetrahedralised through the cache) with a relative
    USD output: scenes/cube.toml under ``folder``."""
    scenes = folder / "scenes"
    scenes.mkdir(parents=True)
    (scenes / "cube.obj").write_text(CUBE_OBJ)
    beam = tiny_beam_toml("cube", frames=2)  # the tiny beam's material, solver and output, the cube's mesh
    text = (beam.replace('generator = "box"\nsize = [1.0, 0.2, 0.2]\ncells = [4, 1, 1]', 'path = "cube.obj"\nmax_edge_length = 0.5')
            .replace("box_max = [0.0, 1.0, 1.0]", "box_max = [0.1, 2.0, 2.0]") + 'usd = "out/cube.usda"\n')
    assert 'path = "cube.obj"' in text and "box_max = [0.1, 2.0, 2.0]" in text
    (scenes / "cube.toml").write_text(text)
    return scenes / "cube.toml"


def test_cli_report_label_paths_and_outputs(tmp_path, monkeypatch, capsys):
    """`warpfem tune` run from one folder on a scene in another: backward Euler is named
    backward_euler (not after its Newton solver), the tuned scene's path is printed as typed, its
    input paths still find the scene's mesh, and its [output] paths, relative to the folder it is
    run from like the original's, write where the original would (run from the folder tune ran in)."""
    from warpfem.cli import main
    from warpfem.scenes import load_scene

    monkeypatch.setenv("WARPFEM_CACHE_DIR", str(tmp_path / "cache"))
    scene = _cube_scene(tmp_path)
    (tmp_path / "space.toml").write_text('integrator = ["backward_euler"]\nelement = ["tet4"]\nsubsteps = [1, 2]\n')
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    monkeypatch.chdir(run_dir)
    code = main(["tune", os.path.join("..", "scenes", "cube.toml"), "--max-error", "0.5", "--space",
                 os.path.join("..", "space.toml"), "--no-truth", "--cost", "work", "--quiet",
                 "--out", os.path.join("tuned", "cube.tuned.toml")])
    out = capsys.readouterr().out
    assert code == 0, out
    assert "newton" not in out and "sub=1 backward_euler tet4" in out
    assert f"wrote {os.path.join('tuned', 'cube.tuned.toml')}\n" in out  # as typed, not <tmp>/...
    tuned = run_dir / "tuned" / "cube.tuned.toml"
    with open(tuned, "rb") as f:
        doc = tomllib.load(f)
    assert doc["integrator"]["type"] == "backward_euler"
    # the mesh (an input: relative to the scene file) is the original's
    assert os.path.realpath(tuned.parent / doc["mesh"]["path"]) == os.path.realpath(scene.parent / "cube.obj")
    # the outputs (relative to the folder it is run from): the original's, unchanged
    assert doc["output"]["usd"] == "out/cube.usda"
    assert os.path.realpath(load_scene(str(tuned)).spec.output["usd"]) == os.path.realpath(
        load_scene(str(scene)).spec.output["usd"])
    assert main(["run", os.path.join("tuned", "cube.tuned.toml"), "--frames", "1", "--quiet"]) == 0
    assert (run_dir / "out" / "cube.usda").is_file()  # where `warpfem run ../scenes/cube.toml` writes
    assert not (tmp_path / "scenes" / "out").exists() and not (run_dir / "tuned" / "out").exists()


def test_cache_hit_line_once_with_a_count(tmp_path, monkeypatch, caplog):
    """Every run of a search reads the scene's tetrahedralised mesh: the cache-hit line is logged
    once per search (the first meshes the surface, a second identical one finds it cached), with
    the number of reads from the cache."""
    import logging

    import warpfem.mesh.tetrahedralization as tetra

    monkeypatch.setenv("WARPFEM_CACHE_DIR", str(tmp_path / "cache"))
    read = tetra._read_cache
    reads = []

    def counted(entry):
        hit = read(entry)
        reads.append(hit is not None)
        return hit

    monkeypatch.setattr(tetra, "_read_cache", counted)
    scene = str(_cube_scene(tmp_path))
    cands = [_cfg(integrator="backward_euler", substeps=s, tol=1e-3) for s in (1, 2)]
    caplog.set_level(logging.INFO, logger="warpfem")
    for search in range(2):
        caplog.clear()
        reads.clear()
        tune(scene, 0.5, candidates=cands, truth=None, keep=1, cost="work")
        hits = [r.getMessage() for r in caplog.records if "cache hit" in r.getMessage()]
        assert len(hits) == 1, hits
        assert hits[0].endswith(f"({sum(reads)} times)")
        assert sum(reads) >= 4  # the reference, prefix and full runs each read it
        assert reads[0] == (search == 1)  # the first search meshed the surface, the second found it cached


def test_runner_up_over_budget_is_marked(tmp_path):
    """The table says what the budget was, and a runner-up whose full run missed it says so."""
    import dataclasses

    from warpfem.tradeoff.tune import format_tune

    path = tmp_path / "tiny.toml"
    path.write_text(tiny_beam_toml("tiny", cells=2, frames=2))
    cands = [_cfg(integrator="backward_euler", substeps=s, tol=1e-3) for s in (1, 2)]
    res = tune(str(path), 0.5, candidates=cands, truth=None, keep=2, cost="work")
    assert res.winner is not None and res.runners_up
    over = dict(res.runners_up[0], error=0.75, name="over one")
    text = format_tune(dataclasses.replace(res, runners_up=[over]))
    header = next(ln for ln in text.splitlines() if ln.lstrip().startswith("configuration"))
    assert header.rstrip().endswith("budget: tip err <= 0.5")
    row = next(ln for ln in text.splitlines() if "over one" in ln)
    assert "0.75" in row and row.rstrip().endswith("over budget")
    assert next(ln for ln in text.splitlines() if ln.lstrip().startswith("winner")).rstrip().endswith("within")
    # an absolute --out is printed absolute (the JSON keeps its portable form)
    write_scene(res, str(tmp_path / "abs.tuned.toml"))
    assert f"wrote {tmp_path / 'abs.tuned.toml'}" in format_tune(res).splitlines()
    assert res.scene_out == "<tmp>/abs.tuned.toml"
