"""Strict device mode (``WARPFEM_STRICT_DEVICE=1``, warpfem.transfer): the CPU behaves like a
discrete device, so the code paths written for CUDA run here. The device test subset
(tests/device_subset.txt) runs again in that mode, and the GPU check (``make gpu-check``) is
checked by reading: what it would run exists, and without a GPU it says so in one line."""

from __future__ import annotations

import ast
import os
import subprocess
import sys

import numpy as np
import pytest
import warp as wp

import warpfem as wf
from warpfem import transfer as T
from warpfem.transfer import read, read_int, read_scalar, strict_device_mode, to_device, upload

from conftest import ROOT, device_subset


def test_reads_are_copies_and_uploads_the_only_way_in_under_strict_mode():
    a = to_device(np.arange(12, dtype=np.float64).reshape(4, 3), wp.vec3d, "cpu")
    r0, u0 = T.COUNTERS["reads"], T.COUNTERS["uploads"]
    with strict_device_mode():
        assert T.strict_device() and not T.host_aliases("cpu")
        h = read(a)
        h[:] = -1.0  # a copy: the device array is untouched
        np.testing.assert_array_equal(read(a), np.arange(12.0).reshape(4, 3))
        np.testing.assert_array_equal(read(a, 2), np.arange(6.0).reshape(2, 3))
        upload(a, np.ones(12, dtype=np.float32))  # cast and reshaped into the array's layout
        np.testing.assert_array_equal(read(a), np.ones((4, 3)))
        i = to_device(np.array([3, 5, 7], dtype=np.int32), wp.int32, "cpu")
        f = to_device(np.array([0.5, 1.5]), wp.float64, "cpu")
        assert read_int(i, 1) == 5 and read_int(i, -1) == 7 and read_scalar(f, 1) == 1.5
        with pytest.raises(ValueError, match="upload: 5 values for a device array of shape"):
            upload(a, np.zeros(5))
    assert T.COUNTERS["reads"] - r0 == 7 and T.COUNTERS["uploads"] - u0 == 3  # every crossing counted
    # outside strict mode the CPU read is the array's memory (what strict mode takes away)
    with strict_device_mode(False):
        read(a)[0] = (9.0, 9.0, 9.0)
        assert read_scalar(to_device(np.array([2.5]), wp.float64, "cpu")) == 2.5
    np.testing.assert_array_equal(a.numpy()[0], [9.0, 9.0, 9.0])


def test_the_environment_switch(monkeypatch):
    previous = T.set_strict_device(None)  # back to the environment's setting
    try:
        monkeypatch.setenv("WARPFEM_STRICT_DEVICE", "yes")
        assert T.strict_device()
        T.set_strict_device(None)
        monkeypatch.setenv("WARPFEM_STRICT_DEVICE", "0")
        assert not T.strict_device()
        T.set_strict_device(None)
        monkeypatch.setenv("WARPFEM_STRICT_DEVICE", "maybe")
        with pytest.raises(ValueError, match="WARPFEM_STRICT_DEVICE='maybe': expected 1 or 0"):
            T.strict_device()
    finally:
        monkeypatch.setenv("WARPFEM_STRICT_DEVICE", "0")
        T.set_strict_device(previous)


def _beam_sim(**kw):
    mesh = wf.box_tet_mesh(size=(1.0, 0.2, 0.2), cells=(8, 2, 2))
    model = wf.Model(mesh, wf.StableNeoHookean(youngs_modulus=1e6, poisson_ratio=0.3, density=1000.0),
                     gravity=(0.0, 0.0, -9.81))
    model.fix(np.flatnonzero(mesh.vertices[:, 0] < 1e-9))
    return wf.Simulator(model, dt=1 / 60, tol=1e-8, cg_tol=1e-6, **kw)


