"""`warpfem compare A B` and warpfem.io.compare.compare_runs: two runs' states .npz or USD files
written with the project's writers, one perturbed by a known displacement field; the RMS, max,
where it occurs and the relative numbers exactly; different frame rates (linear interpolation,
exact on a motion linear in time); the errors and exit codes."""

import json

import numpy as np
import pytest

from warpfem.cli import main
from warpfem.io import StatesWriter, UsdMeshWriter
from warpfem.io.compare import CompareError, compare_runs

N = 12  # points
FPS = 20.0
FRAMES = 8
SHIFT = np.array([1e-3, 0.0, 0.0])  # rigid translation of B from frame 2 on (m)
SPIKE_FRAME, SPIKE_POINT, SPIKE = 5, 7, np.array([0.0, 4e-3, 3e-3])  # and one point 5 mm further
VELOCITY = np.array([0.8, -0.3, 0.1])  # m/s: the motion common to both, linear in time

FACES = np.array([[0, 1, 2], [2, 3, 4], [4, 5, 6], [6, 7, 8], [8, 9, 10], [10, 11, 0]])


def rest_points():
    i = np.arange(N, dtype=np.float64)
    return np.stack([0.1 * i, 0.05 * (i % 3), 0.02 * (i % 4)], axis=1)  # 1.1 m x 0.1 m x 0.06 m


def trajectory(fps=FPS, frames=FRAMES, perturbed=False, offset=None):
    """[(time, (N, 3) points)]: rest + VELOCITY t, B's perturbation, an optional constant offset."""
    out = []
    for k in range(frames):
        t = k / fps
        x = rest_points() + VELOCITY * t
        if perturbed and k >= 2:
            x = x + SHIFT
        if perturbed and k == SPIKE_FRAME:
            x[SPIKE_POINT] += SPIKE
        if offset is not None:
            x = x + offset
        out.append((t, x))
    return out


def write_states(path, traj, fps=FPS, extra=None):
    with StatesWriter(path, rest=rest_points(), max_frames=len(traj), fps=fps, extra=extra) as w:
        for t, x in traj:
            w.write_frame(x, t)
    return str(path)


def write_usd(path, traj, fps=FPS, collider_shift=0.0, clip_frames=3):
    with UsdMeshWriter(path, fps=fps, clip_frames=clip_frames, save_every=2) as w:
        w.add_mesh("surface", FACES, N)
        w.add_mesh("collider_floor", FACES, N)
        for k, (_, x) in enumerate(traj):
            w.write_frame(k, {"surface": x, "collider_floor": rest_points() + collider_shift})
    return str(path)


def expected(xa_frames, xb_frames):
    """The numbers computed directly: (rms, max, frame of max, point of max, diagonal, per-frame rms)."""
    d = np.stack([np.linalg.norm(np.asarray(b, np.float64) - np.asarray(a, np.float64), axis=1)
                  for a, b in zip(xa_frames, xb_frames)])
    k, p = np.unravel_index(int(np.argmax(d)), d.shape)
    diag = float(np.linalg.norm(np.ptp(np.asarray(xa_frames[0], np.float64), axis=0)))
    return float(np.sqrt(np.mean(d ** 2))), float(d.max()), int(k), int(p), diag, np.sqrt(np.mean(d ** 2, axis=1))


def test_states_rigid_shift_and_one_point_exactly(tmp_path):
    a = write_states(tmp_path / "a.npz", trajectory())
    b = write_states(tmp_path / "b.npz", trajectory(perturbed=True))
    r = compare_runs(a, b)
    assert [it["name"] for it in r["items"]] == ["positions"]
    it = r["items"][0]
    # by hand: frames 0, 1 agree; frames 2..7 every point 1 mm off, point 7 at frame 5 |SHIFT + SPIKE|
    spike = float(np.linalg.norm(SHIFT + SPIKE))
    sq = (FRAMES - 2) * N * 1e-6 - 1e-6 + spike ** 2
    rms = np.sqrt(sq / (FRAMES * N))
    diag = float(np.linalg.norm(np.ptp(rest_points(), axis=0)))
    assert it["points"] == N and it["frames"] == FRAMES
    assert it["bbox_diagonal"] == pytest.approx(diag, abs=1e-12)
    assert abs(it["rms"] - rms) < 1e-12 and abs(it["max"] - spike) < 1e-12
    assert abs(it["rms_relative"] - rms / diag) < 1e-12 and abs(it["max_relative"] - spike / diag) < 1e-12
    assert (it["max_frame"], it["max_point"]) == (SPIKE_FRAME, SPIKE_POINT)
    assert it["max_time"] == pytest.approx(SPIKE_FRAME / FPS, abs=1e-12)
    per_frame = [0.0, 0.0] + [1e-3] * (FRAMES - 2)
    per_frame[SPIKE_FRAME] = np.sqrt(((N - 1) * 1e-6 + spike ** 2) / N)
    np.testing.assert_allclose(it["rms_per_frame"], per_frame, rtol=0, atol=1e-12)
    assert [s["frame"] for s in it["series"]] == [0, 2, 4, 5, 7]  # 5 evenly spaced of 8 (rounded)
    assert it["matching"]["interpolated_frames"] == 0 and it["matching"]["sampled_at"] == "A"
    assert r["verdict"].startswith("small: ") and "positions" in r["verdict"]
    # identical runs
    same = compare_runs(a, a)
    assert same["items"][0]["rms"] == 0.0 and same["items"][0]["max"] == 0.0
    assert same["verdict"].startswith("identical")


