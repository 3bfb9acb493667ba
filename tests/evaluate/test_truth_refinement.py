"""benchmarks/truth_refinement.py: references of several resolutions compared, and refused
when they pose different problems."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from tests.runs import BENCHMARKS


@pytest.fixture
def refinement(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import truth_refinement

    return truth_refinement


def _reference(path: Path, displacements: dict[str, list], rim: float, nu: float = 0.45,
               depths=(10.0, 20.0)) -> Path:
    """A truth.py reference file: lesion index -> one displacement (mm) or None per depth."""
    key = {"anatomy": "abc", "E_mpa": 0.005, "nu": nu, "footprint": ["rectangle", 50.0, 10.0],
           "depths_mm": list(depths), "tet_size_mm": 10.0, "tet_fine_mm": 4.0, "rim_mm": rim}
    lesions = {li: {"displacement": d} for li, d in displacements.items()}
    path.write_text(json.dumps({"key": key, "lesions": lesions}))
    return path


def test_steps_and_distances_to_the_finest_are_those_of_the_vectors(tmp_path, refinement,
                                                                     capsys):
    coarse = _reference(tmp_path / "a.json", {"0": [[1, 0, 0], [2, 0, 0]],
                                              "1": [[0, 1, 0], None]}, 2.0)
    mid = _reference(tmp_path / "b.json", {"0": [[1, 0.3, 0], [2, 0, 0.4]],
                                           "1": [[0, 1, 0], [0, 2, 0]]}, 1.0)
    fine = _reference(tmp_path / "c.json", {"0": [[1, 0.3, 0.1], [2, 0, 0.4]],
                                            "1": [[0, 1, 0.05], [0, 2, 0]]}, 0.5)
    assert refinement.main([f"r2={coarse}", f"r1={mid}", f"r05={fine}", "--stored",
                            str(coarse), "--no-result-file"]) == 0
    out = capsys.readouterr().out
    rows = refinement.rows_of({k: refinement.read_reference(p) for k, p in
                               (("r2", coarse), ("r1", mid), ("r05", fine))},
                              refinement.read_reference(coarse))
    assert [(r["lesion"], r["depth_mm"]) for r in rows] == [(0, 10.0), (0, 20.0), (1, 10.0)]
    assert rows[1]["step_r2_r1_mm"] == pytest.approx(0.4)  # lesion 1's 20 mm: not in r2
    assert rows[0]["step_r1_r05_mm"] == pytest.approx(0.1)
    assert rows[0]["finest_r2_mm"] == pytest.approx((0.3 ** 2 + 0.1 ** 2) ** 0.5)
    assert rows[2]["stored_truth_to_finest_mm"] == pytest.approx(0.05)
    assert "RESULT step_max_mm=0.1000 finest_max_mm=0.4000 stored_max_mm=0.4000" in out


def test_references_of_another_material_are_refused_by_name(tmp_path, refinement):
    a = _reference(tmp_path / "a.json", {"0": [[1, 0, 0], [2, 0, 0]]}, 2.0)
    b = _reference(tmp_path / "b.json", {"0": [[1, 0, 0], [2, 0, 0]]}, 1.0, nu=0.49)
    with pytest.raises(SystemExit, match="differ in 'nu'"):
        refinement.main([f"a={a}", f"b={b}", "--no-result-file"])


def test_a_file_that_is_no_reference_is_named(tmp_path, refinement):
    a = _reference(tmp_path / "a.json", {"0": [[1, 0, 0], [2, 0, 0]]}, 2.0)
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    with pytest.raises(SystemExit, match="bad.json: not a truth.py reference file"):
        refinement.main([f"a={a}", f"b={bad}", "--no-result-file"])


def test_a_stored_truth_of_another_problem_and_repeated_labels_are_refused(tmp_path, refinement):
    a = _reference(tmp_path / "a.json", {"0": [[1, 0, 0], [2, 0, 0]]}, 2.0)
    b = _reference(tmp_path / "b.json", {"0": [[1, 0, 0], [2, 0, 0]]}, 1.0)
    other = _reference(tmp_path / "other.json", {"0": [[1, 0, 0], [2, 0, 0]]}, 0.0, nu=0.49)
    with pytest.raises(SystemExit, match="--stored and a differ in 'nu'"):
        refinement.main([f"a={a}", f"b={b}", "--stored", str(other), "--no-result-file"])
    with pytest.raises(SystemExit):  # argparse's error: one file would be lost
        refinement.main([f"a={a}", f"a={b}", f"c={b}", "--no-result-file"])


def test_a_file_without_its_label_is_refused_naming_the_form(tmp_path, refinement, capsys):
    a = _reference(tmp_path / "a.json", {"0": [[1, 0, 0], [2, 0, 0]]}, 2.0)
    with pytest.raises(SystemExit):
        refinement.main([f"a={a}", str(a), "--no-result-file"])
    assert "expected LABEL=FILE" in capsys.readouterr().err
