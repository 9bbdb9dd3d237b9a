"""Convergence reports agree with the documented tolerance: a step is converged exactly when its
relative gradient (||P g|| over the gradient at the step's start, friction's lag updates included) is
<= tol; a scene run counts the steps that are not, and ``require_convergence`` makes one an error."""

import json
import logging
import textwrap
import warnings
from dataclasses import replace

import numpy as np
import pytest
import warp as wp

import warpfem as wf
import warpfem.simulator as simulator_module
from warpfem.cli import main
from warpfem.solvers.nonlinear import NotConvergedWarning, newton_solve

from tiny_scenes import cli_beam_toml


def beam_sim(**kw):
    """A 4-cell clamped Tet4 beam under gravity (the command-line tests' beam), backward Euler."""
    mesh = wf.box_tet_mesh(size=(1.0, 0.2, 0.2), cells=(4, 1, 1))
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
                     gravity=(0.0, -9.81, 0.0))
    model.fix(wf.select_vertices_in_box(mesh, (-1.0, -1.0, -1.0), (0.0, 1.0, 1.0)))
    return wf.Simulator(model, dt=0.025, **kw)


# ------------------------------------------------------------------ (a) friction lagged inside the solve
def test_friction_lag_update_keeps_one_solve_held_to_the_steps_start_gradient(monkeypatch):
    """A block thrown sideways onto a plane with friction: friction is lagged again inside the step's
    one Newton solve (no re-solve), the step's residual is ||g|| over the gradient at its start, and it
    is converged exactly when that residual <= tol (or it stopped at the precision limit, which says so)."""
    calls = []
    real = simulator_module.newton_solve

    def spy(problem, y, opts, reference=None):
        st = real(problem, y, opts, reference=reference)
        calls.append((reference, st))
        return st

    monkeypatch.setattr(simulator_module, "newton_solve", spy)
    mesh = wf.box_tet_mesh(size=(0.1, 0.1, 0.1), cells=(2, 2, 2), origin=(0.0, 0.004, 0.0))
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0),
                     gravity=(0.0, -9.81, 0.0))
    tol = 1e-6
    sim = wf.Simulator(model, dt=0.01, tol=tol, friction_iterations=1, friction_tol=1e-9,
                       colliders=[wf.Plane(point=(0, 0, 0), normal=(0, 1, 0), friction=0.5)])
    sim.set_velocities(np.tile([1.0, -0.5, 0.0], (model.num_vertices, 1)))
    lagged = 0
    for _ in range(4):
        calls.clear()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", NotConvergedWarning)
            st = sim.step()
        assert len(calls) == 1 and calls[0][0] is None  # one solve, its own start as reference
        assert st.initial_gradient == calls[0][1].initial_gradient > 0.0
        assert st.residual == pytest.approx(st.gradient_norm / st.initial_gradient, rel=1e-12)
        assert st.tolerance == tol
        if "precision limit" not in st.reason:
            assert st.converged == (st.residual <= tol), (st.residual, st.reason)
        if st.friction_iterations:
            lagged += 1
            assert st.adaptations >= st.friction_iterations  # the potential changed there, and was evaluated again
    assert lagged >= 2  # friction was lagged again after landing
    assert sim.unconverged_steps == 0


def test_resolve_from_a_start_within_the_reference_tolerance_takes_no_iteration():
    """newton_solve with a reference: a start already below tol * reference is converged as it is;
    the same start without the reference (its own gradient as reference) iterates."""
    sim = beam_sim(tol=1e-6)
    pot = sim.potential()
    y = wp.clone(sim.v)
    loose = newton_solve(pot, y, replace(sim.options, max_iters=1))
    g0 = loose.initial_gradient  # the start of the step
    assert loose.newton_iterations == 1 and loose.residual > 1e-6
    y1 = wp.clone(y)
    st = newton_solve(pot, y1, sim.options, reference=1e7 * loose.gradient_norm)
    assert st.converged and st.newton_iterations == 0 and "start already within tolerance" in st.reason
    assert st.residual == pytest.approx(1e-7, rel=1e-9) and st.initial_gradient == 1e7 * loose.gradient_norm
    np.testing.assert_array_equal(y1.numpy(), y.numpy())  # not moved
    st = newton_solve(pot, wp.clone(y), replace(sim.options, max_iters=1), reference=g0)
    # continuing from the loose point with the step's reference: one more iteration, residual over g0
    assert st.newton_iterations == 1 and st.initial_gradient == g0
    assert st.residual == pytest.approx(st.gradient_norm / g0, rel=1e-12)
    assert st.converged == (st.residual <= 1e-6)


# ------------------------------------------------------------------ (b) max_iters = 1
def test_step_stopped_at_max_iters_is_converged_exactly_when_its_gradient_is_within_tol():
    probe = beam_sim(max_iters=1, tol=1e-12)
    with pytest.warns(NotConvergedWarning) as caught:
        st = probe.step()
    r = st.residual
    assert st.newton_iterations == 1 and not st.converged and 1e-4 < r < 0.5
    assert st.residual == pytest.approx(st.gradient_norm / st.initial_gradient, rel=1e-12)
    message = str(caught[0].message)
    assert issubclass(caught[0].category, RuntimeWarning)
    assert f"relative gradient {r:.2e} > tol 1.0e-12" in message and "step 0 did not converge" in message
    assert probe.unconverged_steps == 1

    above = beam_sim(max_iters=1, tol=2.0 * r)  # the same one iteration, now within tolerance
    with warnings.catch_warnings():
        warnings.simplefilter("error", NotConvergedWarning)
        st = above.step()
    assert st.converged and st.newton_iterations == 1 and st.residual == pytest.approx(r, rel=1e-9)
    assert above.unconverged_steps == 0

    below = beam_sim(max_iters=1, tol=0.5 * r)
    with pytest.warns(NotConvergedWarning, match=rf"relative gradient {r:.2e} > tol {0.5 * r:.1e}"):
        st = below.step()
    assert not st.converged and st.reason == "reached max_iters=1" and below.unconverged_steps == 1

    strict = beam_sim(max_iters=1, tol=0.5 * r, require_convergence=True)
    with pytest.raises(wf.SolveFailed, match=rf"step 0 did not converge: reached max_iters=1 \(relative gradient "
                                            rf"{r:.2e} > tol {0.5 * r:.1e}\); state left unchanged"):
        strict.step()
    assert strict.unconverged_steps == 0 and strict.time == 0.0