def test_states_of_several_bodies_per_body(tmp_path):
    extra = {"body_offsets": np.array([0, 5, N]), "body_names": np.array(["left", "right"])}
    a = write_states(tmp_path / "a.npz", trajectory(), extra=extra)
    b = write_states(tmp_path / "b.npz", trajectory(perturbed=True), extra=extra)
    r = compare_runs(a, b)
    assert [it["name"] for it in r["items"]] == ["positions", "left", "right"]
    left, right = r["items"][1], r["items"][2]
    assert left["points"] == 5 and right["points"] == N - 5
    assert abs(left["max"] - 1e-3) < 1e-12 and right["max_point"] == SPIKE_POINT - 5
    only = compare_runs(a, b, prim="right")
    assert [it["name"] for it in only["items"]] == ["right"] and only["items"][0]["max"] == right["max"]


def test_usd_with_clips_colliders_excluded_unless_named(tmp_path):
    ta, tb = trajectory(), trajectory(perturbed=True)
    a = write_usd(tmp_path / "a.usda", ta)
    b = write_usd(tmp_path / "b.usdc", tb, collider_shift=np.array([0.0, 2e-3, 0.0]))
    r = compare_runs(a, b)
    assert [it["name"] for it in r["items"]] == ["/Root/surface"]
    assert r["skipped"] == [{"name": "/Root/collider_floor", "why": "a collider; name it with prim to compare it"}]
    it = r["items"][0]
    # USD points are float32: the expected numbers from the float32 values the files hold
    xa = [x.astype(np.float32) for _, x in ta]
    xb = [x.astype(np.float32) for _, x in tb]
    rms, mx, k, p, diag, per_frame = expected(xa, xb)
    assert abs(it["rms"] - rms) < 1e-9 and abs(it["max"] - mx) < 1e-9
    assert abs(it["rms_relative"] - rms / diag) < 1e-9 and abs(it["max_relative"] - mx / diag) < 1e-9
    assert abs(it["bbox_diagonal"] - diag) < 1e-9
    assert (it["max_frame"], it["max_point"]) == (SPIKE_FRAME, SPIKE_POINT) == (k, p)
    assert abs(it["max_time"] - SPIKE_FRAME / FPS) < 1e-12
    np.testing.assert_allclose(it["rms_per_frame"], per_frame, rtol=0, atol=1e-9)
    assert abs(it["max"] - np.linalg.norm(SHIFT + SPIKE)) < 1e-6  # and it is the field put in
    # a collider when named (by name or path), with the surface
    r2 = compare_runs(a, b, prim=["collider_floor", "/Root/surface"])
    assert [it["name"] for it in r2["items"]] == ["/Root/collider_floor", "/Root/surface"]
    col = r2["items"][0]
    assert abs(col["max"] - 2e-3) < 1e-6 and abs(col["rms"] - 2e-3) < 1e-6 and r2["skipped"] == []


