"""Structure rules read from the source (issue 28): small stage modules, narrow public functions, and library
errors that name no CLI flag.

- No module under stages/ is over `MAX_STAGE_LINES` lines: a stage that grows is split into modules with one job
  each inside its package.
- An error raised in radiance/, data/ or model/ names an option as its config field (`refine_poses`) or says what
  to do, never as a CLI flag (`--refine-poses`): those packages are called by stages, tests and scripts as much as
  by the CLI, and cli.py is where a flag's name belongs. Checked on the string constants inside `raise`
  statements (f-string parts included), read with `ast`.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MAX_STAGE_LINES = 400
LIBRARIES = ("radiance", "data", "model")
FLAG = re.compile(r"(?<![\w-])--[a-z]")
"""A CLI flag: two dashes then a lower-case letter, not inside a word (`NeRF--`, `a--b` are no flags)."""

PENDING: set[str] = set()
"""Stage modules still over MAX_STAGE_LINES while another change splits them; the lead empties this set."""
PENDING_FLAG_MESSAGES = {"model/loop.py"}
"""Library modules whose raised messages still name a flag. model/loop.py: the training loop's Interrupted and
TrainingDiverged messages ("continue with --resume", "try a lower --lr") are read at the command line and tested
there (tests/test_reliability.py); they move to the stages' own wording once the stages pass it in."""


def _sources(*tops: str) -> list[Path]:
    return sorted(p for top in tops for p in (ROOT / top).rglob("*.py") if "__pycache__" not in p.parts)


def _rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def flag_messages(source: str, where: str = "<string>") -> list[str]:
    """'where:line: text' for each string constant inside a `raise` statement that names a CLI flag."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Raise) and node.exc is not None:
            for sub in ast.walk(node.exc):
                if isinstance(sub, ast.Constant) and isinstance(sub.value, str) and FLAG.search(sub.value):
                    found.append((node.lineno, sub.value))
    return [f"{where}:{line}: {text!r}" for line, text in sorted(found)]


def test_checker_finds_flags_in_raised_messages():
    """The checker itself: a flag in a raised message (plain or f-string) is found; the field's name, a flag in a
    docstring, a comment or a non-raised string, and dashes inside words are not."""
    bad = (
        "def f(x):\n"
        "    if x:\n"
        '        raise UserError(f"--frames: expected >= 1, got {x}")\n'
        '    raise ValueError("a bad path; use --path turntable")\n'
    )
    assert [m.split(":")[1] for m in flag_messages(bad)] == ["3", "4"]
    good = (
        '"""Docstring: `render --path`."""\n'
        "HELP = 'train --refine-poses'  # not raised\n"
        "def f(x):\n"
        "    # --comment\n"
        '    raise UserError(f"frames: expected >= 1, got {x} (NeRF--, a--b, -- c, --1)")\n'
    )
    assert flag_messages(good) == []


def test_stage_modules_stay_small():
    sizes = {_rel(p): len(p.read_text(encoding="utf-8").splitlines()) for p in _sources("stages")}
    assert sizes, "no stage sources found"
    over = {path: n for path, n in sizes.items() if n > MAX_STAGE_LINES and path not in PENDING}
    assert not over, f"stage modules over {MAX_STAGE_LINES} lines (split them into modules with one job): {over}"


def test_library_errors_name_no_cli_flag():
    found = []
    for path in _sources(*LIBRARIES):
        if _rel(path) not in PENDING_FLAG_MESSAGES:
            found += flag_messages(path.read_text(encoding="utf-8"), _rel(path))
    assert not found, "errors naming a CLI flag (name the config field instead):\n" + "\n".join(found)


MAX_PUBLIC_PARAMETERS = 10


def wide_functions(source: str, where: str = "<string>") -> dict[str, int]:
    """'where:name' -> parameter count (self and cls not counted) of each public function or method over the limit."""
    found = {}
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not node.name.startswith("_"):
            a = node.args
            names = [p.arg for p in (*a.posonlyargs, *a.args, *a.kwonlyargs)] + [
                p.arg for p in (a.vararg, a.kwarg) if p
            ]
            n = len([x for x in names if x not in ("self", "cls")])
            if n > MAX_PUBLIC_PARAMETERS:
                found[f"{where}:{node.name}"] = n
    return found


def test_public_functions_take_at_most_ten_parameters():
    """The widest public function of the product's packages takes <= 10 parameters (group the rest in a config)."""
    assert wide_functions("def f(a, b, c, d, e, f, g, h, i, j, *, k):\n    pass\n") == {"<string>:f": 11}
    wide = {}
    for p in _sources("radiance", "data", "model", "stages"):
        wide.update(wide_functions(p.read_text(encoding="utf-8"), _rel(p)))
    assert not wide, f"public functions over {MAX_PUBLIC_PARAMETERS} parameters: {wide}"


METHOD_NAME_COMPARISONS_ALLOWED = {
    "model/methods/registry.py": "the registry: the one place that maps names (and legacy field kinds) to methods",
    "stages/mesh/config.py": "mesh's own --method (density | poisson): how a surface is extracted",
    "stages/mesh/field_access.py": "a capability's name (model.run.CAPABILITIES), not a method's",
}


def method_name_comparisons(source: str, names: set[str], where: str = "<string>") -> list[str]:
    """'where:line: code' for each comparison with a string constant (or a tuple of them) naming a method."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Compare):
            for side in (node.left, *node.comparators):
                consts = side.elts if isinstance(side, (ast.Tuple, ast.List, ast.Set)) else [side]
                if any(isinstance(c, ast.Constant) and c.value in names for c in consts):
                    found.append(f"{where}:{node.lineno}: {ast.unparse(node)}")
                    break
    return found


def test_no_string_test_on_a_method_name_outside_the_registry():
    """A stage asks a run what it can do (model.run capabilities), never which method made it (issue 47): no
    comparison with a method's name (or a legacy field kind) outside the registry."""
    from nerfpipe.model.methods.registry import BUILTIN, LEGACY_FIELDS

    names = set(BUILTIN) | set(LEGACY_FIELDS)
    bad = "if run.method == 'nerf':\n    pass\n"
    assert method_name_comparisons(bad, names) == ["<string>:1: run.method == 'nerf'"]
    found = []
    for p in _sources("radiance", "data", "model", "stages", "pipelines"):
        if _rel(p) not in METHOD_NAME_COMPARISONS_ALLOWED:
            found += method_name_comparisons(p.read_text(encoding="utf-8"), names, _rel(p))
    found += method_name_comparisons((ROOT / "cli.py").read_text(encoding="utf-8"), names, "cli.py")
    assert not found, "method names compared outside the registry:\n" + "\n".join(found)
