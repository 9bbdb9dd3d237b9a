"""Friction coefficients as parameters of scene gradient runs (``warpfem.diff``) and ``warpfem fit``:
``friction:<collider name>`` (a ``[[collider]]``'s friction) and ``contact_friction`` (``[contact]
friction``, surface contact). Their scene gradients against central differences of the loss
(float64), a fit of a floor's mu from a noisy recording of a box thrown sideways onto it, and the
one-line errors on bad names.

The scenes set ``[contact] friction_iterations = 0``: recorded steps lag friction once from the
step start (docs/gradients.md), so the unrecorded runs compare with the recorded ones.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from warpfem.cli import main
from warpfem.diff import FRICTION_FLOOR, DiffInputError, SceneProblem, scene_with_parameters
from warpfem.scenes import load_scene


def _box_body(name, offset, size, extra="", element=""):
    """A ``[[body]]`` table: a box mesh of 2 x 1 x 1 cells of ``size`` (m) at ``offset``, stable
    neo-Hookean E 1e5, nu 0.3, 1000 kg/m^3; ``extra`` lines after the offset (initial velocity),
    ``element`` a mesh line (e.g. 'element = "hex8"')."""
    return (f'[[body]]\nname = "{name}"\noffset = {list(offset)}\n{extra}[body.mesh]\ngenerator = "box"\n'
            f'size = {list(size)}\ncells = [2, 1, 1]\n{element}[body.material]\nmodel = "stable_neo_hookean"\n'
            'youngs_modulus = 1e5\npoisson_ratio = 0.3\ndensity = 1000.0\n')


# both scenes' run: 10 frames of one backward Euler step of 10 ms
_RUN = """[integrator]
type = "backward_euler"
dt = 0.01
max_iters = 300
[output]
fps = 100
frames = 10
"""

# a 10 cm box (2 x 1 x 1 Tet4 cells) resting in the barrier's range (9.2 mm above the plane, dhat
# 1 cm), thrown sideways at 0.4 m/s: it slides on the floor with friction in every step and comes
# to rest in the last one
SLIDE = """name = "slide"
gravity = [0.0, 0.0, -9.81]
""" + _box_body("box", (0.0, 0.0, 0.0092), (0.1, 0.05, 0.05), "initial_velocity = [0.4, 0.1, -0.02]\n") + """[[collider]]
type = "plane"
name = "floor"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
friction = MU
stiffness = 1e4
dhat = 0.01
[[collider]]                # never reached: its friction's gradient is 0
type = "sphere"
center = [0.0, 0.0, 1.0]
radius = 0.1
friction = 0.2
stiffness = 1e4
[contact]
friction_iterations = 0
""" + _RUN

# two bodies in frictional surface contact: a Tet4 beam thrown sideways and down onto a Hex8 block
# whose bottom is clamped (the beam's offset is not a multiple of the cells: no vertex of it right
# above an edge of the block, where the lagged closest-point weights are only continuous)
BEAM_ON_BLOCK = """name = "beam_on_block"
gravity = [0.0, 0.0, -9.81]
""" + _box_body("top", (0.0123, 0.0071, 0.0), (0.2, 0.05, 0.05), "initial_velocity = [0.3, 0.1, -0.3]\n") + """[[body.force]]
box_min = [-1.0, -1.0, -0.001]
box_max = [1.0, 1.0, 1.0]
force = [0.0, 0.0, -0.5]
""" + _box_body("base", (-0.05, -0.025, -0.059), (0.3, 0.1, 0.05), element='element = "hex8"\n') + """[[body.fixed]]
box_min = [-1.0, -1.0, -1.0]
box_max = [1.0, 1.0, -0.05]
[contact]
bodies = true
friction = 0.4
stiffness = 1e5
dhat = 0.01
friction_iterations = 0
""" + _RUN


def _positions(scene, active):
    """The scene's run (frames + 1, n, 3) and per frame the count that ``active(sim)`` gives."""
    run = scene.build()
    xs, counts = [run.sim.positions()], []
    for _ in range(run.frames):
        assert run.step_frame().converged
        xs.append(run.sim.positions())
        counts.append(active(run.sim))
    return np.array(xs), counts


def _fd_check(problem, name, mu, h=1e-5):
    """(the evaluation at mu, its gradient's relative error to central differences); the problem is
    built at mu + h, mu - h and mu come from in-place changes."""
    fd = (problem.evaluate({name: mu + h}).loss - problem.evaluate({name: mu - h}).loss) / (2 * h)
    res = problem.evaluate({name: mu})
    return res, abs(res.gradients[name] - fd) / abs(fd)