@pytest.mark.parametrize("linear_solver", ["pcg", "direct"])
def test_the_cuda_code_paths_give_the_cpu_paths_numbers_bit_for_bit(linear_solver):
    """PCG: chunks of launches captured as a graph and replayed (CUDA's path) against the serial
    one-launch solve (the CPU's): the same operations in the same order. Direct: the solution
    uploaded through a staging copy against written into the array's memory."""

    def run(strict):
        with strict_device_mode(strict):
            sim = _beam_sim(linear_solver=linear_solver)
            xs, syncs = [], 0
            for _ in range(4):
                st = sim.step()
                syncs += st.newton_syncs
                xs.append(sim.positions())
        return sim, np.array(xs), syncs

    cpu, x_cpu, syncs_cpu = run(False)
    dev, x_dev, syncs_dev = run(True)
    if linear_solver == "pcg":
        assert cpu._pcg.cpu_serial and not dev._pcg.cpu_serial
        assert dev._pcg._graph is not None  # the chunk was captured and replayed
    np.testing.assert_array_equal(x_dev, x_cpu)
    assert syncs_dev == syncs_cpu  # one read-back per Newton iteration either way


def test_auto_chooses_as_on_cuda_in_strict_mode():
    with strict_device_mode(False):
        assert _beam_sim()._pcg.active == "direct"  # a small CPU system: the host's direct solver
    with strict_device_mode():
        sim = _beam_sim()
        assert sim._pcg.active == "pcg" and "direct" not in sim._pcg.candidates


def test_the_device_subset_passes_in_strict_mode():
    """tests/device_subset.txt again with WARPFEM_STRICT_DEVICE=1 (one child pytest)."""
    env = dict(os.environ, WARPFEM_STRICT_DEVICE="1")
    env.pop("WARPFEM_TEST_DEVICE", None)
    r = subprocess.run([sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", *device_subset()],
                       cwd=ROOT, env=env, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stdout[-4000:] + r.stderr[-2000:]


def test_the_device_subset_names_existing_tests():
    ids = device_subset()
    assert len(ids) == len(set(ids)) >= 10
    for node in ids:
        path, _, name = node.partition("::")
        src = (ROOT / path).read_text()
        tree = ast.parse(src)
        names = {n.name for n in ast.walk(tree) if isinstance(n, (ast.FunctionDef, ast.ClassDef))}
        assert name.split("[")[0] in names, node


def test_gpu_check_without_a_gpu_says_so_in_one_line(tmp_path, capsys):
    sys.path.insert(0, str(ROOT / "kernels_bench"))
    try:
        import gpu_check
        import run_all
    finally:
        sys.path.remove(str(ROOT / "kernels_bench"))
    # what it would run, checked by reading: the scripts exist and take the flags passed
    cmds = gpu_check.plan("cuda:0", tmp_path)
    assert set(cmds) == {name for name, _ in gpu_check.STAGES}
    assert sum(limit for _, limit in gpu_check.STAGES) <= 480
    for name, argv in cmds.items():
        script = next((a for a in argv if a.endswith(".py")), None)
        if script is None:  # pytest: the subset, on the device
            assert argv[1:3] == ["-m", "pytest"] and argv[argv.index("--device") + 1] == "cuda:0"
            continue
        src = open(script).read()
        for flag in (a for a in argv if a.startswith("--")):
            assert f'"{flag}"' in src, (name, flag)
    names = {p[0] for p in run_all.plan(type("A", (), {"quick": True, "device": "cuda:0"})(), tmp_path)}
    assert set(gpu_check.RUN_ALL) <= names
    if wp.get_cuda_device_count() > 0:
        pytest.skip("a CUDA device is present: make gpu-check runs for real")
    assert gpu_check.main(["--out", str(tmp_path / "cuda")]) == 0
    out = capsys.readouterr().out
    assert out == "gpu-check: no CUDA device here (no NVIDIA driver or GPU); nothing run\n"
    assert not (tmp_path / "cuda").exists()
