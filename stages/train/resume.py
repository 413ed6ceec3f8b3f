"""`resume` continues the same run: the options that shape the result must be the ones config.json records.

config.json records the resolved Config and the scene's identity (`scene_sha256`: the sha256 of its
transforms.json, written by the run's first start). On resume:
- automatic defaults left automatic (None: batch_rays, lr, downscale and every option of the method's group whose
  default is None: the density method's resolution, rank, upsample_at, step_ratio, tv, depth_loss,
  density_activation, mlp_width, view_dependent) take the run's recorded values (not the values this device or this
  code version would choose afresh; a run recorded before an option existed had the value its method's
  `recorded_before` names);
- every other option that shapes the result (the method, seed, scene model, background, learning-rate decay,
  grid and prior settings, pose refinement, appearance, ...) must equal the recorded one, and so must the scene:
  the same transforms.json content (runs without `scene_sha256`: the same scene folder). A difference is refused
  with one line naming each (`field: recorded -> given`). "Not given" cannot be told from "given the default"
  here, so a run trained with a non-default value is resumed by giving that value again (the line says which);
- budget and bookkeeping options (`BUDGET`: steps, seconds, device, threads, evaluation and logging cadence,
  checkpoint cadence, the final evaluation) may change: config.json then records the new values, and its
  `resumed` list one entry per resume: {step, changed: {field: [recorded, given]}}.
"""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

from nerfpipe.data.errors import UserError
from nerfpipe.data.rundir import config_to_json, find_run_scene, sha256_file
from nerfpipe.model.methods import Method, method_named, method_of_run
from nerfpipe.stages.train.config import Config

__all__ = ["BUDGET", "AUTOMATIC", "scene_sha256", "resume_config"]

BUDGET = (
    "max_steps",
    "max_seconds",
    "device",
    "threads",
    "eval_every",
    "eval_pixels",
    "log_every",
    "checkpoint_every",
    "checkpoint_seconds",
    "final_eval_views",
    "final_eval_fraction",
)
"""Options that change how long the run goes on and what it logs, not what it fits: may change on resume."""
AUTOMATIC = ("batch_rays", "lr", "downscale")
"""Run options whose None means "chosen by the run" (and the method's options whose default is None): None takes the
record."""
_NOT_COMPARED = ("scene_dir", "run_dir", "resume", "overwrite")
_MISSING = object()


def scene_sha256(scene_path: Path) -> str:
    """The scene's identity: the sha256 of its transforms.json (`scene_path` is the folder or the file)."""
    scene_path = Path(scene_path)
    return sha256_file(scene_path / "transforms.json" if scene_path.is_dir() else scene_path)


def resume_config(config: Config, run_dir: Path, scene_path: Path) -> tuple[Config, dict[str, Any]]:
    """The Config to continue the run with (automatic options as recorded) and this resume's `resumed` entry
    without its step ({changed}); UserError naming every difference that would change the result (module doc)."""
    path = Path(run_dir) / "config.json"
    stored = _read(path)
    config = _inherit(config, stored)
    given, recorded = config_to_json(config), _defaults_for_missing(stored, config)
    differ, changed = [], {}
    scene = _scene_difference(stored, Path(run_dir), Path(scene_path))
    if scene:
        differ.append(scene)
    elif _same_path(stored.get("scene_dir"), scene_path) is False:
        changed["scene_dir"] = [stored.get("scene_dir"), str(Path(scene_path).resolve())]
    for key, value in _flat(given).items():
        before = recorded.get(key, _MISSING)
        if key in _NOT_COMPARED or _equal(before, value):
            continue
        if key in BUDGET:
            if value is not None:
                changed[key] = [None if before is _MISSING else before, value]
        else:
            differ.append(f"{key}: {_show(before)} -> {_show(value)}")
    if differ:
        raise UserError(
            f"{path}: resume continues the run recorded here, and the given settings differ: "
            f"{', '.join(differ)}; give the recorded values, or replace the run with "
            "overwrite=True"
        )
    return config, {"changed": changed}


