"""benchmarks/mri_exam.py: its check of the tracker's 95 % bound on an MRI breast, and its
one-material case (the like-with-like check against the P2 truth)."""

from __future__ import annotations

import argparse
from pathlib import Path

from tests.runs import BENCHMARKS

ROOT = Path(__file__).resolve().parents[1]


def test_the_bound_checked_is_the_one_the_tracker_gave(monkeypatch):
    """Each push is judged against the bound the tracker returned with that answer
    (``truth.py``'s ``bound_mm``, self-check included), and a push the truth did not answer
    is left out rather than stopping the benchmark."""
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import mri_exam

    def row(lesion: int, tre: float) -> dict:
        return {"lesion": lesion, "depth_mm": 10.0, "reference_mm": 5.0,
                "status": {"net": "ok"}, "tre_mm": {"net": tre}, "bound_mm": {"net": 0.4}}

    out = mri_exam.bound_check([row(1, 0.3), row(2, 0.5),
                                {"lesion": 1, "depth_mm": 30.0, "reference_mm": None}])
    assert out["covered"] == "1/2"
    assert [p["bound_mm"] for p in out["pushes"]] == [0.4, 0.4]


def test_one_material_makes_a_case_the_truth_accepts_and_judges_table_2_by_it(monkeypatch,
                                                                             tmp_path):
    """``--one-material``: ``init`` with the collection's label flags, the skin made fat and
    the tumours as soft as the fat gives a case of one material (what the P2 truth and a stored
    truth require), and the truth solved after ``init`` becomes Table 2's reference."""
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import mri_exam
    from biopsynav.case import Case
    from biopsynav.cli import main
    from biopsynav.config import load_config
    from biopsynav.evaluate.references import other_materials
    from tests.anatomy.test_torso import torso_labels, write

    write(tmp_path / "torso.nrrd", torso_labels())
    args = argparse.Namespace(recipe=None, one_material=True)
    flags = mri_exam.init_flags(args, tmp_path)
    assert flags[flags.index("--tissue-labels") + 1] == mri_exam.ONE_MATERIAL_TISSUES
    case_dir = tmp_path / "e99-right"
    assert main(["init", str(case_dir), "--labelmap", str(tmp_path / "torso.nrrd"), *flags,
                 "--lesion-labels", "-3", "--side", "right"]) == 0
    assert other_materials(Case.load(case_dir)) == []
    asked = []
    monkeypatch.setattr(mri_exam, "truth_run", lambda *a: asked.append(a))
    mri_exam.judge_by_truth(case_dir, 5.0)
    assert asked == [(case_dir, 5.0, "--reference-only")]
    cfg = load_config(case_dir)
    assert cfg.evaluate.reference == "stored"
    assert (case_dir / cfg.evaluate.truth_file).resolve() \
        == mri_exam.reference_path(case_dir).resolve()
    two = mri_exam.init_flags(argparse.Namespace(recipe="pushes", one_material=False), tmp_path)
    assert two == [*mri_exam.LABEL_FLAGS, "--recipe", "pushes"]
