"""biopsynav's P2 truth against NGSolve (``benchmarks/truth_agreement.py``): two FE codes on
the same tetrahedra and the same glued-face push agree."""

from __future__ import annotations

import json

import pytest

from tests.runs import BENCHMARKS, run_benchmark

pytest.importorskip("ngsolve", reason="NGSolve is the second FE code (the peer extra, which "
                    "requirements.lock holds)")


def test_the_p2_truth_and_ngsolve_agree_on_one_mesh(tmp_path):
    """A coarse phantom mesh (20 mm, 12 mm under the probe), a 6 mm push over lesion 1 (index
    0): the lesion displacements of the two codes agree to 1e-3 mm (2.2e-5 mm measured on
    2026-12-02; the quadrature rules differ, both of degree 5), while the push moves the
    lesion by about a millimetre; P3 on the same mesh moves it by more than that agreement
    (the check can tell the codes apart from the discretisation)."""
    out = tmp_path / "agree.json"
    _, result = run_benchmark("truth_agreement.py", [
        "--lesion-ids", "1", "--depths", "3", "6", "--tet-size", "20", "--tet-fine", "12",
        "--orders", "2", "3", "--out", str(out), "--no-result-file"], tmp_path)
    figures = json.loads(out.read_text())
    rows = figures["rows"]
    assert [r["depth_mm"] for r in rows] == [3.0, 6.0]
    moved = [sum(c * c for c in r["p2"]) ** 0.5 for r in rows]
    assert 0.3 < moved[0] < moved[1] < 5.0, moved
    assert figures["codes_max_mm"] < 1e-3, figures["codes_max_mm"]
    assert figures["p_max_mm"] > 10 * figures["codes_max_mm"], figures
    assert result["codes_max_mm"] == f"{figures['codes_max_mm']:.4f}"


def test_h_refinement_of_the_p2_truth_alone(tmp_path):
    """``--orders`` with none, ``--h-fine`` and ``--rim-fine``: biopsynav's P2 alone, on the
    coarse mesh, on one refined near the probe and on one refined along the face's edge; each
    refinement moves the lesion (a discretisation error that can be told), by less than the
    push moves it, and the result line names both."""
    out = tmp_path / "h.json"
    _, result = run_benchmark("truth_agreement.py", [
        "--lesion-ids", "1", "--depths", "6", "--tet-size", "20", "--tet-fine", "12",
        "--orders", "--h-fine", "8", "--rim-fine", "6", "--out", str(out),
        "--no-result-file"], tmp_path)
    figures = json.loads(out.read_text())
    (row,) = figures["rows"]
    moved = sum(c * c for c in row["p2"]) ** 0.5
    assert 1e-4 < row["h8_mm"] < 0.5 * moved, (row["h8_mm"], moved)
    assert 1e-4 < row["r6_mm"] < 0.5 * moved, (row["r6_mm"], moved)
    assert figures["h_max_mm"] == row["h8_mm"] and row["codes_mm"] is None
    assert figures["rim_max_mm"] == row["r6_mm"] and "h8-r6_mm" not in row
    assert "ngsolve_p2" not in row
    assert result["h_max_mm"] == f"{row['h8_mm']:.4f}"
    assert result["rim_max_mm"] == f"{row['r6_mm']:.4f}"


@pytest.mark.parametrize("option, sizes", [("--h-fine", ["12"]), ("--h-fine", ["0"]),
                                           ("--h-fine", ["x"]), ("--rim-fine", ["0"]),
                                           ("--rim-fine", ["3", "--rim", "2"])])
def test_a_refinement_that_is_not_finer_is_refused_before_any_solve(option, sizes, tmp_path,
                                                                      capsys, monkeypatch):
    """An ``--h-fine`` size no finer than ``--tet-fine``, a ``--rim-fine`` size no finer
    than ``--rim`` (or not a size) stops the script with one line naming the option, before
    a case is made or a file written."""
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import truth_agreement

    out = tmp_path / "h.json"
    with pytest.raises(SystemExit) as stop:
        truth_agreement.main(["--tet-fine", "12", "--orders", option, *sizes,
                              "--out", str(out), "--no-result-file"])
    assert stop.value.code == 2 and option in capsys.readouterr().err
    assert not out.exists()


def test_each_refinement_step_is_measured_against_the_mesh_before_it(monkeypatch):
    """With several --h-fine sizes a row holds each finer answer against the 4 mm one and
    against the mesh before it: how far one more refinement moves the lesion."""
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import truth_agreement

    p2 = [[1.0, 0.0, 0.0]]
    finer = {"h2.8": [[1.0, 0.3, 0.0]], "h2": [[1.0, 0.3, 0.4]], "r1": [[1.0, 0.0, 0.2]]}
    (row,) = truth_agreement.lesion_rows(0, [10.0], p2, {}, {}, finer)
    assert row["h2.8_mm"] == pytest.approx(0.3) and row["h2_mm"] == pytest.approx(0.5)
    assert row[truth_agreement.step_key("h2.8", "h2")] == pytest.approx(0.4)
    assert truth_agreement.step_key("h2.8", "h2") == "h2.8-h2_mm"
    # a rim refinement is measured against the first mesh, not against the last h mesh
    assert row["r1_mm"] == pytest.approx(0.2) and "h2-r1_mm" not in row
