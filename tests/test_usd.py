"""USD export: animated triangle meshes, metadata, extents, validators, interrupted runs."""

import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

from warpfem.io import UsdMeshWriter, UsdWriterError, read_usd_mesh_frames, usd_validation_errors

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


@pytest.mark.parametrize("ext", [".usda", ".usdc", ".usd"])
def test_write_five_frames(tmp_path, ext):
    from pxr import Usd, UsdGeom, UsdValidation

    path = tmp_path / f"anim{ext}"
    with UsdMeshWriter(path, fps=FPS, up_axis="Z", meters_per_unit=0.01, save_every=2) as w:
        assert w.add_mesh("surface", FACES, len(REST)) == "/Root/surface"
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

    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Root/surface"))
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
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([os.path.dirname(os.path.dirname(os.path.abspath(__file__))),
                                         env.get("PYTHONPATH", "")])
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=120)
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
    mesh = UsdGeom.Mesh(stage.GetPrimAtPath("/Root/surface"))
    assert mesh.GetNormalsInterpolation() == UsdGeom.Tokens.vertex
    assert mesh.GetNormalsAttr().GetTimeSamples() == [0.0, 1.0]
    np.testing.assert_array_equal(np.array(mesh.GetNormalsAttr().Get(1)), -n)
