"""The README and the documentation site: the site builds with warnings as errors, the README's quick
start runs quietly and prints what the README says it prints, and the code blocks of the README and
docs/*.md name only API that exists (with keyword arguments the callables accept)."""

from __future__ import annotations

import ast
import inspect
import os
import re
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
DOCS = ROOT / "docs"


def code_blocks(path: Path, lang: str) -> list[str]:
    """The fenced ```lang blocks of a markdown file, in order."""
    return [textwrap.dedent(m.group(1)) for m in
            re.finditer(rf"^```{lang}[^\n]*\n(.*?)^```", path.read_text(), flags=re.S | re.M)]


def _env():
    env = dict(os.environ)
    env["PYTHONPATH"] = str(ROOT) + os.pathsep + env.get("PYTHONPATH", "")
    env.pop("WARPFEM_VERBOSE", None)
    return env


# ---------------------------------------------------------------------------------------- the site
def test_docs_site_builds_strict_with_every_page(tmp_path):
    """`mkdocs build --strict` (broken links, anchors, docstring references fail it) and every
    docs/*.md page is in the site (mkdocs.yml's `nav` lists them in reading order; a page left out
    of it fails the strict build)."""
    site = tmp_path / "site"
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--quiet", "-f", str(ROOT / "mkdocs.yml"),
                        "-d", str(site)], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0, r.stdout + r.stderr
    pages = sorted(p.stem for p in DOCS.glob("*.md"))
    assert {"index", "api", "results", "overview"} <= set(pages)
    for stem in pages:
        html = site / ("index.html" if stem == "index" else f"{stem}/index.html")
        assert html.is_file(), f"docs/{stem}.md is not in the site"
    api = (site / "api" / "index.html").read_text()
    # the API reference is made from the docstrings: a phrase of Simulator.step's docstring appears
    assert "class Simulator" in api or "Simulator" in api
    from warpfem.simulator import Simulator

    first = inspect.getdoc(Simulator).split("\n")[0].split("(")[0].strip()
    assert first and first.split()[0] in api


# ------------------------------------------------------------------------------------ the README
def test_readme_is_short_and_says_how_to_reach_the_command():
    text = README.read_text()
    assert len(text.encode()) <= 10_000, f"README is {len(text.encode())} bytes (limit 10,000; tables go in docs/)"
    setup = next(b for b in code_blocks(README, "bash") if "make demo" in b)
    assert "make test" in setup and "source .venv/bin/activate" in setup
    assert ".venv/bin/warpfem" in text
    for section in ("## Set-up", "## Python quick start", "## Command line", "## Example scenes", "## Features",
                    "## Troubleshooting"):
        assert section in text, section
    for image in re.findall(r"\]\((docs/images/[^)]+)\)", text):  # the gallery exists
        assert (ROOT / image).is_file(), image
    assert len(re.findall(r"\]\(docs/images/", text)) >= 3
    for link in re.findall(r"\]\((docs/[^)#]+)", text):
        assert (ROOT / link).exists(), link
    scenes = {p.name for p in (ROOT / "examples" / "scenes").glob("*.toml")}
    assert scenes and all(f"`{name}`" in text for name in scenes), "every example scene is listed"


_CLAIM = re.compile(r"#\s*prints:\s*peak sag ([\d.]+) mm, at rest ([\d.]+) mm \(beam theory[^:]*: ([\d.]+) mm")
_OUT = re.compile(r"peak sag ([\d.]+) mm, at rest ([\d.]+) mm")


