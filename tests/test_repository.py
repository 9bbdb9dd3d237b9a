"""The repository is self-contained: nothing reads a path outside it (a fresh clone must pass)."""

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCANNED = ("*.py", "*.toml", "Makefile", "*.cfg", "*.sh")
# a sibling data folder a user does not have, and absolute home/work paths of one machine.
FORBIDDEN = re.compile(r"(\.\./)+shared/|[\"'](/work|/root|/home|/Users)/")


def _files():
    for pattern in SCANNED:
        for p in ROOT.rglob(pattern):
            parts = set(p.relative_to(ROOT).parts)
            if parts & {".venv", ".git", "build", "out", "__pycache__", ".pytest_cache"}:
                continue
            yield p


def test_no_path_outside_the_repository():
    offenders = []
    for p in _files():
        if p.resolve() == Path(__file__).resolve():
            continue
        for i, line in enumerate(p.read_text(errors="replace").splitlines(), 1):
            if FORBIDDEN.search(line):
                offenders.append(f"{p.relative_to(ROOT)}:{i}: {line.strip()}")
    assert not offenders, "paths outside the repository:\n" + "\n".join(offenders)


# an absolute path of one machine in a recorded result or a doc (POSIX homes / work / temp folders, a
# Windows drive); not after a word character, '.', '~', '/' or '-' (URLs, relative paths, ~/.cache)
MACHINE_ROOTS = ("work", "root", "home", "tmp", "Users", "private/var", "var/folders")
MACHINE_PATH = re.compile(r"(?<![\w.~/-])/(?:" + "|".join(MACHINE_ROOTS) + r")/"
                          r"|(?<![\w])[A-Za-z]:\\(?=[\w\\])")
RECORDS = ("kernels_bench/results", "docs")


def test_results_and_docs_hold_no_absolute_path_of_a_machine():
    """Benchmark results and docs are read on other machines: paths in them are repository-relative
    (``warpfem.paths.portable_path``), ``<tmp>/...`` or ``~/...``."""
    # each machine root in the contexts results write it (JSON value, log line, brackets, code span)
    for root in MACHINE_ROOTS:
        for bad in (f'"scene": "/{root}/me/scene.toml"', f"log: /{root}/x.log", f"(/{root}/warpfem)", f"`/{root}/.cache`"):
            assert MACHINE_PATH.search(bad), bad
    assert MACHINE_PATH.search('"' + "C:" + "\\Users\\me\\scene.toml" + '"')
    for fine in ("examples/scenes/cantilever.toml", "<tmp>/warpfem", "~/.cache/warp/1.9", "kernels_bench/tmp/x",
                 "https://example.org/home/page", "ratio 3:1"):
        assert not MACHINE_PATH.search(fine), fine
    files = [p for d in RECORDS for p in sorted((ROOT / d).rglob("*")) if p.is_file()] + [ROOT / "README.md"]
    assert len(files) > 20
    offenders = []
    for p in files:
        data = p.read_bytes()
        if b"\0" in data:  # binary (images)
            continue
        for i, line in enumerate(data.decode("utf-8", errors="replace").splitlines(), 1):
            if MACHINE_PATH.search(line):
                offenders.append(f"{p.relative_to(ROOT)}:{i}: {line.strip()[:160]}")
    assert not offenders, "absolute paths of a machine (write them repository-relative):\n" + "\n".join(offenders)


def test_shipped_meshes_are_documented():
    meshes = ROOT / "examples" / "meshes"
    readme = (meshes / "README.md").read_text()
    files = sorted(p.name for p in meshes.iterdir() if p.name != "README.md")
    assert files, "no meshes shipped"
    for name in files:
        assert f"`{name}`" in readme, f"{name} has no origin/licence entry in examples/meshes/README.md"


def test_scene_meshes_resolve_inside_the_repository():
    try:
        import tomllib
    except ModuleNotFoundError:  # Python 3.10
        import tomli as tomllib

    for scene in sorted((ROOT / "examples" / "scenes").glob("*.toml")):
        data = tomllib.loads(scene.read_text())
        for section in ("mesh", "surface"):
            path = data.get(section, {}).get("path")
            if path is None:
                continue
            target = (scene.parent / path).resolve()
            assert target.is_file(), f"{scene.name}: [{section}] path {path!r} does not exist"
            assert ROOT in target.parents, f"{scene.name}: [{section}] path {path!r} leaves the repository"


def test_portable_paths_name_no_folder_of_this_machine(tmp_path):
    """What results record for a path (warpfem.paths): repository-relative inside the checkout,
    <tmp>/<name> in the temporary folder, else the file name."""
    import os

    from warpfem.paths import portable_message, portable_path, repository_root

    assert Path(repository_root()) == ROOT
    scene = ROOT / "examples" / "scenes" / "cantilever.toml"
    assert portable_path(scene) == "examples/scenes/cantilever.toml"
    assert portable_path(os.path.relpath(scene)) == "examples/scenes/cantilever.toml"  # relative to the cwd
    assert portable_path(tmp_path / "deep" / "beam.toml") == "<tmp>/beam.toml"
    assert portable_path(Path(os.sep) / "opt" / "data" / "bunny.msh") == "bunny.msh"
    msg = portable_message(f"{tmp_path / 'a' / 'beam.toml'}: [mesh].path: no file '{ROOT / 'examples' / 'x.msh'}'")
    assert msg == "<tmp>/beam.toml: [mesh].path: no file 'examples/x.msh'"
    home = os.path.expanduser("~")
    if os.path.dirname(home) != home and not str(ROOT).startswith(home + os.sep):
        assert portable_message(f"Kernel cache: {os.path.join(home, '.cache', 'warp')}") == \
            f"Kernel cache: {os.path.join('~', '.cache', 'warp')}"
