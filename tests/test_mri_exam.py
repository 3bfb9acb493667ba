"""benchmarks/mri_exam.py's check of the tracker's 95 % bound on an MRI breast."""

from __future__ import annotations

from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_the_bound_checked_is_the_one_the_tracker_gave(monkeypatch):
    """Each push is judged against the bound the tracker returned with that answer
    (``truth.py``'s ``bound_mm``, self-check included), and a push the truth did not answer
    is left out rather than stopping the benchmark."""
    monkeypatch.syspath_prepend(str(ROOT / "benchmarks"))
    import mri_exam

    def row(lesion: int, tre: float) -> dict:
        return {"lesion": lesion, "depth_mm": 10.0, "reference_mm": 5.0,
                "status": {"net": "ok"}, "tre_mm": {"net": tre}, "bound_mm": {"net": 0.4}}

    out = mri_exam.bound_check([row(1, 0.3), row(2, 0.5),
                                {"lesion": 1, "depth_mm": 30.0, "reference_mm": None}])
    assert out["covered"] == "1/2"
    assert [p["bound_mm"] for p in out["pushes"]] == [0.4, 0.4]
