"""benchmarks/error_bands.py: the network's error against its teacher by distance from the
probe, on the samples Table 1 judges."""

from __future__ import annotations

import json

import numpy as np
import pytest

from biopsynav.case import Case
from biopsynav.layout import CasePaths
from tests.runs import BENCHMARKS


@pytest.fixture
def error_bands(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import error_bands

    return error_bands


def test_the_held_out_error_is_table_1s_and_the_bands_share_its_nodes(trained_case,
                                                                      error_bands, capsys):
    table1 = json.loads(CasePaths(trained_case).table1.read_text())
    r = error_bands.main([str(trained_case), "--train-samples", "4"])
    assert r["test"]["mean_e_mm"] == pytest.approx(table1["mean_e_mm"], rel=1e-4)
    assert r["test"]["max_e_mm"] == pytest.approx(table1["max_e_mm"], rel=1e-4)
    assert r["train"]["samples"] == 4
    for figures in (r["train"], r["test"]):
        bands = figures["bands"]
        counts = {where: sum(row[2] for row in rows) for where, rows in bands.items()}
        assert counts["all"] == counts["inside"] + counts["outside"] > 0
        assert counts["inside"] > 0 and counts["outside"] > 0  # an immersed grid
        # the band means, weighted by their node counts, give the mean nodal error
        total = sum(row[2] * row[3] for row in bands["all"] if row[2])
        parts = sum(row[2] * row[3] for key in ("inside", "outside") for row in bands[key]
                    if row[2])
        assert np.isclose(total, parts, rtol=1e-6)
        n_lesions = len(Case.load(trained_case).anatomy.lesions)
        assert sum(row[2] for row in bands["lesions"]) == figures["samples"] * n_lesions
        assert 0.0 <= figures["lesion_mm"] < np.inf
        # every sample in one probe-displacement bin; their means give the mean e back
        depth = figures["by_depth"]
        assert sum(row[2] for row in depth) == figures["samples"]
        assert sum(row[2] * row[3] for row in depth if row[2]) == pytest.approx(
            figures["samples"] * figures["mean_e_mm"], rel=1e-6)
        assert max(row[4] for row in depth if row[2]) == pytest.approx(figures["max_e_mm"])
    assert capsys.readouterr().out.splitlines()[-1].startswith("RESULT train_e_mm=")


def test_a_case_without_data_is_one_line(tmp_path, error_bands):
    with pytest.raises(SystemExit, match="error: .*nowhere: case folder does not exist"):
        error_bands.main([str(tmp_path / "nowhere")])


@pytest.mark.parametrize("bad", ["0", "-3", "many"])
def test_a_bad_training_sample_count_is_refused_before_any_work(bad, trained_case, error_bands,
                                                                capsys):
    with pytest.raises(SystemExit):
        error_bands.main([str(trained_case), "--train-samples", bad])
    assert "is not a whole number of at least 1" in capsys.readouterr().err
