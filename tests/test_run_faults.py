"""Nothing lost on a fault: a run killed with SIGKILL (a real subprocess) leaves every output readable
with every frame finished before the kill (the states file through its stream, which ``warpfem
recover`` turns into the .npz); an output that cannot be written (a writer failing on purpose, its
folder removed mid-run) stops the run with one line naming the file, exit code 1, and every earlier
frame readable. And the writer protocol: one snapshot per frame, a new format is one class."""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from tiny_scenes import cli_beam_toml
from warpfem.cli import main
from warpfem.io import OutputWriteError, read_states, read_usd_mesh_frames
from warpfem.io.states import StatesWriter, stream_directory
from warpfem.io.stats import read_stats
from warpfem.scenes import load_scene

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def beam(tmp_path, frames, outputs):
    path = tmp_path / "beam.toml"
    path.write_text(cli_beam_toml(frames=frames) + outputs)
    return str(path)


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


def test_sigkill_leaves_every_finished_frame_readable(tmp_path):
    """Killed once the 6th frame's statistics are written (frames 0..5 finished, the kill lands anywhere
    in frame 6's writing): states (from its stream), USD, ParaView collection and statistics log each
    hold at least frames 0..5, with the right times; ``warpfem recover`` writes the npz with exactly the
    stream's arrays and removes the stream."""
    scene = beam(tmp_path, 100000, 'usd = "out/beam.usda"\nstates = "out/beam.npz"\nvtu = "out/beam.pvd"\n'
                                   "clip_frames = 3\n")
    run_until_killed(scene, tmp_path / "out" / "beam.stats.jsonl", 6, tmp_path)
    npz = tmp_path / "out" / "beam.npz"
    assert not npz.exists() and os.path.isdir(stream_directory(npz))
    d = read_states(npz)
    k = len(d["times"])
    assert d["complete"] is False and k >= 6 and d["positions"].shape == (k, 20, 3)
    np.testing.assert_allclose(d["times"], np.arange(k) / 20.0, rtol=1e-12)
    assert np.all(np.isfinite(d["positions"])) and d["positions"][-1, :, 1].min() < d["rest"][:, 1].min()
    stats = read_stats(tmp_path / "out" / "beam.stats.jsonl")
    assert len(stats) >= 6 and [r["frame"] for r in stats] == list(range(1, len(stats) + 1))
    times, frames = read_usd_mesh_frames(tmp_path / "out" / "beam.usda", "boundary")
    assert len(times) >= 6 and times.tolist() == list(range(len(times)))  # the USD is saved with every frame
    from warpfem.io import read_pvd

    entries, meta = read_pvd(tmp_path / "out" / "beam.pvd")
    assert len(entries) >= 6 and meta["complete"] is False
    positions = np.array(d["positions"])
    assert main(["recover", str(npz)]) == 0
    assert not os.path.exists(stream_directory(npz))
    with np.load(npz) as z:
        np.testing.assert_array_equal(z["positions"], positions)
        assert sorted(z.files) == ["fps", "positions", "rest", "times"]