def _read(path: Path) -> dict[str, Any]:
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise UserError(
            f"{path}: missing; resume needs the config.json the run wrote to check that it continues the same run"
        ) from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise UserError(f"{path}: cannot read the run's config ({exc})") from None
    if not isinstance(doc, dict):
        raise UserError(f"{path}: expected a JSON object (the run's config)")
    return doc


def _stored_options(stored: dict[str, Any], method: Method) -> dict[str, Any]:
    """The recorded method options: under `options`; runs from before methods kept the density field's under `fast`
    (or flat, before that grouping) and view_dependent at the top level."""
    if isinstance(stored.get("options"), dict):
        return stored["options"]
    old = stored.get("fast") if isinstance(stored.get("fast"), dict) else stored
    out = {}
    for f in dataclasses.fields(method.Options):
        if f.name in old:
            out[f.name] = old[f.name]
        elif f.name in stored:
            out[f.name] = stored[f.name]
    return out


def _automatic(method: Method) -> list[str]:
    """The method's options whose default is None (chosen by the run)."""
    return [f.name for f in dataclasses.fields(method.Options) if f.default is None]


def _inherit(config: Config, stored: dict[str, Any]) -> Config:
    """`config` with its automatic options (None) replaced by the recorded values."""
    method = method_named(config.method)
    options = method.Options() if config.options is None else config.options
    recorded = dict(method.recorded_before)
    recorded |= {k: v for k, v in _stored_options(stored, method).items() if v is not None}
    inherited = {k: _typed(recorded[k]) for k in _automatic(method) if getattr(options, k) is None and k in recorded}
    top = {k: _typed(stored[k]) for k in AUTOMATIC if getattr(config, k) is None and stored.get(k) is not None}
    return dataclasses.replace(config, options=dataclasses.replace(options, **inherited), **top)


def _typed(value: Any) -> Any:
    return tuple(value) if isinstance(value, list) else value


def _defaults_for_missing(stored: dict[str, Any], config: Config) -> dict[str, Any]:
    """The record flattened (`options.x`, the method as `method`); an option the recording version did not have
    counts as its default (or as the method's `recorded_before` says)."""
    method = method_named(config.method)
    blank = Config(scene_dir=Path(), run_dir=Path(), method=config.method, options=method.Options())
    base = _flat(config_to_json(blank)) | {f"options.{k}": v for k, v in method.recorded_before.items()}
    legacy = {"fast", "field", "options"} | {f.name for f in dataclasses.fields(method.Options)}
    flat = {k: v for k, v in stored.items() if k not in legacy}
    flat |= {f"options.{k}": v for k, v in _stored_options(stored, method).items()}
    flat["method"] = method_of_run(stored, "config.json")
    return {k: flat.get(k, base[k]) for k in base}


def _flat(doc: dict[str, Any]) -> dict[str, Any]:
    out = {k: v for k, v in doc.items() if k != "options"}
    out.update({f"options.{k}": v for k, v in (doc.get("options") or {}).items()})
    return out


def _equal(a: Any, b: Any) -> bool:
    return a == b or (isinstance(a, int | float) and isinstance(b, int | float) and float(a) == float(b))


def _show(value: Any) -> str:
    if value is _MISSING:
        return "(none)"
    return json.dumps(value) if not isinstance(value, str) else value


def _same_path(recorded: Any, scene_path: Path) -> bool | None:
    if not isinstance(recorded, str):
        return None
    return Path(recorded).resolve() == Path(scene_path).resolve()


def _scene_difference(stored: dict[str, Any], run_dir: Path, scene_path: Path) -> str | None:
    """ "scene: ..." when the given scene is not the run's: another transforms.json content (`scene_sha256`), or,
    for runs recorded without it, another folder than the recorded ones."""
    if isinstance(stored.get("scene_sha256"), str):
        found = scene_sha256(scene_path)
        if found == stored["scene_sha256"]:
            return None
        return (
            f"scene: {stored.get('scene_dir')} (transforms.json sha256 {stored['scene_sha256'][:12]}) -> "
            f"{scene_path} (sha256 {found[:12]})"
        )
    recorded = find_run_scene(run_dir, stored, ("scene_dir",))
    if not recorded or any(p.resolve() == scene_path.resolve() for p in recorded):
        return None
    return f"scene_dir: {stored.get('scene_dir')} -> {scene_path}"
