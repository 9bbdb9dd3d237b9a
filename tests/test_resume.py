"""``warpfem run SCENE --resume``: real runs killed with SIGKILL (a subprocess, killed once k frames'
statistics are on disk, so the kill lands anywhere in the writing of the next frames) and resumed end
with the files of an uninterrupted run: the states bit for bit (float64 with a named linear solver,
and float32; pcg and direct), the same USD frames, the same statistics (but the timings), the same ParaView frames.
Cases: a beam (with USD value clips cut mid-clip and checkpoints every 4 frames), float32, a contact
scene, a reduced scene and a two-body scene. Resuming a changed scene, or with nothing to resume, is
one line."""

from __future__ import annotations

import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from test_bodies_scenes import BODY_SOFT, BODY_STIFF, SHARED
from tiny_scenes import cli_beam_toml, reduced_beam_toml
from warpfem.cli import main
from warpfem.io import read_pvd
from warpfem.io.stats import read_stats

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
LONG = 100000  # frames of the killed run's scene: it cannot finish before the kill

BEAM_OUT = 'usd = "out/s.usda"\nstates = "out/s.npz"\nclip_frames = 3\n'


def beam(solver="pcg", extra=""):
    text = cli_beam_toml(frames=LONG).replace('dt = 0.025\n', f'dt = 0.025\nlinear_solver = "{solver}"\n')
    return text + BEAM_OUT + extra


def contact():
    """A free 0.4 m bar dropped 2 cm onto a plane with friction (barrier contact, lagged friction)."""
    return f"""
gravity = [0.0, 0.0, -9.81]
[mesh]
generator = "box"
size = [0.4, 0.1, 0.1]
cells = [4, 1, 1]
origin = [0.0, 0.0, 0.02]
[material]
model = "stable_neo_hookean"
youngs_modulus = 1e5
poisson_ratio = 0.3
[[collider]]
type = "plane"
point = [0.0, 0.0, 0.0]
normal = [0.0, 0.0, 1.0]
friction = 0.5
[integrator]
type = "backward_euler"
dt = 0.01
linear_solver = "pcg"
[output]
fps = 50
frames = {LONG}
""" + BEAM_OUT


def reduced():
    sub = '[subspace]\nmodes = 4\nmax_cubature_points = 16\ntraining = "random"\nmax_error = 0\n'
    text = reduced_beam_toml("s", g=-9.81, frames=LONG, subspace=sub)
    return text.replace("[output]\n", "[output]\n" + BEAM_OUT)


def bodies():
    shared = SHARED.replace("frames = 3", f"frames = {LONG}").replace("clip_frames = 0\n", "")
    return shared + BEAM_OUT + 'vtu = "out/s.pvd"\n' + BODY_SOFT + BODY_STIFF


