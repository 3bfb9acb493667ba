"""benchmarks/truth.py: which lesions it evaluates."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture
def truth(monkeypatch):
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[2] / "benchmarks"))
    import truth

    return truth


def test_lesions_are_chosen_by_id_or_spread_over_the_list(phantom_case, truth):
    ids = [int(lesion.id) for lesion in phantom_case.anatomy.lesions]
    assert truth.chosen_lesions(phantom_case, 0) == list(range(len(ids)))
    assert truth.chosen_lesions(phantom_case, 3) == [0, 4, 9]  # as Table 2 spreads them
    picked = truth.chosen_lesions(phantom_case, 3, f"{ids[6]},{ids[1]},{ids[1]}")
    assert picked == [1, 6]


@pytest.mark.parametrize("ids, words", [("2,x", "not a comma list"),
                                        ("2,99", "no lesion with id 99")])
def test_a_bad_lesion_id_is_one_line_naming_it(phantom_case, truth, ids, words):
    with pytest.raises(SystemExit) as exc:
        truth.chosen_lesions(phantom_case, 3, ids)
    assert words in str(exc.value) and "\n" not in str(exc.value)
