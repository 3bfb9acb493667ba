"""Timing alternatives in turn."""

from __future__ import annotations

from biopsynav.timing import medians_in_turn


def test_each_call_runs_in_turn_and_the_warm_up_is_not_timed():
    order: list[str] = []
    medians = medians_in_turn([lambda: order.append("a"), lambda: order.append("b")],
                              warmup=2, timed=3)
    assert order == ["a", "b"] * 5
    assert len(medians) == 2 and all(m >= 0.0 for m in medians)