def test_readme_quick_start_converges_quietly_and_prints_what_it_claims(tmp_path):
    """The first ```python block of the README, run as a user would (a fresh process): no warning
    and no Warp banner or module-load line, and it prints the numbers its "# prints:" comment
    states; those agree with beam theory (static sag q L^4 / 8EI) and with a suddenly applied load
    peaking at twice the static sag."""
    block = code_blocks(README, "python")[0]
    claim = _CLAIM.search(block)
    assert claim, "the quick start ends with '# prints: peak sag X mm, at rest Y mm (beam theory ...: Z mm'"
    script = tmp_path / "quick_start.py"
    script.write_text("import warnings\nwarnings.simplefilter('always')\n" + block)
    r = subprocess.run([sys.executable, str(script)], capture_output=True, text=True, cwd=tmp_path, env=_env(),
                       timeout=300)
    assert r.returncode == 0, r.stderr
    out = r.stdout + r.stderr
    for noise in ("Warning", "warning", "Warp ", "Module ", "not converge"):
        assert noise not in out, out
    got = _OUT.fullmatch(r.stdout.strip())
    assert got, r.stdout
    peak, rest = float(got.group(1)), float(got.group(2))
    assert abs(peak - float(claim.group(1))) <= 0.3 and abs(rest - float(claim.group(2))) <= 0.3, (got.group(0), claim.group(0))
    # Euler-Bernoulli for the README's beam: 1 m x 0.1 m x 0.1 m, E 5e7, rho 1000, g 9.81
    E, L, h, rho, g = 5e7, 1.0, 0.1, 1000.0, 9.81
    theory = 1e3 * rho * g * h * h * L ** 4 / (8 * E * h ** 4 / 12)
    assert abs(float(claim.group(3)) - theory) < 0.05
    assert abs(rest - theory) / theory < 0.03  # Hex27, 10 elements: within 3 % of beam theory
    assert 1.9 < peak / rest < 2.1


def test_readme_collider_toml_is_valid_with_the_box_corners(tmp_path):
    """The README's [[collider]] block, added to the cantilever scene, loads: a plane and a box
    with the box_min / box_max it shows; a box without them is refused by name."""
    from warpfem.scenes import SceneError, load_scene

    block = next(b for b in code_blocks(README, "toml") if "[[collider]]" in b)
    base = (ROOT / "examples" / "scenes" / "cantilever.toml").read_text()
    scene = tmp_path / "with_colliders.toml"
    scene.write_text(base + "\n" + block)
    spec = load_scene(scene).spec
    kinds = [c["type"] for c in spec.collider]
    assert kinds == ["plane", "box"]
    box = spec.collider[1]
    assert list(box["box_min"]) == [0.8, -0.6, -0.5] and list(box["box_max"]) == [1.2, -0.2, 0.5]
    assert "box_min" in block and "box_max" in block
    scene.write_text(base + "\n" + block.replace("box_min", "corner_min"))
    with pytest.raises(SceneError, match="box_min"):
        load_scene(scene)


# ------------------------------------------------------------------- code blocks name real API
def _markdown_files():
    return [README] + sorted(DOCS.glob("*.md"))


def _resolve(node, names):
    """The object an expression such as ``wf.reduced.ReducedSimulator`` names, or None."""
    parts = []
    while isinstance(node, ast.Attribute):
        parts.append(node.attr)
        node = node.value
    if not isinstance(node, ast.Name) or node.id not in names:
        return None
    obj = names[node.id]
    for part in reversed(parts):
        if not hasattr(obj, part):
            import importlib

            try:  # a submodule not imported by its package
                obj = importlib.import_module(f"{obj.__name__}.{part}")
                continue
            except (ImportError, AttributeError):
                raise AssertionError(f"{ast.unparse(node)}.{'.'.join(reversed(parts))}: no attribute {part!r}")
        obj = getattr(obj, part)
    return obj


def _check_block(code: str, where: str):
    import importlib

    import warpfem

    tree = ast.parse(code, filename=where)
    names = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                if a.name.split(".")[0] == "warpfem":
                    mod = importlib.import_module(a.name)
                    names[a.asname or a.name.split(".")[0]] = mod if a.asname else warpfem
        elif isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "warpfem":
            mod = importlib.import_module(node.module)
            for a in node.names:
                assert hasattr(mod, a.name), f"{where}: {node.module} has no {a.name!r}"
                names[a.asname or a.name] = getattr(mod, a.name)
    names.setdefault("wf", warpfem)  # fragments continue the page's `import warpfem as wf`
    checked = 0
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute):
            _resolve(node, names)
        if isinstance(node, ast.Call):
            fn = _resolve(node.func, names)
            if fn is None or not callable(fn):
                continue
            try:
                sig = inspect.signature(fn)
            except (TypeError, ValueError):
                continue
            params = sig.parameters
            if any(p.kind is p.VAR_KEYWORD for p in params.values()):
                continue
            for kw in node.keywords:
                if kw.arg is not None:
                    assert kw.arg in params, f"{where}: {ast.unparse(node.func)}() takes no keyword {kw.arg!r}"
            checked += 1
    return checked


