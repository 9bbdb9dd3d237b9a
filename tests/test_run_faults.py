"""Nothing lost on a fault: an output that cannot be written (a writer failing on purpose, its folder
removed mid-run) stops the run with one line naming the file, exit code 1, and every earlier frame
readable (the states from their stream, which ``warpfem recover`` turns into the .npz); a torn last
frame of the stream is not a frame. And the writer protocol: one snapshot per frame, a new format is
one class. (Runs killed with SIGKILL: test_resume.py, which also checks what they leave.)"""

from __future__ import annotations

import errno
import os
import shutil
import sys

import numpy as np
import pytest

from tiny_scenes import cli_beam_toml
from warpfem.cli import main
from warpfem.io import OutputWriteError, read_states, read_usd_mesh_frames
from warpfem.io.states import StatesWriter, stream_directory
from warpfem.io.stats import read_stats
from warpfem.scenes import load_scene

def beam(tmp_path, frames, outputs):
    path = tmp_path / "beam.toml"
    path.write_text(cli_beam_toml(frames=frames) + outputs)
    return str(path)


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
    positions = np.array(d["positions"])
    from warpfem.io import compare_runs

    assert compare_runs("out/beam.npz", "out/beam.npz")["verdict"].startswith("identical")  # reads the stream
    assert main(["recover", "out/beam.npz"]) == 0
    assert not os.path.exists(stream_directory("out/beam.npz"))
    with np.load("out/beam.npz") as z:
        np.testing.assert_array_equal(z["positions"], positions)
        assert sorted(z.files) == ["fps", "positions", "rest", "times"] and len(z["times"]) == 3
    assert main(["recover", scene]) == 0  # the scene's [output] states: nothing left to recover, not an error
    assert "nothing to recover" in capsys.readouterr().out


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