def run_until_killed(scene, stats, frames_seen, cwd, extra=()):
    """``warpfem run SCENE`` in a subprocess, SIGKILLed once ``stats`` has ``frames_seen`` records."""
    env = {**os.environ, "PYTHONPATH": ROOT}
    p = subprocess.Popen([sys.executable, "-m", "warpfem", "run", scene, "--quiet", *extra], cwd=cwd, env=env,
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    try:
        while time.monotonic() < deadline and p.poll() is None:
            if os.path.exists(stats) and len(read_stats(stats)) >= frames_seen:
                break
            time.sleep(0.002)
        assert p.poll() is None, f"the run ended before it was killed: {p.stderr.read().decode()}"
        os.kill(p.pid, signal.SIGKILL)
    finally:
        p.wait()
    assert p.returncode == -signal.SIGKILL


CASES = {  # name: (scene text, precision, frames seen before the kill, frames of the finished run)
    "beam-float64-every4": (beam(extra='checkpoint_every = 4\nvtu = "out/s.pvd"\n'), "float64", 6, 11),
    "beam-float32": (beam("direct"), "float32", 3, 7),
    "contact": (contact(), "float64", 4, 8),
    "reduced": (reduced(), "float64", 4, 8),
    "two-bodies": (bodies(), "float64", 2, 5),
}


def _setup(folder, text, *, cache=None):
    os.makedirs(folder)
    (folder / "s.toml").write_text(text)
    if cache is not None:
        shutil.copy(cache, folder / "s.subspace.npz")
    return str(folder / "s.toml")


def _run(folder, *args):
    cwd = os.getcwd()
    os.chdir(folder)
    try:
        return main(["run", "s.toml", "--quiet", *args])
    finally:
        os.chdir(cwd)


def _usd_frames(path):
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.Open(str(path))
    out = {}
    for prim in stage.Traverse():
        if prim.IsA(UsdGeom.PointBased):  # surfaces, colliders, usd_volume TetMeshes
            attr = UsdGeom.PointBased(prim).GetPointsAttr()
            times = attr.GetTimeSamples()
            out[str(prim.GetPath())] = (list(times), np.array([np.array(attr.Get(t)) for t in times]))
    return out


def check_killed_outputs(out, seen):
    """What a run killed once ``seen`` frames' statistics were written leaves (frames 0..seen - 1
    finished, the kill landing anywhere in the writing of the next): the states (from their stream),
    the USD (saved with every frame), the ParaView collection and the statistics log each hold at
    least those frames, with their times, marked incomplete where the format says so."""
    from warpfem.io import read_states
    from warpfem.io.states import stream_directory

    assert not (out / "s.npz").exists() and os.path.isdir(stream_directory(out / "s.npz"))
    d = read_states(out / "s.npz")
    k = len(d["times"])
    assert d["complete"] is False and k >= seen and d["positions"].shape[0] == k
    assert np.all(np.isfinite(d["positions"])) and d["times"][0] == 0.0 and np.all(np.diff(d["times"]) > 0)
    stats = read_stats(out / "s.stats.jsonl")
    assert len(stats) >= seen and [r["frame"] for r in stats] == list(range(1, len(stats) + 1))
    for prim, (times, _) in _usd_frames(out / "s.usda").items():
        assert len(times) >= seen and times == list(range(len(times))), prim
    if (out / "s.pvd").exists():
        entries, meta = read_pvd(out / "s.pvd")
        assert len(entries) >= seen and meta["complete"] is False


@pytest.mark.parametrize("case", list(CASES))
def test_killed_run_resumes_to_the_uninterrupted_files(tmp_path, case):
    text, precision, seen, frames = CASES[case]
    cache = None
    if case == "reduced":  # the subspace, trained once for both runs
        scene = _setup(tmp_path / "train", text)
        assert main(["train", scene, "--quiet"]) == 0
        cache = tmp_path / "train" / "s.subspace.npz"
    ref, cut = tmp_path / "ref", tmp_path / "cut"
    _setup(ref, text, cache=cache)
    _setup(cut, text, cache=cache)
    assert _run(ref, "--frames", str(frames), "--precision", precision) == 0
    run_until_killed("s.toml", cut / "out" / "s.stats.jsonl", seen, cut, extra=("--precision", precision))
    check_killed_outputs(cut / "out", seen)
    assert _run(cut, "--resume", "--frames", str(frames), "--precision", precision) == 0

    with np.load(ref / "out" / "s.npz") as a, np.load(cut / "out" / "s.npz") as b:
        assert sorted(a.files) == sorted(b.files)
        for key in a.files:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)  # bit for bit
        assert len(a["times"]) == frames + 1
    usd_a, usd_b = _usd_frames(ref / "out" / "s.usda"), _usd_frames(cut / "out" / "s.usda")
    assert sorted(usd_a) == sorted(usd_b)
    for prim, (times, pts) in usd_a.items():
        assert usd_b[prim][0] == times == list(range(frames + 1)), prim
        np.testing.assert_array_equal(usd_b[prim][1], pts, err_msg=prim)
    from pxr import Sdf

    assert Sdf.Layer.FindOrOpen(str(cut / "out" / "s.usda")).customLayerData["warpfem"]["complete"] is True
    sa, sb = read_stats(ref / "out" / "s.stats.jsonl"), read_stats(cut / "out" / "s.stats.jsonl")
    assert [{k: v for k, v in r.items() if k != "step_seconds"} for r in sa] == \
        [{k: v for k, v in r.items() if k != "step_seconds"} for r in sb]
    if (ref / "out" / "s.pvd").exists():
        ea, ma = read_pvd(ref / "out" / "s.pvd")
        eb, mb = read_pvd(cut / "out" / "s.pvd")
        blocks = 2 if case == "two-bodies" else 1
        assert [t for t, _ in ea] == [t for t, _ in eb] and len(ea) == blocks * (frames + 1) and mb["complete"]
        import meshio

        for (_, fa), (_, fb) in zip(ea[-blocks:], eb[-blocks:]):  # the last frame's volume and stresses
            va, vb = meshio.read(fa), meshio.read(fb)
            np.testing.assert_array_equal(va.points, vb.points)
            np.testing.assert_array_equal(va.cell_data["von_mises"][0], vb.cell_data["von_mises"][0])


def test_resume_refusals_and_a_longer_run(tmp_path, capsys):
    """Nothing to resume is one line (no checkpoint: exit 2; every frame done: exit 0); a finished 3-frame run resumed
    to 5 frames equals a 5-frame run bit for bit; a changed material is refused naming the key and
    both values; a changed solver tolerance is accepted."""
    text = beam()
    folder, ref = tmp_path / "a", tmp_path / "b"
    _setup(folder, text)
    _setup(ref, text)
    assert _run(folder, "--resume", "--frames", "3") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "nothing to resume: no checkpoint out/s.checkpoint.npz" in err[0], err
    assert _run(folder, "--frames", "3") == 0
    capsys.readouterr()
    assert _run(folder, "--resume", "--frames", "3") == 0  # already complete: said, not an error
    out = capsys.readouterr()
    assert out.err == "" and "nothing to resume: out/s.checkpoint.npz is at frame 3, the run has 3 frames" in out.out

    assert _run(folder, "--resume", "--frames", "5") == 0
    assert _run(ref, "--frames", "5") == 0
    with np.load(ref / "out" / "s.npz") as a, np.load(folder / "out" / "s.npz") as b:
        for key in a.files:
            np.testing.assert_array_equal(a[key], b[key], err_msg=key)
    assert _usd_frames(ref / "out" / "s.usda")["/Root/boundary"][0] == list(range(6))
    np.testing.assert_array_equal(_usd_frames(ref / "out" / "s.usda")["/Root/boundary"][1],
                                  _usd_frames(folder / "out" / "s.usda")["/Root/boundary"][1])

    scene = folder / "s.toml"
    scene.write_text(text.replace("youngs_modulus = 1e5", "youngs_modulus = 2e5"))
    assert _run(folder, "--resume", "--frames", "7") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "physics changed" in err[0], err
    assert "[material].youngs_modulus (100000.0 -> 200000.0)" in err[0], err

    scene.write_text(text.replace("dt = 0.025\n", "dt = 0.025\ntol = 1e-7\n"))  # a solver setting: allowed
    assert _run(folder, "--resume", "--frames", "7") == 0
    with np.load(folder / "out" / "s.npz") as z:
        assert len(z["times"]) == 8
