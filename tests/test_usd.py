"""USD export: animated triangle meshes, metadata, extents, validators, interrupted runs."""

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from warpfem.io import UsdMeshWriter, UsdWriterError, read_usd_mesh_frames, usd_validation_errors

ROOT_PRIM = "/" + "Root"  # the writer's default root prim (root_name), a USD path

FPS = 30
FACES = np.array([[0, 1, 2], [0, 2, 3], [1, 4, 2]])
REST = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0], [2.0, 0.5, 0.3]])


def frame_points(f):
    """A moving, rotating, stretching mesh: bounds differ per frame and per axis."""
    a = 0.3 * f
    R = np.array([[np.cos(a), -np.sin(a), 0.0], [np.sin(a), np.cos(a), 0.0], [0.0, 0.0, 1.0]])
    S = np.diag([1.0 + 0.1 * f, 1.0, 1.0 - 0.05 * f])
    return REST @ (R @ S).T + np.array([0.5 * f, -0.25 * f, 1.0 + 0.125 * f])


def open_stage(path):
    from pxr import Sdf, Usd

    # the writer released its layer: this reads the file from disk
    assert not Sdf.Layer.Find(str(path))
    stage = Usd.Stage.Open(str(path))
    assert stage is not None
    return stage


def warpfem_info(stage):
    return dict(stage.GetRootLayer().customLayerData["warpfem"])


