"""First-contact behaviour: device names, ``python -m warpfem``, one version, progress with ETA,
logging instead of print, the mesh loader's warnings shown by describe/run, tomllib fallback."""

import ast
import os
import subprocess
import sys
import textwrap

import numpy as np
import pytest

import warpfem
from warpfem.cli import main
from warpfem.device import DeviceError, resolve_device
from warpfem.progress import Progress, format_duration

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

SCENE = """
gravity = [0.0, -9.81, 0.0]
[mesh]
{mesh}
[material]
model = "stable_neo_hookean"
youngs_modulus = 1e5
poisson_ratio = 0.3
[[fixed]]
box_min = [-1.0, -1.0, -1.0]
box_max = [0.0, 1.0, 1.0]
[integrator]
type = "backward_euler"
dt = 0.025
[output]
fps = 20
frames = 2
"""
BOX = 'generator = "box"\nsize = [1.0, 0.2, 0.2]\ncells = [4, 1, 1]'


def write(tmp_path, text, name="s.toml"):
    p = tmp_path / name
    p.write_text(textwrap.dedent(text))
    return str(p)


def cuda_count():
    import warp as wp

    return wp.get_cuda_device_count()


# ----------------------------------------------------------------------------- devices
def test_resolve_device_names():
    assert resolve_device("cpu") == "cpu" and resolve_device("CPU") == "cpu"
    expected_auto = "cpu" if cuda_count() == 0 else resolve_device("cuda")
    assert resolve_device("auto") == expected_auto
    with pytest.raises(DeviceError) as e:
        resolve_device("gpu")
    msg = str(e.value)
    assert msg.startswith("unknown device 'gpu'") and "available: cpu" in msg and "(and 'auto')" in msg
    if cuda_count() <= 7:
        with pytest.raises(DeviceError, match=r"'cuda:7' is not available.*available: cpu"):
            resolve_device("cuda:7")
    if cuda_count() == 0:
        with pytest.raises(DeviceError, match="no CUDA device here"):
            resolve_device("cuda")
    with pytest.raises(DeviceError, match="must be a name"):
        resolve_device(3)


def test_simulators_check_device_first():
    mesh = warpfem.box_tet_mesh(size=(1, 0.2, 0.2), cells=(2, 1, 1))
    model = warpfem.Model(mesh, warpfem.StableNeoHookean(youngs_modulus=1e5, poisson_ratio=0.3, density=1000.0))
    for cls in (warpfem.Simulator, warpfem.StiffnessWarpingSimulator):
        with pytest.raises(DeviceError, match="unknown device 'gpu'.*available: cpu"):
            cls(model, device="gpu")
    from warpfem.reduced.simulator import CubatureForces

    U = np.zeros((3 * mesh.num_vertices, 1))
    with pytest.raises(DeviceError, match="unknown device 'gpu'"):
        CubatureForces(model, U, np.array([0]), np.array([1.0]), device="gpu")
    sim = warpfem.Simulator(model, device="auto")
    assert sim.device.alias == resolve_device("auto")


