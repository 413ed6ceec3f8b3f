"""The one registry of methods: name -> `Method` (`model.methods.base`).

Built-in methods are named in `BUILTIN` (module and attribute, imported on first use, so that listing the names
imports no model code); third-party methods register through the Python entry-point group `nerfpipe.methods`
(each entry a `Method` instance or class: `[project.entry-points."nerfpipe.methods"] mine = "pkg.mod:MINE"`, as
nerfstudio's plugins do), and code (a test, a notebook) may call `register(method)`.

This module is the only place where a method's name is compared with a string: a run's config.json names its
method (`method`); runs trained before methods existed name a field kind instead (`field`: "fast" -> density,
"vanilla" -> nerf; `LEGACY_FIELDS`), and so do their checkpoints (`field_config.kind`).
"""

from __future__ import annotations

import importlib
from importlib.metadata import entry_points
from typing import Any

from nerfpipe.data.errors import UserError
from nerfpipe.model.methods.base import Method

__all__ = [
    "BUILTIN",
    "DEFAULT",
    "ENTRY_POINT_GROUP",
    "LEGACY_FIELDS",
    "register",
    "unregister",
    "method_named",
    "method_names",
    "methods",
    "method_of_run",
    "method_of_checkpoint",
]

BUILTIN = {
    "density": ("nerfpipe.model.methods.density", "DENSITY"),
    "nerf": ("nerfpipe.model.methods.nerf", "NERF"),
    "sdf": ("nerfpipe.model.methods.sdf", "SDF"),
    "gnt": ("nerfpipe.model.methods.gnt", "GNT"),
}
"""Built-in methods: name -> (module, attribute)."""
DEFAULT = "density"
"""`train`'s method when none is named."""
ENTRY_POINT_GROUP = "nerfpipe.methods"
LEGACY_FIELDS = {"fast": "density", "vanilla": "nerf"}
"""The field kinds that runs and checkpoints recorded before methods existed, and the method each is."""

_registered: dict[str, Method] = {}
_plugins_loaded = False


def register(method: Method | type[Method]) -> Method:
    """Add `method` (an instance, or a class made with no arguments) under its name; returns the instance.
    Registering a name twice replaces the first (a test's stand-in, a plugin's newer version)."""
    if isinstance(method, type):
        method = method()
    if not isinstance(method, Method):
        raise TypeError(f"expected a model.methods.Method, got {type(method).__name__}")
    name = getattr(method, "name", None)
    if not isinstance(name, str) or not name.isidentifier():
        raise ValueError(f"a method's name must be a Python identifier, got {name!r}")
    _registered[name] = method
    return method


def unregister(name: str) -> None:
    """Remove a method registered with `register` (tests clean up their stand-ins)."""
    _registered.pop(name, None)


def _load_plugins() -> None:
    global _plugins_loaded
    if _plugins_loaded:
        return
    _plugins_loaded = True
    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.name not in _registered:
            register(ep.load())


def method_names() -> list[str]:
    """Every method's name: the built-in ones first, then the registered and plugged-in ones."""
    _load_plugins()
    return list(BUILTIN) + sorted(set(_registered) - set(BUILTIN))


def method_named(name: str) -> Method:
    """The method called `name`; UserError naming the ones there are."""
    if name in _registered:
        return _registered[name]
    if name in BUILTIN:
        module, attr = BUILTIN[name]
        return register(getattr(importlib.import_module(module), attr))
    _load_plugins()
    if name in _registered:
        return _registered[name]
    raise UserError(f"unknown method {name!r}: expected one of {', '.join(method_names())}")


def methods() -> list[Method]:
    """Every method, in `method_names` order."""
    return [method_named(n) for n in method_names()]


def method_of_run(doc: dict[str, Any], where: str) -> str:
    """The method a run's config.json names (`method`, or a legacy `field` kind); UserError when neither."""
    if isinstance(doc.get("method"), str):
        return doc["method"]
    legacy = doc.get("field")
    if isinstance(legacy, str) and legacy in LEGACY_FIELDS:
        return LEGACY_FIELDS[legacy]
    raise UserError(f"{where}: config.json names no method (written by another nerfpipe version?)")


def method_of_checkpoint(state: dict[str, Any]) -> str | None:
    """The method a checkpoint was written by (`method`, or a legacy field kind); None when it says neither."""
    if isinstance(state.get("method"), str):
        return state["method"]
    cfg = state.get("field_config")
    kind = cfg.get("kind") if isinstance(cfg, dict) else None
    return LEGACY_FIELDS.get(kind) if isinstance(kind, str) else None
