"""`warpfem describe` says what will actually run: the linear solver `auto` picks for the mesh size
(the one the built simulator then uses) and the colliders with the contact parameters the run
fills in (text and JSON)."""

import json

import pytest

from tiny_scenes import tiny_beam_toml
from warpfem.cli import main
from warpfem.scenes import load_scene

COLLIDERS = """
[[collider]]
type = "plane"
name = "floor"
point = [0.0, -0.5, 0.0]
friction = 0.3

[[collider]]
type = "sphere"
center = [0.5, -1.0, 0.1]
radius = 0.3
dhat = 0.01
translation = [0.0, 0.2, 0.0]
"""


def _scene(tmp_path, extra="", solver=None):
    text = tiny_beam_toml("plan", cells=4) + extra
    if solver:
        text = text.replace('type = "backward_euler"', f'type = "backward_euler"\nlinear_solver = "{solver}"')
    p = tmp_path / "plan.toml"
    p.write_text(text)
    return str(p)


def test_describe_names_the_solver_auto_will_run(tmp_path, capsys):
    path = _scene(tmp_path)
    assert main(["describe", path]) == 0
    text = capsys.readouterr().out
    # 60 unknowns on the CPU: auto factorises from the first solve (and says so, not "PCG")
    assert "Newton + block-Jacobi PCG" not in text
    assert "linear solver: auto" in text and "cpu: direct (sparse Cholesky" in text and "60 unknowns" in text
    assert "cuda: block-Jacobi PCG" in text
    run = load_scene(path).build(device="cpu")
    assert run.sim._pcg.active == "direct"  # what the built simulator really uses
    assert main(["describe", path, "--json"]) == 0
    plan = json.loads(capsys.readouterr().out)["integrator"]["linear_solver_plan"]
    assert plan["name"] == "auto" and plan["unknowns"] == 60 and plan["cpu"].startswith("direct")


def test_auto_choice_by_size(monkeypatch):
    from warpfem.solvers.linear import auto

    big = auto.describe_choice(auto.MULTIGRID_MIN_DOFS + 3)
    # the size rule: multigrid above its limit (pyamg is in the test extra) on both devices
    assert big["cpu"].startswith("multigrid-preconditioned CG") and big["cuda"].startswith("multigrid")
    assert auto.describe_choice(auto.SMALL_DIRECT_DOFS_CPU)["cpu"].startswith("direct")
    assert auto.describe_choice(auto.SMALL_DIRECT_DOFS_CPU)["cuda"] == "block-Jacobi PCG (the data stay on the device)"
    assert auto.describe_choice(auto.SMALL_DIRECT_DOFS_CPU + 3)["cuda"].startswith("block-Jacobi PCG; multigrid")
    mid = auto.SMALL_DIRECT_DOFS_CPU + 3  # between: PCG, multigrid past an iteration count
    assert f"more than {auto.switch_after_iterations(mid)} CG iterations" in auto.describe_choice(mid)["cpu"]
    monkeypatch.setattr(auto, "_multigrid_available", lambda: False)  # without pyamg: the same above the limit
    assert "; direct (sparse Cholesky" in auto.describe_choice(auto.MULTIGRID_MIN_DOFS + 3)["cpu"]


def test_describe_named_solver(tmp_path, capsys):
    assert main(["describe", _scene(tmp_path, solver="pcg")]) == 0
    text = capsys.readouterr().out
    assert "linear solver: pcg:" in text and "cpu: Block-Jacobi PCG" in text


def test_describe_lists_colliders_with_the_parameters_the_run_uses(tmp_path, capsys):
    path = _scene(tmp_path, COLLIDERS)
    assert main(["describe", path]) == 0
    text = capsys.readouterr().out
    assert "collider #1: plane 'floor', point [0.0, -0.5, 0.0], normal [0.0, 1.0, 0.0], friction 0.3" in text
    assert "collider #2: sphere 'sphere2', center [0.5, -1.0, 0.1], radius 0.3, friction 0" in text
    assert "dhat 0.01 m, barrier stiffness" in text and "moves by [0.0, 0.2, 0.0] m over the run" in text
    assert main(["describe", path, "--json"]) == 0
    cols = json.loads(capsys.readouterr().out)["colliders"]
    assert [c["type"] for c in cols] == ["plane", "sphere"] and cols[1]["radius"] == 0.3
    assert cols[0]["dhat_default"] and not cols[1]["dhat_default"] and cols[1]["moving"] and not cols[0]["moving"]
    # the defaults describe fills in are the ones the built run's contact set uses
    run = load_scene(path).build(device="cpu")
    contact = run.sim.contact
    for c, col in zip(cols, contact.colliders):
        dhat, kappa, epsv = contact.defaults(col)
        assert c["dhat"] == pytest.approx(dhat, rel=1e-12)
        assert c["stiffness"] == pytest.approx(kappa, rel=1e-9)
        assert c["friction_velocity"] == pytest.approx(epsv, rel=1e-12)
        assert c["friction"] == pytest.approx(col.friction)


def test_describe_reduced_scene_says_the_reduced_solve_and_the_training_run(tmp_path, capsys):
    path = _scene(tmp_path, "[subspace]\nmodes = 4\n")
    assert main(["describe", path]) == 0
    text = capsys.readouterr().out
    assert "builds: reduced basis U and cubature points (from the cache), reduced Hessian (dense r x r)" in text
    assert "linear solver: dense r x r (the reduced system); `warpfem train`'s full training run: auto" in text
    assert "cpu: direct (sparse Cholesky" in text
    assert main(["describe", path, "--json"]) == 0
    plan = json.loads(capsys.readouterr().out)["integrator"]["linear_solver_plan"]
    assert plan["name"] == "dense (reduced r x r)" and plan["training_run"]["unknowns"] == 60
