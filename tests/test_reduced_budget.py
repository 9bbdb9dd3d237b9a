"""`warpfem train`'s error budget (`[subspace] max_error`, default 2 % RMS replay error) and its
report: POD columns are added until the replay of the training run is within the budget, an
impossible budget fails with a message and writes no cache, and the report's numbers add up."""

import json
import math
import re

import numpy as np

from tiny_scenes import reduced_beam_toml
from warpfem.cli import main

# 8 m beam of 8 cells, soft (E 1e5) so that it sags well past what 2 modal columns follow:
# measured 2.6 % RMS replay error with no POD column, 0.016 % with 4
SUBSPACE = ('[subspace]\nmodes = 2\nmax_cubature_points = 48\ntraining = "snapshots"\n'
            'cubature_tolerance = 0.01\n{extra}')


def _write(tmp_path, name, extra=""):
    p = tmp_path / f"{name}.toml"
    text = reduced_beam_toml(name, g=-9.81, frames=12, states=True, subspace=SUBSPACE.format(extra=extra))
    p.write_text(text.replace("youngs_modulus = 1e6", "youngs_modulus = 1e5"))
    return str(p)


def _report(path):
    with np.load(path, allow_pickle=False) as z:
        return json.loads(str(z["meta"]))["report"]


def test_default_budget_adds_pod_columns_and_the_report_adds_up(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    path = _write(tmp_path, "budget")
    assert main(["train", path, "--quiet"]) == 0
    out = capsys.readouterr().out
    rep = _report(tmp_path / "budget.subspace.npz")
    b = rep["budget"]
    assert b["max_error"] == 0.02 and b["checked"] and b["met"]  # the schema default
    first, last = b["attempts"][0], b["attempts"][-1]
    assert first["pod_modes"] == 0 and first["rms_error"] > 0.02  # the scene's own sizes miss 2 %
    assert last["pod_modes"] > 0 and last["rms_error"] <= 0.02  # POD columns bring it within
    assert rep["replay_rms_error"] == last["rms_error"] and rep["pod_modes"] == last["pod_modes"]
    assert rep["modes"] == last["r"] == 2 + last["pod_modes"]
    assert f"error budget: replay RMS error {100 * last['rms_error']:.2g} % <= max_error 2 %" in out
    assert f"({last['pod_modes']} POD columns chosen; tried 0 POD: {100 * first['rms_error']:.2g} %" in out
    # first train without --retrain: no "retrain requested"
    assert "cache: trained (no cache yet)" in out and "retrain requested" not in out
    # the training cost is the sum of its items (the report and the printed line)
    items = rep["training_items"]
    assert "earlier budget attempt" in " ".join(items) and min(items.values()) >= 0.0
    assert math.isclose(sum(items.values()), rep["training_seconds"], rel_tol=1e-12)
    line = next(ln for ln in out.splitlines() if ln.startswith("training cost:"))
    total = float(re.match(r"training cost: ([\d.]+) s = ", line).group(1))
    printed = [float(v) for v in re.findall(r" ([\d.]+) s(?= \+| \()", line.split(" = ", 1)[1])]
    assert len(printed) == len(items)
    assert abs(sum(printed) - total) <= 0.05 * (len(printed) + 1)  # each printed to 0.1 s
    # speed-up and break-even follow from the printed step times and the cost beyond a full run's
    red, full = rep["reduced_step_seconds"], rep["full_step_seconds"]
    assert math.isclose(rep["predicted_speedup"], full / red, rel_tol=1e-12)
    setup = items["setup (model, simulators)"]
    assert math.isclose(rep["break_even_seconds"], rep["training_seconds"] - setup - rep["kernel_load_seconds"],
                        rel_tol=1e-9, abs_tol=1e-12)
    if full > red:
        assert rep["break_even_frames"] == math.ceil(rep["break_even_seconds"] / (full - red))  # 1 substep
    # the cache records the scene's settings: a second train reuses it and `run` accepts it
    assert main(["train", path, "--quiet"]) == 0 and "up to date" in capsys.readouterr().out
    assert main(["train", path, "--quiet", "--retrain"]) == 0 and "trained (--retrain requested)" in capsys.readouterr().out
    assert main(["describe", path]) == 0
    desc = capsys.readouterr().out
    assert "error budget: train adds POD columns (up to 32) until its replay of the training run is within 0.02" in desc
    assert (f"cache {tmp_path / 'budget.subspace.npz'}: r = {last['r']}," in desc
            and f"replay RMS error {last['rms_error']:.3g} with {last['pod_modes']} POD columns chosen" in desc)
    assert main(["run", path, "--quiet"]) == 0
    # the reduced run is the replay train measured: the same RMS error against the full training run
    from warpfem.reduced.scene import trajectory_errors
    from warpfem.scenes import load_scene

    x_red = np.load(tmp_path / "budget.npz")["positions"]
    full_scene = load_scene(path)
    run = full_scene.build(full=True)
    xs = [run.sim.positions()]
    for _ in range(12):
        run.step_frame()
        xs.append(run.sim.positions())
    err = trajectory_errors(run.model, np.array(xs), x_red)["replay_rms_error"]
    assert abs(err - last["rms_error"]) <= 1e-6 + 1e-3 * last["rms_error"]


def test_budget_off_and_impossible_budget(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    off = _write(tmp_path, "off", "max_error = 0.0\n")  # no budget: the scene's sizes, as before
    assert main(["train", off, "--quiet"]) == 0
    rep = _report(tmp_path / "off.subspace.npz")
    assert rep["pod_modes"] == 0 and rep["replay_rms_error"] > 0.02 and len(rep["budget"]["attempts"]) == 1
    bad = _write(tmp_path, "bad", "max_error = 1e-9\nmax_pod_modes = 4\n")
    capsys.readouterr()
    assert main(["train", bad, "--quiet"]) == 1
    err = capsys.readouterr().err
    assert "[subspace] max_error = 1e-09 not met" in err and "tried POD columns 0, 4" in err
    assert "max_pod_modes = 4" in err and "the cache was not written" in err
    assert not (tmp_path / "bad.subspace.npz").exists()