def test_code_blocks_of_the_readme_and_docs_name_existing_api():
    """Every ```python block of README.md and docs/*.md parses, every ``wf.X`` / ``from warpfem.m
    import y`` it names exists, and calls to them use keyword arguments the callables accept (the
    README's quick start is also run, above)."""
    checked = blocks = 0
    for md in _markdown_files():
        for k, code in enumerate(code_blocks(md, "python")):
            checked += _check_block(code, f"{md.relative_to(ROOT)} block {k + 1}")
            blocks += 1
    assert blocks >= 8 and checked >= 20, (blocks, checked)


def test_the_checker_catches_a_renamed_keyword_and_a_missing_name():
    with pytest.raises(AssertionError, match="youngs_modulus_pa"):
        _check_block("import warpfem as wf\nwf.StableNeoHookean(youngs_modulus_pa=1e5)", "t")
    with pytest.raises(AssertionError, match="no attribute"):
        _check_block("import warpfem as wf\nwf.NoSuchSimulator(1)", "t")


def test_examples_are_quiet_by_default(tmp_path):
    """An example script prints its summary only: no Warp banner, no module-load lines, no CUDA
    driver note on a CPU (the library is quiet as the command line is)."""
    r = subprocess.run([sys.executable, str(ROOT / "examples" / "cantilever.py"), "--device", "cpu", "--num-frames", "1",
                        "--stage-path", str(tmp_path / "c.usda"), "--headless"], capture_output=True, text=True,
                       cwd=tmp_path, env=_env(), timeout=300)
    assert r.returncode == 0, r.stderr
    out = r.stdout + r.stderr
    assert "Warp " not in out and "Module " not in out and "CUDA" not in out, out
    assert "frame 1/1" in out


def test_readme_command_lines_parse():
    """Every `warpfem ...` line of the README's shell blocks is a valid command line (subcommand and
    options exist; a renamed option fails here) and names files that exist."""
    import shlex

    from warpfem.cli import build_parser

    parser = build_parser()
    lines = [ln.split("#")[0].strip() for b in code_blocks(README, "bash") for ln in b.splitlines()]
    commands = [shlex.split(ln)[1:] for ln in lines if ln.startswith("warpfem ")]
    assert len(commands) >= 5
    for argv in commands:
        try:
            args = parser.parse_args(argv)
        except SystemExit:
            raise AssertionError(f"README: `warpfem {' '.join(argv)}` does not parse")
        assert (ROOT / args.scene).is_file(), args.scene


def test_api_reference_has_every_exported_class_and_function():
    """docs/api.md has a `::: name` entry for every class and function in the ``__all__`` of the
    public modules (a whole-module entry such as ``::: warpfem.diff`` covers that module's names)."""
    import importlib

    entries = set(re.findall(r"^::: (\S+)", (DOCS / "api.md").read_text(), flags=re.M))
    missing = []
    for name in ("warpfem", "warpfem.contact", "warpfem.io", "warpfem.scenes", "warpfem.diff"):
        mod = importlib.import_module(name)
        if name in entries:
            continue
        for public in mod.__all__:
            obj = getattr(mod, public)
            if not (inspect.isclass(obj) or inspect.isfunction(obj)):
                continue  # constants and the version string
            if f"{name}.{public}" not in entries and f"warpfem.{public}" not in entries:
                missing.append(f"{name}.{public}")
    assert not missing, f"docs/api.md has no entry for {missing}"


def test_first_steps_command_lines_parse():
    """Every `warpfem ...` line of docs/first_steps.md's shell blocks is a valid command line, and the
    scene it names exists."""
    import shlex

    from warpfem.cli import build_parser

    parser = build_parser()
    page = DOCS / "first_steps.md"
    lines = [ln.split("#")[0].strip() for b in code_blocks(page, "bash") for ln in b.splitlines()]
    commands = [shlex.split(ln)[1:] for ln in lines if ln.startswith("warpfem ")]
    assert len(commands) >= 6
    for argv in commands:
        try:
            args = parser.parse_args(argv)
        except SystemExit:
            raise AssertionError(f"first_steps.md: `warpfem {' '.join(argv)}` does not parse")
        if getattr(args, "scene", None):
            assert (ROOT / args.scene).is_file(), args.scene
