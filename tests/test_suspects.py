"""`pipelines/suspects.py`, the chain's last step: one line per failed self-check of the records under OUT, or
"self-checks: all N ok"; exit status 0 either way. On fabricated records (the chain itself: test_makefile)."""

from __future__ import annotations

import json
from pathlib import Path

from nerfpipe.data.checks import Check, check_line, verdict
from nerfpipe.pipelines import suspects


def _write(out: Path, rel: str, checks: list[Check] | None) -> Path:
    doc = {"stage": "x", "used": {}}
    if checks is not None:
        doc.update(verdict(checks))
    path = out / rel
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc))
    return path


def _ok(name: str) -> Check:
    return Check.upper(name, 0.1, 1.0, "fine")


def test_all_ok_is_one_line_counting_every_check(tmp_path):
    _write(tmp_path, "run/manifest.json", None)  # a record without checks (older, or a stage without any)
    _write(tmp_path, "video.manifest.json", [_ok("empty_frames"), _ok("non_finite")])
    _write(tmp_path, "depth/manifest.json", [_ok("depth_coverage")])
    assert suspects.summary(tmp_path) == ["self-checks: all 3 ok"]


def test_each_failed_check_is_one_line_naming_stage_record_figure_and_rule(tmp_path, capsys):
    _write(tmp_path, "video.manifest.json", [_ok("empty_frames")])
    slab = Check.upper("box_fill", 0.99, 0.95, "the mesh spans the scene's box on every axis")
    parts = Check.upper("large_components", 14, 10, "the surface breaks into 14 sizeable pieces")
    mesh = _write(tmp_path, "mesh.report.json", [slab, _ok("x"), parts])
    low = Check.lower("holdout_psnr", 12.3, 15.0, "hardly the photos", unit=" dB")
    evaluation = _write(tmp_path, "eval.manifest.json", [low])
    lines = suspects.summary(tmp_path)
    records = {c["name"]: c for c in json.loads(mesh.read_text())["checks"]}
    assert lines == [  # in the chain's order: eval before mesh
        check_line("eval", str(evaluation), json.loads(evaluation.read_text())["checks"][0]),
        check_line("mesh", str(mesh), records["box_fill"]),
        check_line("mesh", str(mesh), records["large_components"]),
    ]
    assert lines[1].startswith(f"mesh ({mesh}): box_fill = 0.99 (expected <= 0.95): ")
    assert "holdout_psnr = 12.3 (expected >= 15 dB)" in lines[0]
    assert suspects.main([str(tmp_path)]) == 0  # suspect is reported, not an error
    assert capsys.readouterr().out.splitlines() == lines


def test_missing_records_are_skipped_and_unreadable_ones_said(tmp_path, capsys):
    assert suspects.summary(tmp_path) == [f"self-checks: no record under {tmp_path} holds any"]
    (tmp_path / "mesh.report.json").write_text("{not json")
    _write(tmp_path, "depth/manifest.json", [_ok("depth_coverage")])
    (line,) = suspects.summary(tmp_path)
    assert line.startswith(f"mesh ({tmp_path / 'mesh.report.json'}): cannot read its self-checks (JSONDecodeError")
    assert suspects.main([str(tmp_path)]) == 0 and capsys.readouterr().out.strip() == line


def test_every_record_of_the_chain_is_read(tmp_path):
    rels = [rel for _, rel in suspects.RECORDS]
    assert rels == [
        "scene/poses_report.json",
        "scene/convert_manifest.json",
        "run/manifest.json",
        "video.manifest.json",
        "depth/manifest.json",
        "eval.manifest.json",
        "mesh.report.json",
    ]
    for stage, rel in suspects.RECORDS:
        _write(tmp_path, rel, [Check.upper(f"{stage}_check", 2.0, 1.0, "too big")])
    lines = suspects.summary(tmp_path)
    assert [line.split(" ", 1)[0] for line in lines] == [stage for stage, _ in suspects.RECORDS]