@pytest.mark.parametrize("case", ["collider", "surface"])
def test_scene_friction_gradient_matches_central_differences(tmp_path, case):
    if case == "collider":
        text, name, mu = SLIDE.replace("MU", "0.3"), "friction:floor", 0.3
        active = lambda sim: int(np.sum(sim.contact.normal_forces().reshape(-1, len(sim.contact))[:, 0] > 0))  # noqa: E731
    else:
        text, name, mu = BEAM_ON_BLOCK, "contact_friction", 0.4
        active = lambda sim: sim.surface_contact.num_friction  # noqa: E731
    path = tmp_path / "scene.toml"
    path.write_text(text)
    scene = load_scene(str(path))
    xs, counts = _positions(scene, active)
    assert min(counts) >= 1, counts  # friction in every step (measured: 6 vertices / 13-23 pairs)
    # the observation: the run itself with 2 mm noise (a loss with a slope in mu)
    obs = xs + 2e-3 * np.random.default_rng(1).standard_normal(xs.shape)
    problem = SceneProblem(scene, obs, newton_tol=1e-12)
    res, err = _fd_check(problem, name, 0.7 * mu)
    print(name, f"{err:.1e}")
    assert err <= 1e-5, (name, err)  # measured 4e-12 (floor), 3e-9 (surface)
    # the in-place change of mu between evaluations gives the rebuilt scene's numbers
    fresh = SceneProblem(scene_with_parameters(scene, {name: 0.7 * mu}), obs, newton_tol=1e-12).evaluate()
    assert fresh.loss == pytest.approx(res.loss, rel=1e-10)
    assert fresh.gradients[name] == pytest.approx(res.gradients[name], rel=1e-8)
    if case == "collider":
        assert res.gradients["friction:sphere2"] == 0.0  # the unreached sphere (default name: type + position)
        assert res.gradients["friction:floor"] == res.gradients["collider_friction"]["floor"]
        # friction matters: without it the box slides 3.6x as far (measured)
        x0, _ = _positions(scene_with_parameters(scene, {name: 0.0}), active)
        assert np.mean(x0[-1, :, 0] - x0[0, :, 0]) > 2.0 * np.mean(xs[-1, :, 0] - xs[0, :, 0])


def test_a_friction_of_zero_gives_the_one_sided_gradient(tmp_path):
    """mu = 0 runs as FRICTION_FLOOR (the simulator lags friction only where mu > 0): the gradient
    there is the one-sided derivative (second-order one-sided differences)."""
    path = tmp_path / "slide.toml"
    path.write_text(SLIDE.replace("MU", "0.0"))
    scene = load_scene(str(path))
    truth = scene_with_parameters(scene, {"friction:floor": 0.3})
    xs, _ = _positions(truth, lambda sim: 0)
    problem = SceneProblem(scene, xs, newton_tol=1e-12)
    res = problem.evaluate({"friction:floor": 0.0})
    h = 1e-5
    l1, l2 = (problem.evaluate({"friction:floor": FRICTION_FLOOR + k * h}).loss for k in (1, 2))
    fd = (-3.0 * res.loss + 4.0 * l1 - l2) / (2 * h)
    g = res.gradients["friction:floor"]
    assert g < 0.0  # more friction brings the run closer to the truth
    assert abs(g - fd) <= 1e-5 * abs(fd), (g, fd)  # measured 2e-11
    # the loss there is mu = 0's to FRICTION_FLOOR x its slope: the run without friction
    frictionless = SceneProblem(scene_with_parameters(scene, {}), xs, newton_tol=1e-12).evaluate(wanted=[])
    assert abs(frictionless.loss - res.loss) <= 10 * FRICTION_FLOOR * abs(g) + 1e-12 * res.loss