def test_failing_writer_one_line_exit_1_earlier_frames_kept(tmp_path, monkeypatch, capsys):
    """The states writer fails (a full disk) at frame 3: exit code 1, one line naming the file and the
    frame; the states stream holds frames 0..2 exactly, the USD frames 0..2 marked incomplete."""
    scene = beam(tmp_path, 6, 'usd = "out/beam.usda"\nstates = "out/beam.npz"\n')
    real = StatesWriter.write_frame

    def write_frame(self, positions, t):
        if self.frames_written == 3:
            raise OSError(errno.ENOSPC, "No space left on device", self._pos_path)
        return real(self, positions, t)

    monkeypatch.chdir(tmp_path)
    monkeypatch.setattr(StatesWriter, "write_frame", write_frame)
    assert main(["run", scene, "--quiet"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert "out/beam.npz" in err[0] and "frame 3" in err[0] and "No space left on device" in err[0], err
    d = read_states("out/beam.npz")
    assert d["complete"] is False and d["times"].tolist() == [0.0, 0.05, 0.1]
    times, _ = read_usd_mesh_frames("out/beam.usda", "boundary")
    assert times.tolist() == [0.0, 1.0, 2.0]
    from pxr import Sdf

    info = Sdf.Layer.FindOrOpen(str(tmp_path / "out" / "beam.usda")).customLayerData["warpfem"]
    assert info["complete"] is False and "OutputWriteError" in info["incompleteReason"]


def test_output_folder_removed_mid_run(tmp_path):
    """The USD's folder is removed after frame 3: OutputWriteError naming the USD and frame 4; the
    states file (another folder) is complete with frames 0..4, the last one written."""
    scene = beam(tmp_path, 8, f'usd = "{tmp_path}/o1/b.usda"\nstates = "{tmp_path}/o2/b.npz"\nclip_frames = 3\n')
    run = load_scene(scene).build()

    def progress(fs):
        if fs.frame == 3:
            shutil.rmtree(tmp_path / "o1")

    with pytest.raises(OutputWriteError, match=r"o1/b\.usda: cannot write frame 4") as e:
        run.run(progress=progress)
    assert "\n" not in str(e.value)
    d = read_states(tmp_path / "o2" / "b.npz")
    assert d["complete"] is True and len(d["times"]) == 5


def test_states_stream_survives_a_torn_last_frame(tmp_path):
    """A frame cut short on disk (positions without its time) is not a frame: the reader skips it and
    a writer continuing the stream appends after the last whole frame."""
    rest = np.arange(12.0).reshape(4, 3)
    w = StatesWriter(tmp_path / "s.npz", rest=rest, max_frames=10, fps=2.0)
    for f in range(3):
        w.write_frame(rest + f, f / 2.0)
    w._pos.write(b"\0" * 40)  # half a frame, then the process dies
    w._pos.flush()
    d = read_states(tmp_path / "s.npz")
    assert len(d["times"]) == 3 and d["positions"].shape == (3, 4, 3)
    w2 = StatesWriter(tmp_path / "s.npz", rest=rest, max_frames=10, fps=2.0, keep_frames=2)
    w2.write_frame(rest + 7, 1.0)
    w2.close()
    with np.load(tmp_path / "s.npz") as z:
        np.testing.assert_array_equal(z["positions"], [rest, rest + 1, rest + 7])


def test_a_new_output_format_is_one_writer_class(tmp_path, monkeypatch):
    """A FrameWriter registered in OUTPUT_FORMATS gets one snapshot per frame (frames 0..N, the run's
    times, positions equal to the states file's) and close(complete=True)."""
    from warpfem.io import FrameWriter
    from warpfem.io import outputs

    seen = {}

    class Recorder(FrameWriter):
        label = "recorder"

        def open(self, run):
            seen["open"] = (run.fps, run.total_frames, run.resume_after)
            seen["frames"] = []

        def write(self, snapshot):
            seen["frames"].append((snapshot.frame, snapshot.time, snapshot.positions.copy()))

        def close(self, complete, reason=None):
            seen["closed"] = (complete, reason)

    sys.modules[__name__].Recorder = Recorder
    monkeypatch.setitem(outputs.OUTPUT_FORMATS, "states", f"{__name__}:Recorder")
    scene = beam(tmp_path, 3, f'states = "{tmp_path}/r.bin"\n')
    run = load_scene(scene).build()
    run.run(checkpoint_every=0)
    assert seen["open"] == (20.0, 3, None) and seen["closed"] == (True, None)
    assert [f for f, _, _ in seen["frames"]] == [0, 1, 2, 3]
    assert [t for _, t, _ in seen["frames"]] == pytest.approx([0.0, 0.05, 0.1, 0.15])
    np.testing.assert_array_equal(seen["frames"][0][2], run.model.rest_positions)