def test_different_frame_rates_interpolate_the_finer_linearly(tmp_path):
    """A at 20 fps, B at 30 fps with a constant 1 mm offset on a motion linear in time: compared at
    A's times, B interpolated where it has no frame (t = 0.05, 0.15, 0.25 s), and exactly 1 mm
    everywhere (the nearest frame instead would be 8.8 mm off at 0.86 m/s)."""
    offset = np.array([0.0, 0.0, 1e-3])
    a = write_states(tmp_path / "a.npz", trajectory(fps=20.0, frames=6))
    b = write_states(tmp_path / "b.npz", trajectory(fps=30.0, frames=10, offset=offset), fps=30.0)
    for first, second, at in ((a, b, "A"), (b, a, "B")):
        r = compare_runs(first, second)
        it = r["items"][0]
        m = it["matching"]
        assert m["sampled_at"] == at and m["interpolated_frames"] == 3 and it["frames"] == 6
        np.testing.assert_allclose(it["times"], np.arange(6) / 20.0, rtol=0, atol=1e-12)
        assert abs(it["rms"] - 1e-3) < 1e-9 and abs(it["max"] - 1e-3) < 1e-9
        np.testing.assert_allclose(it["rms_per_frame"], 1e-3, rtol=0, atol=1e-9)
    # USD too (time codes over timeCodesPerSecond), the coarser one covering less time
    ua = write_usd(tmp_path / "a.usda", trajectory(fps=20.0, frames=6), fps=20.0)
    ub = write_usd(tmp_path / "b.usda", trajectory(fps=30.0, frames=7, offset=offset), fps=30.0)
    r = compare_runs(ua, ub)
    it = r["items"][0]
    assert it["frames"] == 5 and it["matching"]["interpolated_frames"] == 2  # up to t = 0.2 s, B's last
    assert abs(it["rms"] - 1e-3) < 1e-6 and abs(it["max"] - 1e-3) < 1e-6  # float32 points


def test_cli_prints_and_writes_json(tmp_path, capsys):
    a = write_usd(tmp_path / "a.usda", trajectory())
    b = write_usd(tmp_path / "b.usda", trajectory(perturbed=True))
    out = tmp_path / "sub" / "cmp.json"
    assert main(["compare", a, b, "--json", str(out)]) == 0
    text = capsys.readouterr().out
    lines = text.strip().splitlines()
    assert lines[0].startswith("A: ") and lines[1].startswith("B: ") and lines[2].startswith("times: 8 compared")
    assert any(ln.startswith("/Root/surface: 12 points") for ln in lines)
    assert f"(frame {SPIKE_FRAME} of A), point {SPIKE_POINT}" in text and "RMS over time: " in text
    assert "not compared: /Root/collider_floor: a collider; name it with --prim" in text
    assert lines[-1].startswith("verdict: small: ")
    saved = json.loads(out.read_text())
    direct = compare_runs(a, b)
    assert saved["items"][0]["rms"] == direct["items"][0]["rms"] and saved["verdict"] == direct["verdict"]
    # different rates: the line says which was interpolated
    c = write_states(tmp_path / "c.npz", trajectory(fps=30.0, frames=10), fps=30.0)
    d = write_states(tmp_path / "d.npz", trajectory(fps=20.0, frames=6))
    assert main(["compare", c, d]) == 0
    assert "at B's frames; A interpolated linearly at 3 of them (A at 30 fps, B at 20 fps)" in capsys.readouterr().out


def _fails(capsys, argv, *phrases):
    assert main(["compare", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("warpfem: error: "), err
    for p in phrases:
        assert p in err, err
    return err


def test_errors_exit_2_with_one_line(tmp_path, capsys):
    a = write_states(tmp_path / "a.npz", trajectory())
    u = write_usd(tmp_path / "u.usda", trajectory())
    _fails(capsys, [a, str(tmp_path / "missing.npz")], "missing.npz: no such file")
    (tmp_path / "x.vtu").write_text("")
    _fails(capsys, [a, str(tmp_path / "x.vtu")], "unknown format '.vtu'")
    _fails(capsys, [a, u], "is a states file", "a USD file")
    # different point counts, named both
    with StatesWriter(tmp_path / "small.npz", rest=rest_points()[:9], max_frames=2, fps=FPS) as w:
        w.write_frame(rest_points()[:9], 0.0)
        w.write_frame(rest_points()[:9], 0.05)
    _fails(capsys, [a, str(tmp_path / "small.npz")], "has 12 points", "has 9")
    # no common time
    late = [(t + 10.0, x) for t, x in trajectory()]
    late_path = write_states(tmp_path / "late.npz", late)
    _fails(capsys, [a, late_path], "no common time", "t = 10 .. 10.35 s")
    # an unknown prim, and a USD pair sharing none
    _fails(capsys, [u, u, "--prim", "nope"], "no animated prim 'nope'")
    with UsdMeshWriter(tmp_path / "other.usda", fps=FPS) as w:
        w.add_mesh("elsewhere", FACES, N)
        w.write_frame(0, {"elsewhere": rest_points()})
    _fails(capsys, [u, str(tmp_path / "other.usda")], "nothing to compare")
    # a .npz that is not a states file
    np.savez(tmp_path / "plain.npz", x=np.zeros(3))
    _fails(capsys, [a, str(tmp_path / "plain.npz")], "not a warpfem states file")
    with pytest.raises(CompareError):
        compare_runs(a, tmp_path / "missing.npz")