def test_fit_recovers_a_floors_friction_from_a_noisy_recording(tmp_path, capsys):
    """The box thrown onto the floor recorded with mu = 0.3 (+ 10 um noise); the scene's mu = 0.9
    (3x off) is the start."""
    path = tmp_path / "slide.toml"
    path.write_text(SLIDE.replace("MU", "0.9"))
    truth = scene_with_parameters(load_scene(str(path)), {"friction:floor": 0.3}, newton_tol=1e-12)
    xs, _ = _positions(truth, lambda sim: 0)
    noisy = xs + 1e-5 * np.random.default_rng(7).standard_normal(xs.shape)
    np.savez(tmp_path / "obs.npz", positions=noisy)
    code = main(["fit", str(path), "--observed", str(tmp_path / "obs.npz"), "--params", "friction:floor",
                 "--bounds", "friction:floor=0,1.5", "--report", str(tmp_path / "r.json"),
                 "--out", str(tmp_path / "fitted.toml")])
    assert code == 0
    rep = json.loads((tmp_path / "r.json").read_text())
    mu = rep["params"]["friction:floor"]
    print(rep["params"], rep["iterations"], rep["evaluations"], rep["loss_history"])
    assert abs(mu - 0.3) < 0.005, mu
    assert rep["initial"] == {"friction:floor": 0.9} and rep["bounds"] == {"friction:floor": [0.0, 1.5]}
    assert rep["loss_history"][-1] < 1e-3 * rep["loss_history"][0]
    assert rep["loss"] < 2.0 * 3 * 12 * 11 * 1e-10  # the noise's: 3 x 12 vertices x 11 frames x (10 um)^2
    fitted = load_scene(str(tmp_path / "fitted.toml"))
    assert fitted.spec.collider[0]["friction"] == pytest.approx(mu)  # the floor's table; the sphere's kept
    assert fitted.spec.collider[1]["friction"] == 0.2
    assert "fitted friction:floor" in capsys.readouterr().out


@pytest.mark.parametrize("case", ["collider", "no_collider", "no_contact", "contact_off", "unknown", "bounds",
                                  "negative_bound"])
def test_bad_friction_parameters_are_one_line_and_exit_2(tmp_path, case, capsys):
    path = tmp_path / "slide.toml"
    text = SLIDE.replace("MU", "0.3")
    params, extra = ["friction:floor"], []
    if case == "collider":
        params = ["friction:flor"]
    elif case == "no_collider":
        text = text.split("[[collider]]")[0] + "[contact]" + text.split("[contact]")[1]
        params = ["friction:floor"]
    elif case == "no_contact":
        text = text.replace("[contact]\nfriction_iterations = 0\n", "")
        params = ["contact_friction"]
    elif case == "contact_off":  # one body, [contact] without self = true: no surface contact
        params = ["contact_friction"]
    elif case == "unknown":
        params = ["friction"]
    elif case == "bounds":
        extra = ["--bounds", "friction:wall=0,1"]
    else:
        extra = ["--bounds", "friction:floor=-0.1,1"]
    path.write_text(text)
    obs = np.zeros((11, 12, 3))
    np.savez(tmp_path / "obs.npz", positions=obs)
    code = main(["fit", str(path), "--observed", str(tmp_path / "obs.npz"), "--params", *params, "--quiet", *extra])
    err = capsys.readouterr().err.strip()
    assert code == 2
    assert len(err.splitlines()) == 1 and err.startswith("warpfem: error:"), err
    expect = {"collider": "no collider named 'flor' (its colliders are 'floor', 'sphere2')",
              "no_collider": "it has no [[collider]]", "no_contact": "no [contact] table",
              "contact_off": "surface contact is off",
              "unknown": "unknown parameter 'friction'", "bounds": "bounds given for 'friction:wall'",
              "negative_bound": "must be >= 0"}[case]
    assert expect in err, err


def test_scene_with_parameters_names_what_a_scene_takes(tmp_path):
    """A [[body]] scene of two bodies takes no material parameter (a material per body); the names
    it takes are listed."""
    path = tmp_path / "bob.toml"
    path.write_text(BEAM_ON_BLOCK)
    scene = load_scene(str(path))
    with pytest.raises(DiffInputError, match=r"2 \[\[body\]\] tables .* it takes contact_friction$"):
        scene_with_parameters(scene, {"youngs_modulus": 1e5})
    with pytest.raises(DiffInputError, match="must be >= 0"):
        scene_with_parameters(scene, {"contact_friction": -0.1})
    assert scene_with_parameters(scene, {"contact_friction": 0.25}).spec.contact["friction"] == 0.25
    assert scene.spec.contact["friction"] == 0.4  # the copy's, not the scene's


def test_a_one_body_scene_of_a_body_table_takes_its_material(tmp_path):
    """A [[body]] scene caches its bodies' scenes (with their materials) once its mesh is loaded:
    scene_with_parameters's copy still builds with the new values."""
    path = tmp_path / "slide.toml"
    path.write_text(SLIDE.replace("MU", "0.3"))
    scene = load_scene(str(path))
    scene.mesh()
    sim = scene_with_parameters(scene, {"youngs_modulus": 2e5, "friction:floor": 0.5}).build().sim
    assert sim.model.material.youngs_modulus == 2e5
    assert sim.contact.collider("floor").friction == 0.5
