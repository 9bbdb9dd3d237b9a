"""A newcomer's first hour: output paths checked before any work, SIGTERM
recorded like Ctrl-C, the "compiling kernels" notice with compile time out of the ETA, describe's
tetrahedralisation line once, --quiet without the cache-hit line, "did you mean" in grid files."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from warpfem.cli import main
from warpfem.io.outputs import OutputPathError, check_output_paths, output_path_problem
from warpfem.progress import COMPILING_NOTICE, CompileWatch, Progress

from tiny_scenes import cli_beam_toml

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))



def scene_file(tmp_path, extra="", frames=2, name="s.toml"):
    p = tmp_path / name
    p.write_text(textwrap.dedent(cli_beam_toml(frames=frames)) + textwrap.dedent(extra))
    return str(p)


def layer_info(path):
    from pxr import Sdf

    layer = Sdf.Layer.FindOrOpen(str(path))
    layer.Reload()
    return dict(layer.customLayerData)["warpfem"]


# ------------------------------------------------------------------------------- output paths
def test_output_path_problem_names_the_file_in_the_way(tmp_path):
    (tmp_path / "a_file").write_text("x")
    (tmp_path / "folder").mkdir()
    assert output_path_problem(tmp_path / "new" / "deeper" / "x.usda") is None  # folders can be made
    assert output_path_problem(tmp_path / "a_file") is None  # an existing writable file is overwritten
    assert "a_file is a file, not a folder" in output_path_problem(tmp_path / "a_file" / "b" / "x.usda")
    assert output_path_problem(tmp_path / "folder") == "it is a folder"
    assert "is a file, not a folder" in output_path_problem(tmp_path / "a_file", folder=True)
    with pytest.raises(OutputPathError, match=r"\[output\] vtu .*a_file/x.pvd: cannot create it: .*a_file is a file"):
        check_output_paths({"[output] usd": None, "[output] vtu": str(tmp_path / "a_file" / "x.pvd")})
    (tmp_path / "r.clips").write_text("in the way")  # the USD's value-clip folder is a file
    with pytest.raises(OutputPathError, match="value clips"):
        check_output_paths({"--out": str(tmp_path / "r.usda")})
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "folder", "r.clips"]  # nothing created


@pytest.mark.parametrize("where", ["--out", "vtu", "states", "--preview", "stats"])
def test_run_refuses_an_uncreatable_output_path_before_any_work(tmp_path, capsys, monkeypatch, where):
    """`--out a_file/x.usda`, `[output] vtu = "a_file/x.pvd"`, states, stats or --preview under a
    file: one line, exit code 2, and no output at all (no partial USD)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "a_file").write_text("not a folder")
    extra = {"vtu": '\nvtu = "a_file/x.pvd"\n', "states": '\nstates = "a_file/x.npz"\n',
             "stats": '\nstats = "a_file/x.jsonl"\n'}.get(where, "")
    scene = scene_file(tmp_path, "" if where.startswith("--") else extra)
    if not where.startswith("--"):  # the [output] keys go in the [output] table (the last one)
        assert extra.strip() in open(scene).read()
    argv = ["run", scene, "--quiet"]
    if where != "stats":  # --out puts the statistics log next to the USD
        argv += ["--out", "a_file/x.usda" if where == "--out" else "out/good.usda"]
    if where == "--preview":
        pytest.importorskip("matplotlib")
        argv += ["--preview", "a_file/p.png"]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("warpfem: error:"), err
    assert "a_file is a file, not a folder" in err and "Traceback" not in err
    label = {"--out": "--out", "vtu": "[output] vtu", "states": "[output] states", "--preview": "--preview",
             "stats": "statistics log"}[where]
    assert label in err, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "s.toml"]  # no out/, no USD


def test_scene_run_checks_every_path_before_writing(tmp_path, monkeypatch):
    from warpfem.scenes import load_scene

    monkeypatch.chdir(tmp_path)
    (tmp_path / "a_file").write_text("x")
    run = load_scene(scene_file(tmp_path)).build(device="cpu")
    with pytest.raises(OutputPathError, match="vtu a_file/v.pvd"):
        run.run(frames=1, usd="out/x.usda", states="out/x.npz", vtu="a_file/v.pvd")
    assert not (tmp_path / "out").exists() and run.frame == 0