def _run_killed_writer(script):
    """Run a writer script in a fresh Python process (it ends with os._exit, as a kill would)."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                                         env.get("PYTHONPATH", "")])
    return subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("ext", [".usda", ".usdc", ".usd"])
def test_write_five_frames(tmp_path, ext):
    from pxr import Usd, UsdGeom, UsdValidation

    path = tmp_path / f"anim{ext}"
    with UsdMeshWriter(path, fps=FPS, up_axis="Z", meters_per_unit=0.01, save_every=2) as w:
        assert w.add_mesh("surface", FACES, len(REST)) == ROOT_PRIM + "/surface"
        for f in range(5):
            w.write_frame(f, {"surface": frame_points(f)})
        assert w.frames_written == 5 and w.last_frame == 4
    assert w.closed

    stage = open_stage(path)
    assert stage.GetTimeCodesPerSecond() == FPS
    assert stage.GetFramesPerSecond() == FPS
    assert stage.GetStartTimeCode() == 0.0
    assert stage.GetEndTimeCode() == 4.0
    assert UsdGeom.GetStageUpAxis(stage) == UsdGeom.Tokens.z
    assert UsdGeom.GetStageMetersPerUnit(stage) == pytest.approx(0.01)
    root = stage.GetDefaultPrim()
    assert root.GetPath() == "/Root" and root.IsA(UsdGeom.Xform)
    info = warpfem_info(stage)
    assert info["complete"] is True and info["framesWritten"] == 5 and info["lastFrame"] == 4

    mesh = UsdGeom.Mesh(stage.GetPrimAtPath(ROOT_PRIM + "/surface"))
    assert list(mesh.GetFaceVertexCountsAttr().Get()) == [3, 3, 3]
    assert list(mesh.GetFaceVertexIndicesAttr().Get()) == FACES.reshape(-1).tolist()
    assert not mesh.GetFaceVertexIndicesAttr().ValueMightBeTimeVarying()
    pts_attr, ext_attr = mesh.GetPointsAttr(), mesh.GetExtentAttr()
    assert pts_attr.GetTimeSamples() == [0.0, 1.0, 2.0, 3.0, 4.0]
    assert ext_attr.GetTimeSamples() == [0.0, 1.0, 2.0, 3.0, 4.0]
    for f in range(5):
        pts = np.array(pts_attr.Get(f), dtype=np.float64)
        assert pts.shape == (len(REST), 3)
        np.testing.assert_allclose(pts, frame_points(f), atol=1e-6)
        extent = np.array(ext_attr.Get(f), dtype=np.float64)
        np.testing.assert_array_equal(extent, np.stack([pts.min(0), pts.max(0)]))
        # independent check with USD's own extent computation
        computed = np.array(UsdGeom.PointBased.ComputeExtent(pts_attr.Get(f)), dtype=np.float64)
        np.testing.assert_array_equal(extent, computed)
    # frames differ: the extent really is per time sample
    e0, e4 = np.array(ext_attr.Get(0)), np.array(ext_attr.Get(4))
    assert np.abs(e4 - e0).min() > 0.1

    times, frames = read_usd_mesh_frames(path, "surface")
    assert times.tolist() == [0.0, 1.0, 2.0, 3.0, 4.0] and len(frames) == 5
    np.testing.assert_allclose(frames[3], frame_points(3), atol=1e-6)

    # every registered UsdValidation validator, no errors
    registry = UsdValidation.ValidationRegistry()
    context = UsdValidation.ValidationContext(registry.GetOrLoadAllValidators())
    errors = [e for e in context.Validate(stage) if e.GetType() == UsdValidation.ValidationErrorType.Error]
    assert errors == [], [e.GetMessage() for e in errors]
    assert usd_validation_errors(stage) == []


def test_validators_flag_missing_metadata():
    """The validator set really checks something (so 'no errors' above means something)."""
    from pxr import Usd, UsdGeom

    stage = Usd.Stage.CreateInMemory("bare.usda")
    UsdGeom.Mesh.Define(stage, "/m")
    names = {name for _, name, _ in usd_validation_errors(stage)}
    assert {"MissingDefaultPrim", "MissingUpAxisMetadata", "MissingMetersPerUnitMetadata"} <= names


def test_exception_inside_with_block_leaves_readable_file(tmp_path):
    path = tmp_path / "interrupted.usda"
    with pytest.raises(RuntimeError, match="solver diverged"):
        with UsdMeshWriter(path, fps=FPS, save_every=100) as w:
            w.add_mesh("surface", FACES, len(REST))
            for f in range(5):
                if f == 3:
                    raise RuntimeError("solver diverged")
                w.write_frame(f, {"surface": frame_points(f)})
    stage = open_stage(path)
    assert stage.GetStartTimeCode() == 0.0 and stage.GetEndTimeCode() == 2.0
    info = warpfem_info(stage)
    assert info["complete"] is False and info["framesWritten"] == 3
    assert "solver diverged" in info["incompleteReason"]
    times, frames = read_usd_mesh_frames(path, "surface")
    assert times.tolist() == [0.0, 1.0, 2.0]
    np.testing.assert_allclose(frames[2], frame_points(2), atol=1e-6)
    assert usd_validation_errors(stage) == []


def test_killed_process_keeps_periodically_saved_frames(tmp_path):
    """A process killed mid-run (no close, no exception handling) leaves the last saved frames."""
    path = tmp_path / "killed.usdc"
    script = textwrap.dedent(
        f"""
        import os, numpy as np
        from warpfem.io import UsdMeshWriter
        w = UsdMeshWriter({str(path)!r}, fps=24, save_every=2)
        w.add_mesh("tri", np.array([[0, 1, 2]]), 3)
        for f in range(5):
            w.write_frame(f, {{"tri": np.eye(3) * (f + 1)}})
        os._exit(3)  # frame 4 written but not saved; close() never runs
        """
    )
    proc = _run_killed_writer(script)
    assert proc.returncode == 3, proc.stderr
    stage = open_stage(path)
    assert stage.GetEndTimeCode() == 3.0 and stage.GetTimeCodesPerSecond() == 24
    info = warpfem_info(stage)
    assert info["complete"] is False and info["framesWritten"] == 4
    times, frames = read_usd_mesh_frames(path, "tri")
    assert times.tolist() == [0.0, 1.0, 2.0, 3.0]
    np.testing.assert_allclose(frames[3], 4.0 * np.eye(3))


def test_rewrite_existing_file(tmp_path):
    path = tmp_path / "again.usda"
    for scale in (1.0, 2.0):
        with UsdMeshWriter(path, fps=FPS) as w:
            w.add_mesh("surface", FACES, len(REST))
            w.write_frame(0, {"surface": scale * REST})
    times, frames = read_usd_mesh_frames(path, "surface")
    assert times.tolist() == [0.0]
    np.testing.assert_allclose(frames[0], 2.0 * REST, atol=1e-6)


def test_bad_input(tmp_path):
    with pytest.raises(UsdWriterError, match="end in"):
        UsdMeshWriter(tmp_path / "x.obj", fps=FPS)
    with pytest.raises(UsdWriterError, match="fps"):
        UsdMeshWriter(tmp_path / "x.usda", fps=0)
    with pytest.raises(UsdWriterError, match="up_axis"):
        UsdMeshWriter(tmp_path / "x.usda", fps=FPS, up_axis="X")
    with UsdMeshWriter(tmp_path / "x.usda", fps=FPS) as w:
        with pytest.raises(UsdWriterError, match="prim name"):
            w.add_mesh("bad name", FACES, 5)
        with pytest.raises(UsdWriterError, match="face 2"):
            w.add_mesh("m", FACES, 4)
        w.add_mesh("m", FACES, 5)
        with pytest.raises(UsdWriterError, match=r"\(5, 3\)"):
            w.write_frame(0, {"m": REST[:4]})
        with pytest.raises(UsdWriterError, match="unknown mesh"):
            w.write_frame(0, {"other": REST})
        bad = REST.copy()
        bad[1, 2] = np.nan
        with pytest.raises(UsdWriterError, match="point 1"):
            w.write_frame(0, {"m": bad})
        w.write_frame(0, {"m": REST})
        with pytest.raises(UsdWriterError, match="increase"):
            w.write_frame(0, {"m": REST})
    with pytest.raises(UsdWriterError, match="closed"):
        w.write_frame(1, {"m": REST})
    times, _ = read_usd_mesh_frames(tmp_path / "x.usda", "m")
    assert times.tolist() == [0.0]


def test_vertex_normals(tmp_path):
    from pxr import UsdGeom

    path = tmp_path / "normals.usda"
    n = np.tile([0.0, 0.0, 1.0], (len(REST), 1))
    with UsdMeshWriter(path, fps=FPS) as w:
        w.add_mesh("surface", FACES, len(REST))
        for f in range(2):
            w.write_frame(f, {"surface": frame_points(f)}, normals={"surface": n * (1 - 2 * f)})
    stage = open_stage(path)
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath(ROOT_PRIM + "/surface"))
    assert mesh.GetNormalsInterpolation() == UsdGeom.Tokens.vertex
    assert mesh.GetNormalsAttr().GetTimeSamples() == [0.0, 1.0]
    np.testing.assert_array_equal(np.array(mesh.GetNormalsAttr().Get(1)), -n)


# ----------------------------------------------------------------------------- value clips (bounded memory)
def check_frames(stage, name, expected, times):
    """Frame count, point count, points, extents = bounds of the points (and USD's own extent)."""
    from pxr import UsdGeom

    mesh = UsdGeom.Mesh(stage.GetPrimAtPath(f"/Root/{name}"))
    pts_attr, ext_attr = mesh.GetPointsAttr(), mesh.GetExtentAttr()
    assert pts_attr.GetTimeSamples() == list(times) and ext_attr.GetTimeSamples() == list(times)
    for t in times:
        pts = np.array(pts_attr.Get(t), dtype=np.float64)
        assert pts.shape == expected(t).shape
        np.testing.assert_allclose(pts, expected(t), atol=1e-5)
        ext = np.array(ext_attr.Get(t), dtype=np.float64)
        np.testing.assert_array_equal(ext, np.stack([pts.min(0), pts.max(0)]))
        np.testing.assert_array_equal(ext, np.array(UsdGeom.PointBased.ComputeExtent(pts_attr.Get(t))))


def test_value_clips_bound_memory_and_compose(tmp_path):
    from pxr import Sdf

    path = tmp_path / "long.usda"
    clip_dir = tmp_path / "long.clips"
    n_frames, clip = 11, 4
    with UsdMeshWriter(path, fps=FPS, clip_frames=clip, save_every=3) as w:
        w.add_mesh("surface", FACES, len(REST))
        for f in range(n_frames):
            w.write_frame(f, {"surface": frame_points(f)})
            # never more than one clip's frames in memory; full clips are saved and released
            assert w.frames_in_memory() == (f % clip + 1) % clip  # 0 right after a clip is full
            for done in range((f + 1) // clip):
                assert Sdf.Layer.Find(str(clip_dir / f"clip_{done:06d}.usdc")) is None
        assert w.peak_frames_in_memory == clip and w.num_clips == 3
    assert sorted(os.listdir(clip_dir)) == ["clip_000000.usdc", "clip_000001.usdc", "clip_000002.usdc", "manifest.usda"]
    # the main layer holds topology and clip metadata only, no time samples
    main = Sdf.Layer.OpenAsAnonymous(str(path))
    assert main.ListAllTimeSamples() == []
    # each clip holds its frames only
    for i, frames in enumerate([[0, 1, 2, 3], [4, 5, 6, 7], [8, 9, 10]]):
        layer = Sdf.Layer.OpenAsAnonymous(str(clip_dir / f"clip_{i:06d}.usdc"))
        assert sorted(layer.ListAllTimeSamples()) == frames
    stage = open_stage(path)
    assert stage.GetStartTimeCode() == 0.0 and stage.GetEndTimeCode() == n_frames - 1
    info = warpfem_info(stage)
    assert info["complete"] is True and info["framesWritten"] == n_frames and info["clips"] == 3
    check_frames(stage, "surface", frame_points, range(n_frames))
    times, frames = read_usd_mesh_frames(path, "surface")
    assert times.tolist() == list(range(n_frames)) and len(frames) == n_frames
    assert usd_validation_errors(stage) == []


def test_single_file_mode_and_stale_clips_removed(tmp_path):
    from pxr import Sdf

    path = tmp_path / "run.usdc"
    with UsdMeshWriter(path, fps=FPS, clip_frames=2) as w:  # 5 clips
        w.add_mesh("surface", FACES, len(REST))
        for f in range(9):
            w.write_frame(f, {"surface": frame_points(f)})
    assert len(os.listdir(tmp_path / "run.clips")) == 6
    with UsdMeshWriter(path, fps=FPS, clip_frames=2) as w:  # a shorter rerun: the old clips 2..4 go
        w.add_mesh("surface", FACES, len(REST))
        for f in range(3):
            w.write_frame(f, {"surface": 2 * frame_points(f)})
    assert sorted(os.listdir(tmp_path / "run.clips")) == ["clip_000000.usdc", "clip_000001.usdc", "manifest.usda"]
    check_frames(open_stage(path), "surface", lambda t: 2 * frame_points(t), range(3))
    with UsdMeshWriter(path, fps=FPS, clip_frames=None) as w:  # one self-contained file
        w.add_mesh("surface", FACES, len(REST))
        for f in range(3):
            w.write_frame(f, {"surface": frame_points(f)})
        assert w.frames_in_memory() == 3 and w.num_clips == 0
    assert not (tmp_path / "run.clips").exists()
    assert sorted(Sdf.Layer.OpenAsAnonymous(str(path)).ListAllTimeSamples()) == [0.0, 1.0, 2.0]
    stage = open_stage(path)
    check_frames(stage, "surface", frame_points, range(3))
    assert usd_validation_errors(stage) == []
    with pytest.raises(UsdWriterError, match="clip_frames"):
        UsdMeshWriter(tmp_path / "x.usda", fps=FPS, clip_frames=0)


def test_killed_process_mid_clip_keeps_saved_frames(tmp_path):
    """Killed in its second clip: the stage holds the frames up to the last save (clip 1 and the
    saved part of clip 2), end time code = last saved frame."""
    path = tmp_path / "killed.usda"
    script = textwrap.dedent(
        f"""
        import os, numpy as np
        from warpfem.io import UsdMeshWriter
        w = UsdMeshWriter({str(path)!r}, fps=24, save_every=2, clip_frames=4)
        w.add_mesh("tri", np.array([[0, 1, 2]]), 3)
        for f in range(7):
            w.write_frame(f, {{"tri": np.eye(3) * (f + 1)}})
        os._exit(3)  # frames 0-3: a full clip; 4, 5 saved (save_every = 2); 6 not saved
        """
    )
    proc = _run_killed_writer(script)
    assert proc.returncode == 3, proc.stderr
    stage = open_stage(path)
    assert stage.GetEndTimeCode() == 5.0
    info = warpfem_info(stage)
    assert info["complete"] is False and info["framesWritten"] == 6 and info["clips"] == 2
    check_frames(stage, "tri", lambda t: np.eye(3) * (t + 1), range(6))
    assert usd_validation_errors(stage) == []


# ----------------------------------------------------------------------------- npz states, streamed
def test_states_writer_streams_frames_to_disk(tmp_path):
    import tracemalloc

    from warpfem.io import StatesWriter

    rng = np.random.default_rng(0)
    rest = rng.standard_normal((3000, 3))
    frame_bytes = rest.nbytes  # 72 kB
    path = tmp_path / "out" / "states.npz"
    tracemalloc.start()
    try:
        w = StatesWriter(path, rest=rest, max_frames=200, fps=30.0, chunk_bytes=1 << 20)
        tracemalloc.reset_peak()
        for f in range(120):  # 8.6 MB of frames
            w.write_frame(rest + 0.01 * f, f / 30.0)
        peak_writing = tracemalloc.get_traced_memory()[1]
        assert all(os.path.exists(p) for p in w.temporary_files)
        tracemalloc.reset_peak()
        w.close()
        peak_closing = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    # Python memory: a few frames while writing, one 1 MiB chunk while assembling (not 120 frames)
    assert peak_writing < 4 * frame_bytes, peak_writing
    assert peak_closing < (1 << 20) + 4 * frame_bytes, peak_closing
    assert not any(os.path.exists(p) for p in w.temporary_files)
    d = np.load(path)
    assert sorted(d.files) == ["fps", "positions", "rest", "times"]
    assert d["positions"].shape == (120, 3000, 3) and d["fps"] == 30.0
    np.testing.assert_array_equal(d["positions"][57], rest + 0.01 * 57)
    np.testing.assert_array_equal(d["rest"], rest)
    np.testing.assert_allclose(d["times"], np.arange(120) / 30.0)
    # closed early (a failed run): the frames written, nothing more
    with StatesWriter(tmp_path / "short.npz", rest=rest[:5], max_frames=10, fps=1.0) as w:
        w.write_frame(rest[:5], 0.0)
        w.write_frame(rest[:5] + 1, 1.0)
    d = np.load(tmp_path / "short.npz")
    assert d["positions"].shape == (2, 5, 3) and d["times"].tolist() == [0.0, 1.0]
    with pytest.raises(ValueError, match="closed"):
        w.write_frame(rest[:5], 2.0)
