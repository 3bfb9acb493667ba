"""``benchmarks/p2_push.py``: the P2 truth's push with single-precision factors (the default)
against the double-precision solve, on a coarse mesh of the built-in phantom."""

from __future__ import annotations

from tests.runs import BENCHMARKS, run_benchmark


def test_single_precision_factors_land_where_double_precision_does(tmp_path):
    """A 5 mm push over lesion 1 on 20 mm tetrahedra (12 mm under the probe): both precisions
    answer, each factoring tangents, and their lesion displacements agree far below the
    truth's own errors (0.1 mm) while the push moves the lesion by about a millimetre."""
    out, figures = run_benchmark("p2_push.py", ["--lesion-ids", "1", "--depths", "5",
                                                "--tet-size", "20", "--tet-fine", "12",
                                                "--no-result-file"], tmp_path)
    assert "push_s" in figures and "full_s" in figures
    assert float(figures["max_diff_mm"]) < 1e-4, figures
    lines = [line.strip() for line in out.splitlines() if "5 mm: " in line]
    assert len(lines) == 3 and lines[0].startswith("single") and lines[1].startswith("double")
    assert lines[2].startswith("5 mm: single") and "mm apart" in lines[2], lines
    moved = float(lines[0].split("|u| ")[1].split()[0])
    assert 0.3 < moved < 5.0 and "0 factorisations" not in lines[0], lines


def test_a_lesion_the_case_lacks_is_one_line_before_any_solve(tmp_path):
    """``--lesion-ids`` naming no lesion of the case: one line naming the ids there are, no
    push solved and no result file written."""
    import subprocess
    import sys


    done = subprocess.run([sys.executable, str(BENCHMARKS / "p2_push.py"), "--lesion-ids", "99",
                           "--result-name", "p2-push-test-refused"],
                          capture_output=True, text=True, timeout=300, cwd=tmp_path)
    assert done.returncode != 0 and "no lesion with id 99" in done.stderr, done.stderr[-2000:]
    assert "Traceback" not in done.stderr and "single" not in done.stdout
    assert not (BENCHMARKS / "results" / "p2-push-test-refused.json").exists()