def test_sigterm_marks_the_usd_incomplete_with_the_reason(tmp_path):
    """SIGTERM during `warpfem run`: exit 143, a one-line message, and the USD closed as Ctrl-C
    closes it: complete = false with the reason and the frames done."""
    scene = scene_file(tmp_path, frames=5000)
    usd = tmp_path / "t.usda"
    p = subprocess.Popen([sys.executable, "-m", "warpfem", "run", scene, "--out", str(usd)], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, cwd=ROOT)
    try:
        for line in p.stdout:  # plain progress lines (not a terminal)
            if "frame 3/5000" in line:
                break
        p.send_signal(signal.SIGTERM)
        rc = p.wait(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    err = p.stderr.read()
    assert rc == 143, err
    assert "terminated (SIGTERM) at frame" in err and "marked incomplete" in err, err
    info = layer_info(usd)
    assert info["complete"] is False and info["framesWritten"] >= 4, info
    assert info["incompleteReason"].startswith("Terminated: SIGTERM at frame"), info
    last = [json.loads(x) for x in (tmp_path / "t.stats.jsonl").read_text().splitlines()][-1]
    assert last["frame"] >= 3


# ------------------------------------------------------------------------- compiling kernels
def test_compile_watch_notices_a_cache_miss_once_and_times_it(tmp_path):
    """A module Warp must compile (a fresh kernel cache) calls on_start once, before compiling, and
    on_compiled with the load's time; a loaded module does not; the hooks are removed on exit."""
    import warp as wp
    from warp._src.context import Module

    load, compile_ = Module.__dict__["load"], Module.__dict__["_compile"]
    saved = wp.config.kernel_cache_dir
    events = []

    @wp.kernel(module="unique")
    def _fh_scale(x: wp.array(dtype=wp.float32), s: wp.float32):
        i = wp.tid()
        x[i] = x[i] * s

    try:
        wp.config.kernel_cache_dir = str(tmp_path / "kernels")  # nothing cached there: a compile
        x = wp.ones(4, dtype=wp.float32, device="cpu")
        with CompileWatch(on_start=lambda: events.append("start"), on_compiled=lambda s: events.append(s)) as w:
            wp.launch(_fh_scale, dim=4, inputs=[x, wp.float32(2.0)], device="cpu")
            wp.launch(_fh_scale, dim=4, inputs=[x, wp.float32(2.0)], device="cpu")  # loaded: no compile
        assert events[0] == "start" and len(events) == 2 and events[1] > 0, events
        assert w.modules == 1 and w.seconds == events[1]
        assert x.numpy().tolist() == [4.0] * 4
    finally:
        wp.config.kernel_cache_dir = saved
    assert Module.__dict__["load"] is load and Module.__dict__["_compile"] is compile_
    with CompileWatch(on_start=lambda: events.append("again")) as w2:  # all cached/loaded now
        wp.launch(_fh_scale, dim=4, inputs=[x, wp.float32(1.0)], device="cpu")
    assert "again" not in events and w2.modules == 0


def test_eta_leaves_compile_time_out():
    """Frame 1 took 20 s of which 19.97 s compiling: the ETA after it is the frames left times
    0.03 s, not times 20 s; later frames keep it out too."""
    now = [0.0]
    lines = []
    bar = Progress(10, unit="frame", bar=False, write=lines.append, clock=lambda: now[0], started=0.0)
    now[0] = 19.97
    bar.exclude(19.97)
    now[0] = 20.0
    bar.update(1)
    assert bar.eta(1) == pytest.approx(9 * 0.03)
    now[0] = 20.1  # frame 2: 0.1 s, of it nothing compiled
    bar.update(2)
    assert bar.eta(2) == pytest.approx(8 * 0.1)
    bar.exclude(5.0)
    now[0] = 25.2  # frame 3 compiled another module for 5 s
    assert bar.eta(3) == pytest.approx(7 * (0.1 + 0.1) / 2)


def test_run_says_compiling_kernels_once(tmp_path, capsys, monkeypatch):
    """The notice is printed (once) when the watch reports a compile, and not with --quiet."""
    import warpfem.progress as progress

    class Compiling(CompileWatch):
        def __enter__(self):
            super().__enter__()
            self._notice_start()
            self._notice_start()  # noticed once
            self.modules, self.seconds = 1, 12.5
            return self

    monkeypatch.setattr(progress, "CompileWatch", Compiling)
    scene = scene_file(tmp_path)
    assert main(["run", scene, "--out", str(tmp_path / "c.usda")]) == 0
    out = capsys.readouterr().out
    assert out.count(COMPILING_NOTICE) == 1, out
    assert "kernels compiled in 12.5 s" in out
    assert main(["run", scene, "--quiet", "--out", str(tmp_path / "c.usda")]) == 0
    assert COMPILING_NOTICE not in capsys.readouterr().out


# ------------------------------------------------------------------- describe, --quiet, grids
CUBE_OBJ = """v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 0 1\nv 1 0 1\nv 1 1 1\nv 0 1 1
f 1 3 2\nf 1 4 3\nf 5 6 7\nf 5 7 8\nf 1 2 6\nf 1 6 5\nf 2 3 7\nf 2 7 6\nf 3 4 8\nf 3 8 7\nf 4 1 5\nf 4 5 8
"""


def test_describe_prints_the_tetrahedralisation_once_and_quiet_drops_the_cache_line(tmp_path, capsys, monkeypatch):
    pytest.importorskip("tetgen")
    monkeypatch.setenv("WARPFEM_CACHE_DIR", str(tmp_path / "cache"))
    (tmp_path / "cube.obj").write_text(CUBE_OBJ)
    text = textwrap.dedent(cli_beam_toml(frames=1)).replace(
        'generator = "box"\nsize = [1.0, 0.2, 0.2]\ncells = [4, 1, 1]', 'path = "cube.obj"')
    scene = tmp_path / "cube.toml"
    scene.write_text(text)
    for attempt in ("meshed", "cache hit"):
        assert main(["describe", str(scene)]) == 0
        cap = capsys.readouterr()
        both = cap.out + cap.err
        assert both.count("tetrahedralis") == 1, both  # once, inside the description
        assert attempt in both
    assert main(["run", str(scene), "--quiet", "--out", str(tmp_path / "q.usda")]) == 0
    cap = capsys.readouterr()
    assert cap.out == "" and cap.err == "", cap  # --quiet: not even the cache-hit line
    assert main(["run", str(scene), "--out", str(tmp_path / "q.usda")]) == 0
    assert "cache hit" in capsys.readouterr().err  # shown without --quiet


def test_grid_files_suggest_the_key_meant(tmp_path):
    from warpfem.tradeoff import GridError, load_grid

    cases = {'frame = 3\n': "did you mean 'frames'",
             '[[config]]\nprecison = "float32"\n': "did you mean 'precision'",
             '[truth]\nrefin = 2\n': "did you mean 'refine'",
             '[axes]\ncg_toll = [1e-2]\n': "did you mean 'cg_tol'"}
    for text, hint in cases.items():
        p = tmp_path / "g.toml"
        p.write_text(text)
        with pytest.raises(GridError, match=hint):
            load_grid(p)


@pytest.mark.parametrize("argv", [
    ["tradeoff", "{scene}", "--grid", "quick", "--json", "a_file/t.json"],
    ["tradeoff", "{scene}", "--grid", "quick", "--markdown", "a_file/t.md"],
    ["tradeoff", "{scene}", "--grid", "quick", "--plot", "a_file/t.png"],
    ["tune", "{scene}", "--max-error", "0.05", "--out", "a_file/x.toml"],
    ["tune", "{scene}", "--max-error", "0.05", "--report", "a_file/x.json"],
    ["train", "{reduced}"],
])
def test_studies_and_training_refuse_an_uncreatable_output_before_any_run(tmp_path, capsys, monkeypatch, argv):
    """tradeoff / tune / train write their results after minutes of runs: a path under a file is
    refused first, one line, exit 2, nothing run or written."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "a_file").write_text("x")
    scene = scene_file(tmp_path)
    reduced = scene_file(tmp_path, extra='[subspace]\nmodes = 4\ncache = "a_file/s.npz"\n', name="r.toml")
    import warpfem.tradeoff.study as study
    import warpfem.tradeoff.tune as tune

    def boom(*a, **k):
        raise AssertionError("no run may start")

    monkeypatch.setattr(study, "run_study", boom)
    monkeypatch.setattr(tune, "tune", boom)
    code = main([a.format(scene=scene, reduced=reduced) for a in argv])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2, err
    assert len(err) == 1 and "a_file" in err[0] and "is a file, not a folder" in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "r.toml", "s.toml"]