def test_bad_device_on_the_command_line_is_an_invalid_command_line(tmp_path, capsys):
    missing = str(tmp_path / "nowhere.toml")  # the device is checked before the scene is read
    for cmd in ("run", "train", "tradeoff"):
        assert main([cmd, missing, "--device", "gpu"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and "error: unknown device 'gpu'" in err and "available: cpu" in err, err
        assert "(and 'auto')" in err and "nowhere" not in err
    # Python API: a scene build names the device, not the scene
    scene = warpfem.scenes.load_scene(write(tmp_path, SCENE.format(mesh=BOX)))
    with pytest.raises(DeviceError, match="unknown device 'gpu'"):
        scene.build(device="gpu")


def test_bad_device_subprocess_exit_code(tmp_path):
    r = subprocess.run([sys.executable, "-m", "warpfem", "run", str(tmp_path / "x.toml"), "--device", "gpu"],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2 and r.stdout == ""
    assert r.stderr.strip().startswith("warpfem: error: unknown device 'gpu'") and "available: cpu" in r.stderr
    assert r.stderr.strip().count("\n") == 0, r.stderr  # Warp's "no CUDA driver" note is not shown


def test_cuda_without_a_gpu_is_one_clean_line(tmp_path):
    """``--device cuda`` where no CUDA device exists: one line naming the device and why, and not
    Warp's native "no CUDA driver" note before it (on a machine with a GPU: the run starts)."""
    if cuda_count() > 0:
        pytest.skip("a CUDA device is present")
    r = subprocess.run([sys.executable, "-m", "warpfem", "run", str(tmp_path / "x.toml"), "--device", "cuda"],
                       capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2 and r.stdout == ""
    err = r.stderr.strip()
    assert err.count("\n") == 0 and "Warp CUDA warning" not in err, err
    assert err.startswith("warpfem: error: device 'cuda' is not available: no CUDA device here") and "available: cpu" in err


# ----------------------------------------------------------------------------- version, python -m
def test_python_m_warpfem_version_is_the_package_version():
    r = subprocess.run([sys.executable, "-m", "warpfem", "--version"], capture_output=True, text=True, cwd=ROOT,
                       timeout=120)
    assert r.returncode == 0 and r.stdout.strip() == f"warpfem {warpfem.__version__}"
    from importlib.metadata import PackageNotFoundError, version

    try:
        assert version("warpfem") == warpfem.__version__
    except PackageNotFoundError:  # a source tree without `pip install -e .`
        pass
    try:
        import tomllib
    except ModuleNotFoundError:  # Python < 3.11
        import tomli as tomllib
    with open(os.path.join(ROOT, "pyproject.toml"), "rb") as f:
        project = tomllib.load(f)
    assert "version" not in project["project"] and "version" in project["project"]["dynamic"]
    assert project["tool"]["setuptools"]["dynamic"]["version"] == {"attr": "warpfem.__version__"}
    deps = project["project"]["dependencies"]
    assert any(d.startswith("tomli") and "python_version < '3.11'" in d for d in deps)
    assert any(d.startswith("rich") for d in deps)


# ----------------------------------------------------------------------------- progress
def test_progress_plain_lines_with_eta():
    t = iter([0.0, 10.0, 11.0, 12.0, 12.4, 13.0])  # the first frame includes compilation
    lines = []
    p = Progress(4, unit="frame", bar=False, write=lines.append, clock=lambda: next(t))
    # units 1..3 finish at 10, 11, 12 s; each update reads the clock at t_first, elapsed, eta
    p.update(1, "a")  # t_first = 10; elapsed 11 - 0; eta uses 12: 12 / 1 * 3 = 36 s
    assert lines[-1].startswith("[######..................] frame 1/4  a  elapsed 0:00:11  ETA 0:00:36")
    p.update(2, "b")  # elapsed 12.4; eta: (13 - 10) / 1 * 2 = 6 s (the first unit excluded)
    assert lines[-1] == "[############............] frame 2/4  b  elapsed 0:00:12  ETA 0:00:06"
    assert format_duration(3725) == "1:02:05" and format_duration(float("inf")) == "-:--:--"
    quiet = []
    Progress(3, enabled=False, write=quiet.append).update(1)
    assert quiet == []


# ----------------------------------------------------------------------------- mesh warnings
def bad_mesh(path):
    """Two tets sharing a face, the second negatively oriented, and an unreferenced vertex 5."""
    import meshio

    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1], [5, 5, 5]], dtype=np.float64) * 0.2
    tets = np.array([[0, 1, 2, 3], [1, 3, 2, 4]])  # (1, 3, 2, 4) has negative volume
    x = pts[tets[1]]
    assert np.linalg.det(np.stack([x[1] - x[0], x[2] - x[0], x[3] - x[0]])) < 0
    meshio.write(path, meshio.Mesh(pts, [("tetra", tets)]))


def test_describe_and_run_show_the_mesh_loader_warnings(tmp_path, capsys):
    bad_mesh(str(tmp_path / "m.vtu"))
    scene = write(tmp_path, SCENE.format(mesh='path = "m.vtu"'))
    assert main(["describe", scene]) == 0
    out = capsys.readouterr().out
    warn = [ln for ln in out.splitlines() if ln.startswith("warning: ")]
    assert len(warn) == 2, out
    assert any("reoriented 1 of 2 negatively oriented tets" in w for w in warn)
    assert any("1 unreferenced vertices removed" in w and "5" in w for w in warn)
    assert "2 elements, 5 vertices" in out
    # run: the same notes through logging (stderr), the frames with elapsed and ETA (stdout, not a tty)
    assert main(["run", scene, "--device", "auto", "--out", str(tmp_path / "o.usda")]) == 0
    cap = capsys.readouterr()
    assert f"2 frames on {resolve_device('auto')} (float64)" in cap.out  # auto: cpu without CUDA
    assert cap.err.count("warning: ") == 2 and "reoriented 1 of 2" in cap.err and "unreferenced" in cap.err, cap.err
    frames = [ln for ln in cap.out.splitlines() if "] frame " in ln]
    assert [ln.split("] frame ")[1].split()[0] for ln in frames] == ["1/2", "2/2"]
    assert all(" elapsed " in ln and " ETA " in ln for ln in frames) and frames[-1].endswith("ETA 0:00:00")


# ----------------------------------------------------------------------------- logging, tomllib
def _library_files():
    for base, _, files in os.walk(os.path.join(ROOT, "warpfem")):
        for f in files:
            if f.endswith(".py"):
                yield os.path.join(base, f)


def test_library_code_logs_instead_of_printing():
    offenders = []
    for path in _library_files():
        if os.path.basename(path) in ("cli.py", "__main__.py", "progress.py"):  # the command line prints
            continue
        tree = ast.parse(open(path).read())
        offenders += [f"{os.path.relpath(path, ROOT)}:{n.lineno}" for n in ast.walk(tree)
                      if isinstance(n, ast.Call) and getattr(n.func, "id", None) == "print"]
    assert offenders == []


def test_library_log_records_reach_stderr_from_the_cli(tmp_path, capsys):
    import logging

    assert main(["describe", write(tmp_path, SCENE.format(mesh=BOX))]) == 0
    capsys.readouterr()
    logging.getLogger("warpfem.reduced.subspace").info("hello %d", 3)
    logging.getLogger("warpfem.x").debug("hidden without --verbose")
    logging.getLogger("warpfem.x").warning("careful")
    assert capsys.readouterr().err.splitlines() == ["hello 3", "warning: careful"]


def test_every_tomllib_import_has_the_tomli_fallback():
    files = list(_library_files()) + [os.path.join(ROOT, "tests", f) for f in os.listdir(os.path.join(ROOT, "tests"))
                                       if f.endswith(".py")]
    found = 0
    for path in files:
        tree = ast.parse(open(path).read())
        for node in ast.walk(tree):
            if isinstance(node, ast.Import) and any(a.name == "tomllib" for a in node.names):
                found += 1
                tries = [t for t in ast.walk(tree) if isinstance(t, ast.Try) and node in t.body]
                assert tries, f"{path}:{node.lineno}: import tomllib without a fallback"
                fallback = [a.name for h in tries[0].handlers for s in h.body if isinstance(s, ast.Import) for a in s.names]
                assert fallback == ["tomli"], f"{path}:{node.lineno}"
    assert found >= 1
