"""Import layering, read from the source with `ast` (every import, inside functions and TYPE_CHECKING too).

    cli -> stages -> model -> data -> radiance        (an arrow: "may import")

- a stage (`stages.<A>`, a module or a package) never imports another stage `stages.<B>`: stages meet through
  files; a stage package may import its own submodules;
- `radiance` (maths) imports none of data, stages, model, cli, benchmarks, tests;
- `data` (file formats) imports none of stages, model, cli, benchmarks, tests;
- `model` (trained runs) imports none of stages, cli, benchmarks, tests;
- `stages` imports neither cli nor benchmarks nor tests (test helpers are also imported by bare name, e.g.
  `import fixtures_convert`: any module named like a file in tests/ counts as tests);
- every file (tests and benchmarks too) imports the product as `nerfpipe.<package>`, never by its folder's bare
  name: the install puts one name, `nerfpipe`, on the path (docs/DESIGN.md, "Package names").
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SKIP_DIRS = {".venv", "runs", "build", "bench_out", "__pycache__", "node_modules"}
TEST_MODULES = {"tests"} | {p.stem for p in (ROOT / "tests").glob("*.py")}
PACKAGE = "nerfpipe"
"""The one installed name: the folders are its subpackages (pyproject.toml maps nerfpipe to the repository root)."""
PRODUCT = {"stages", "data", "model", "radiance", "pipelines", "cli"}
FORBIDDEN = {
    "radiance": {"data", "stages", "model", "cli", "benchmarks", "tests"},
    "data": {"stages", "model", "cli", "benchmarks", "tests"},
    "model": {"stages", "cli", "benchmarks", "tests"},
    "stages": {"cli", "benchmarks", "tests"},
}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imported(tree: ast.AST, module: str, is_package: bool) -> list[tuple[int, str]]:
    """(line, dotted target) for every import; `from X import y` gives X.y (y may be a submodule)."""
    package = module if is_package else module.rpartition(".")[0]
    out = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:  # relative: resolve against this module's package
                parts = package.split(".") if package else []
                parts = parts[: len(parts) - (node.level - 1)]
                base = ".".join([*parts, *([node.module] if node.module else [])])
            out += [(node.lineno, f"{base}.{a.name}" if a.name != "*" else base) for a in node.names]
    return out


def violations(source: str, module: str, *, is_package: bool = False, where: str = "<string>") -> list[str]:
    """Layering violations of one module's source, each as 'where:line: module imports target (rule)'."""
    top = module.split(".")[0]
    bad = []
    full = f"{PACKAGE}.{module}" if top in PRODUCT else module  # relative imports resolve inside nerfpipe
    for line, target in _imported(ast.parse(source), full, is_package):
        if target.split(".")[0] in PRODUCT:
            bad.append(f"{where}:{line}: {module} imports {target} (the product is imported as nerfpipe.{target})")
            continue
        target = target.removeprefix(f"{PACKAGE}.")
        parts = target.split(".")
        t_top = "tests" if parts[0] in TEST_MODULES else parts[0]
        if t_top in FORBIDDEN.get(top, ()):
            bad.append(f"{where}:{line}: {module} imports {target} ({top} must not import {t_top})")
        elif top == "stages" and t_top == "stages" and len(parts) > 1 and len(module.split(".")) > 1:
            own, other = module.split(".")[1], parts[1]
            if other != own:
                bad.append(f"{where}:{line}: {module} imports {target} (stage {own} must not import stage {other})")
    return bad


def _python_files() -> list[Path]:
    return sorted(
        p
        for p in ROOT.rglob("*.py")
        if not any(
            part in SKIP_DIRS or part.startswith(".") or part.endswith(".egg-info")
            for part in p.relative_to(ROOT).parts[:-1]
        )
    )


def test_checker_flags_bad_imports():
    """The checker itself: a synthetic bad source is flagged, with its line; allowed imports are not."""
    bad_stage = "import numpy\n\ndef f():\n    from nerfpipe.stages import render\n"
    assert violations(bad_stage, "stages.depth") == [
        "<string>:4: stages.depth imports stages.render (stage depth must not import stage render)"
    ]
    assert violations("from stages import render", "stages.depth") == [
        "<string>:1: stages.depth imports stages.render (the product is imported as nerfpipe.stages.render)"
    ]
    assert violations("from nerfpipe.stages.train.fit import step", "stages.mesh.grid")
    assert violations("from . import render", "stages.depth")  # relative: stages.render
    assert violations("from ..render import x", "stages.mesh.grid")  # relative: stages.render.x
    assert violations("import nerfpipe.data.transforms", "radiance.render")[0].startswith("<string>:1: ")
    assert violations("from nerfpipe.model import load", "data.transforms")
    assert violations("from nerfpipe.cli import main", "model.run")
    assert violations("import fixtures_convert", "data.importers.colmap")
    assert violations("from benchmarks.standin import StandIn", "stages.mesh")
    ok = (
        "import torch\nfrom nerfpipe.stages.poses import colmap\nfrom .images import screen_image\n"
        "from nerfpipe.data.errors import E\n"
    )
    assert violations(ok, "stages.poses", is_package=True) == []
    assert violations("from nerfpipe.stages.poses.images import Screen", "stages.poses.report") == []
    assert violations("from nerfpipe.radiance.camera import Intrinsics", "data.transforms") == []
    assert violations("from nerfpipe.stages import render", "cli") == []
    assert violations("from data.transforms import Scene", "tests.test_x")  # tests, benchmarks: nerfpipe.* too


def test_layering():
    files = _python_files()
    assert any(p.parts[-3:] == ("stages", "convert", "__init__.py") for p in files)  # the walk sees the stages
    bad = []
    for path in files:
        module = _module_name(path)
        source = path.read_text(encoding="utf-8")
        bad += violations(source, module, is_package=path.name == "__init__.py", where=str(path.relative_to(ROOT)))
    assert not bad, "import layering violated:\n" + "\n".join(bad)


def test_every_package_is_installed_under_nerfpipe():
    """pyproject.toml lists every package folder of the product as nerfpipe.<folder> (setuptools cannot prefix
    found packages, so the list is written out; a new subpackage missing from it would not be installed)."""
    tomllib = pytest.importorskip("tomllib")  # Python >= 3.11

    listed = set(tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]["packages"])
    found = {"nerfpipe"} | {
        "nerfpipe." + ".".join(p.parent.relative_to(ROOT).parts)
        for top in sorted(PRODUCT - {"cli"})
        for p in (ROOT / top).rglob("__init__.py")
        if "__pycache__" not in p.parts
    }
    assert listed == found