# ------------------------------------------------------------------ (c) warpfem run
# max_iters = 1 at tol 0.015: the two steps of frames 1 and 2 stop at relative gradients 0.0048 to
# 0.0116 (converged), those of frames 3 and 4 at 0.017 to 0.025 (not converged)
SCENE = cli_beam_toml(frames=4).replace("dt = 0.025", "dt = 0.025\nmax_iters = 1\ntol = 0.015") + 'states = "{states}"\n'


def write_scene(tmp_path, text):
    p = tmp_path / "tiny.toml"
    p.write_text(textwrap.dedent(text))
    return str(p)


def test_run_counts_unconverged_steps_on_its_final_line(tmp_path, capsys):
    states = tmp_path / "s.npz"
    scene = write_scene(tmp_path, SCENE.format(states=states))
    out = tmp_path / "out.usda"
    assert main(["run", scene, "--out", str(out)]) == 0
    captured = capsys.readouterr()
    final = captured.out.strip().splitlines()[-1]
    assert final.startswith("done: 4 frames (8 steps, 4 not converged: frames 3, 4; worst: frame "), final
    warned = [line for line in captured.err.splitlines() if "not converged" in line]
    assert len(warned) == 2 and warned[0].startswith("warning: frame 3: 2 of 2 steps not converged: step 4: "
                                                     "reached max_iters=1 (relative gradient ")
    assert "> tol 1.5e-02" in warned[0] and warned[1].startswith("warning: frame 4: 2 of 2 steps")
    assert "Warning" not in captured.err and ".py:" not in captured.err  # no Python warning / source line
    log = [json.loads(line) for line in (tmp_path / "out.stats.jsonl").read_text().splitlines()]
    assert [r["unconverged_steps"] for r in log] == [0, 0, 2, 2]
    assert [r["converged"] for r in log] == [True, True, False, False]
    assert all(r["residual"] <= 0.015 for r in log[:2]) and all(r["residual"] > 0.015 for r in log[2:])
    # the worst unconverged step named on the final line is the largest relative gradient of the log
    worst = max(log, key=lambda r: r["worst_residual"])
    assert [r["worst_residual"] for r in log[:2]] == [0.0, 0.0] and worst["worst_residual"] > 0.015
    assert f"; worst: frame {worst['frame']}, relative gradient {worst['worst_residual']:.2e}); wrote " in final


def test_require_convergence_stops_the_run_with_one_line_and_keeps_earlier_frames(tmp_path, capsys):
    from warpfem.io import read_usd_mesh_frames

    states = tmp_path / "s.npz"
    out = tmp_path / "out.usda"
    results = []
    for how, text, extra in (("flag", SCENE, ["--require-convergence"]),
                             ("scene", SCENE.replace("tol = 0.015", "tol = 0.015\nrequire_convergence = true"), [])):
        assert main(["run", write_scene(tmp_path, text.format(states=states)), "--out", str(out), "--quiet"]
                    + extra) == 1, how
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0, err
        assert err.startswith("warpfem: error: ") and "frame 3: step 4 did not converge: reached max_iters=1 " \
            "(relative gradient " in err and "> tol 1.5e-02)" in err and "frames 0..2 are in" in err, err
        times, frames = read_usd_mesh_frames(out, "boundary")
        assert times.tolist() == [0, 1, 2]
        st = np.load(states)
        assert st["positions"].shape[0] == 3 and st["times"] == pytest.approx([0.0, 0.05, 0.1])
        # frame 2 is the moved beam (not the rest pose) in both outputs
        assert np.abs(frames[2] - frames[0]).max() > 1e-4 and np.abs(st["positions"][2] - st["rest"]).max() > 1e-4
        results.append(st["positions"].copy())
    np.testing.assert_array_equal(results[0], results[1])


def test_scene_run_logs_one_line_per_frame_and_no_python_warning(tmp_path, caplog):
    from warpfem.scenes import load_scene

    run = load_scene(write_scene(tmp_path, SCENE.format(states=tmp_path / "s.npz"))).build()
    with warnings.catch_warnings():
        warnings.simplefilter("error", NotConvergedWarning)  # none escapes the run
        with caplog.at_level(logging.WARNING, logger="warpfem"):
            history = run.run(usd=str(tmp_path / "o.usda"))
    lines = [r.getMessage() for r in caplog.records if "not converged" in r.getMessage()]
    assert [ln.split(":")[0] for ln in lines] == ["frame 3", "frame 4"]
    assert run.sim.unconverged_steps == 4
    summary = run.convergence_summary(history)
    worst = summary.pop("worst")
    assert summary == {"steps": 8, "unconverged_steps": 4, "unconverged_frames": [3, 4]}
    assert worst == (4, max(fs.worst_residual for fs in history)) and worst[1] > 0.015
