"""Table 2 binning and aggregation (no FE, no network)."""

from __future__ import annotations

import numpy as np
import pytest

from biopsynav.evaluate.table import (
    BIN_NAMES,
    Record,
    aggregate,
    bin_index,
    bin_name,
    format_markdown,
    format_text,
    table_from_dict,
)


@pytest.mark.parametrize(("mm", "name"), [
    (0.0, "D10"), (12.49, "D10"), (12.5, "D15"), (17.49, "D15"), (17.5, "D20"),
    (22.49, "D20"), (22.5, "D25"), (27.49, "D25"), (27.5, "D30"), (80.0, "D30")])
def test_bin_edges_follow_the_paper(mm, name):
    assert bin_name(mm) == name


def test_bin_index_is_vectorised():
    assert bin_index(np.array([[5.0, 15.0], [20.0, 31.0]])).tolist() == [[0, 1], [2, 4]]


def _rec(lesion, mm, tre, method="net"):
    return Record(lesion, 0, mm, bin_name(mm), method, tre)


def test_aggregation_means_and_stds_skip_missing_cells():
    recs = [_rec(1, 15, 1.0), _rec(1, 20, 3.0), _rec(1, 21, 5.0),  # D20 averages 3 and 5
            _rec(2, 10, 2.0), _rec(2, 30, None),  # a failure is not a number
            _rec(2, 30, 99.0, method="fem"), _rec(3, 25, 7.0)]
    t = aggregate(recs, "net", [1, 2, 3, 4])
    assert np.isnan(t.cells[0, 0]) and t.cells[0, 1] == 1.0 and t.cells[0, 2] == 4.0
    assert t.counts[0, 2] == 2 and t.counts[1, 4] == 0
    rmean, rstd = t.row_stats()
    np.testing.assert_allclose(rmean[:3], [2.5, 2.0, 7.0])
    np.testing.assert_allclose(rstd[:3], [1.5, 0.0, 0.0])  # population std, as the paper
    assert np.isnan(rmean[3]) and np.isnan(rstd[3])
    cmean, cstd = t.col_stats()
    np.testing.assert_allclose(cmean[[0, 1, 2, 3]], [2.0, 1.0, 4.0, 7.0])
    assert np.isnan(cmean[4]) and np.isnan(cstd[4])
    assert t.overall_mean() == pytest.approx((1 + 4 + 2 + 7) / 4)


def test_paper_row_statistics_are_reproduced():
    recs = [_rec(1, mm, v) for mm, v in zip((15, 20, 25, 30), (1.936, 2.002, 1.506, 3.053),
                                            strict=True)]
    d = aggregate(recs, "net", [1]).to_dict()
    assert d["rows"][0]["mean"] == pytest.approx(2.124, abs=1e-3)
    assert d["rows"][0]["std"] == pytest.approx(0.569, abs=1e-3)
    assert d["rows"][0]["cells"][0] is None


def test_text_and_markdown_show_dashes_and_round_trip():
    t = aggregate([_rec(7, 15, 1.23456, method="fem")], "fem", [7, 8])
    text = format_text(t)
    assert "1.235" in text and "-" in text and "D30" in text
    lines = text.splitlines()
    assert len({len(line) for line in lines[1:]}) <= 2  # aligned columns
    md = format_markdown(t)
    assert md.startswith("| Lesion |") and "| 8 | - | - |" in md
    back = table_from_dict(t.to_dict())
    np.testing.assert_array_equal(np.isnan(back.cells), np.isnan(t.cells))
    assert back.lesions == [7, 8] and list(BIN_NAMES) == t.to_dict()["bins"]
