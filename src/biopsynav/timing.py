"""Timing alternatives against each other on a machine whose speed drifts (a shared VM)."""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence

import numpy as np


def medians_in_turn(calls: Sequence[Callable[[], object]], warmup: int, timed: int
                    ) -> list[float]:
    """The median seconds of each of ``calls``: ``warmup`` untimed rounds, then ``timed``
    rounds, each round one call of each in turn (what slows the machine for a while slows
    all alike)."""
    times: list[list[float]] = [[] for _ in calls]
    for round_ in range(warmup + timed):
        for k, call in enumerate(calls):
            start = time.perf_counter()
            call()
            if round_ >= warmup:
                times[k].append(time.perf_counter() - start)
    return [float(np.median(t)) for t in times]
