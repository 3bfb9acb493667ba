"""benchmarks/convergence.py's study in the case folder, and the report's table of it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from biopsynav.report import write_report
from tests.runs import BENCHMARKS

DEPTHS = [10.0, 30.0]


@pytest.fixture()
def convergence(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import convergence

    return convergence


@pytest.fixture()
def case_dir(tmp_path):
    from biopsynav.case import make_phantom_case

    return make_phantom_case(tmp_path / "case", cell_size_mm=15).dir


def _result(case_dir: Path) -> dict:
    """A study of two lesions: grids of 15 and 10 mm and a teacher; the 10 mm grid failed at
    30 mm over lesion 7, and the reference has no field there."""
    ref = {0: {"displacement": [[1.0, 0.0, 0.0], [3.0, 0.0, 0.0]], "tangled_elements": [0, 4],
               "field": [[[1.0, 0.0, 0.0]] * 2, [[3.0, 0.0, 0.0]] * 2],
               "field_points": [[0.0, 0.0, 0.0]] * 2},
           1: {"displacement": [[0.0, 2.0, 0.0], [0.0, 6.0, 0.0]],
               "field": [[[0.0, 2.0, 0.0]] * 2, None], "field_points": [[0.0, 0.0, 0.0]] * 2}}

    def grid(scale: float, failed: bool = False) -> dict:
        disp = {li: [[scale * v for v in d] for d in r["displacement"]]
                for li, r in ref.items()}
        field = {li: [None if f is None else [[scale * v for v in p] for p in f]
                      for f in r["field"]] for li, r in ref.items()}
        if failed:
            disp[1][1], field[1][1] = None, None
        return {"active_cells": int(100 / scale), "displacement": disp, "field": field}

    return {"case": str(case_dir), "E_mpa": 0.005, "nu": 0.45, "depths_mm": DEPTHS,
            "cells_mm": [15.0, 10.0], "variants": ["neo-hookean/elastic"], "teachers": ["2:0"],
            "lesions": [0, 1], "lesion_ids": [3, 7],
            "grids": {"neo-hookean/elastic 15": grid(1.5),
                      "neo-hookean/elastic 10": grid(1.25, failed=True),
                      "teacher 2:0": grid(1.1)},
            "reference": ref, "tet_size_mm": 10.0, "tet_fine_mm": 4.0, "tet_rim_mm": 0.0,
            "friction": "stick", "edge_radius_mm": 0.0, "probe_body": True,
            "case_series": "neo-hookean/elastic 15"}


def test_the_summary_holds_each_series_error_against_the_reference(convergence, case_dir):
    s = convergence.summary(_result(case_dir))
    rows = {row["name"]: row for row in s["series"]}
    coarse, fine = rows["neo-hookean/elastic 15"], rows["neo-hookean/elastic 10"]
    # lesion 3 at 10 / 30 mm: 0.5 and 1.5 mm off (1.5 times the reference's 1 and 3 mm)
    assert sum(coarse["lesion_error_mm"], []) == pytest.approx([0.5, 1.5, 1.0, 3.0])
    assert fine["lesion_error_mm"][1] == [pytest.approx(0.5), None]  # its failed solve
    assert coarse["field_error_mm"][1] == [pytest.approx(1.0), None]  # no reference field
    assert s["case_series"] == "neo-hookean/elastic 15" and s["lesion_ids"] == [3, 7]
    assert s["reference"]["probe_body"] is True and s["material"]["nu"] == 0.45
    assert s["reference"]["folded"] == [[3, 30.0, 4]]  # the reference's folded answer


def test_a_study_goes_to_the_case_and_its_report_shows_it(convergence, case_dir, monkeypatch,
                                                          capsys):
    monkeypatch.setattr(convergence, "run", lambda args: _result(case_dir))
    assert convergence.main([str(case_dir), "--depths", *map(str, DEPTHS)]) == 0
    study = case_dir / "eval" / "convergence.json"
    assert f"written to {study}" in capsys.readouterr().out
    assert "summary" in json.loads(study.read_text())
    assert not (case_dir / "eval" / "convergence.partial.json").exists()
    md = write_report(case_dir)[1].read_text()
    section = md.split("## Convergence")[1].split("\n## ")[0]
    assert "P2" in section and "rigid body" in section and "lesions 3, 7" in section
    assert "folded over at a node (not to be trusted; elements): lesion 3 at 30 mm (4)" in section
    # the case's own FE marked; lesion mean (max) at 10 and 30 mm, field means
    assert "| neo-hookean/elastic 15 mm (this case's FE) | 66 | 0.75 (1.00) | 2.25 (3.00) " \
           "| 0.75 | 1.50 |" in section
    assert "| neo-hookean/elastic 10 mm | 80 | 0.38 (0.50) | 0.75 (0.75) |" in section
    assert "| teacher 2:0 ([dataset] teacher_refine:teacher_extrapolation) |" in section


@pytest.mark.parametrize("content, note", [
    (None, "No convergence study: `python benchmarks/convergence.py"),
    ({"grids": {}}, "holds no summary (an unfinished run"),
    ({"summary": {"depths_mm": [10.0]}}, "is damaged (KeyError"),
])
def test_the_report_says_what_is_missing_or_wrong(case_dir, content, note):
    if content is not None:
        (case_dir / "eval").mkdir()
        (case_dir / "eval" / "convergence.json").write_text(json.dumps(content))
    md = write_report(case_dir)[1].read_text()
    assert note in md.split("## Convergence")[1].split("\n## ")[0]


def test_a_missing_case_is_one_line(convergence, tmp_path):
    with pytest.raises(SystemExit, match=r"^error: .*nowhere: case folder does not exist$"):
        convergence.main([str(tmp_path / "nowhere")])


def test_an_unwritable_output_is_one_line(convergence, case_dir, monkeypatch):
    monkeypatch.setattr(convergence, "run", lambda args: _result(case_dir))
    blocker = case_dir / "not-a-folder"
    blocker.write_text("a file where the output's folder should be")
    with pytest.raises(SystemExit, match=r"^error: .*not-a-folder.*cannot write"):
        convergence.main([str(case_dir), "--depths", *map(str, DEPTHS),
                          "--out", str(blocker / "study.json")])
    assert blocker.read_text().startswith("a file")


def test_a_truncated_study_stops_the_report_in_one_line_and_keeps_the_last_one(case_dir,
                                                                               capfd):
    from biopsynav.cli import main

    assert main(["report", str(case_dir)]) == 0
    before = (case_dir / "report.md").read_text()
    (case_dir / "eval").mkdir()
    (case_dir / "eval" / "convergence.json").write_text('{"summary": {"depths_mm": [10')
    capfd.readouterr()
    assert main(["report", str(case_dir)]) == 2
    err = capfd.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "eval/convergence.json: damaged, not valid JSON" in err[0]
    assert "benchmarks/convergence.py" in err[0]
    assert (case_dir / "report.md").read_text() == before


@pytest.mark.parametrize("content, words", [
    ('{"reference": {', "damaged, not valid JSON"),
    (None, "missing; give the --out JSON of a finished run"),
])
def test_a_bad_reused_reference_is_one_line(convergence, case_dir, tmp_path, content, words):
    earlier = tmp_path / "earlier.json"
    if content is not None:
        earlier.write_text(content)
    with pytest.raises(SystemExit, match=f"^error: {earlier}: {words}"):
        convergence.main([str(case_dir), "--lesions", "1", "--depths", "10",
                          "--reuse-reference", str(earlier)])
    assert not (case_dir / "eval" / "convergence.json").exists()
