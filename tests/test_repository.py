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
