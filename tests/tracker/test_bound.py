"""Each lesion's 95 % error bound (biopsynav.tracker.bound)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from biopsynav.igtl.replies import bounds_messages, point_message, rest_slots
from biopsynav.tracker.bound import COEFFICIENTS, error_bound_mm
from biopsynav.tracker.csvtrack import lesions_csv
from biopsynav.tracker.result import LesionResult, TrackingResult

RESULT_FILE = Path(__file__).resolve().parents[2] / "benchmarks" / "results" / "error-bound.json"


def test_the_coefficients_are_those_the_benchmark_fitted():
    """The tracker's bound is the one benchmarks/error_bound.py fitted and checked: a refit
    that is not carried into the code (or a hand edit) fails here."""
    fitted = json.loads(RESULT_FILE.read_text())["figures"]
    assert COEFFICIENTS == pytest.approx((fitted["c"], fitted["a"], fitted["b"]), rel=1e-3)


def test_the_bound_grows_with_the_lesions_motion_and_the_push():
    d = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 5.0], [3.0, 4.0, 0.0], [0.0, 12.0, 0.0]])
    at10, at30 = error_bound_mm(d, 10.0), error_bound_mm(d, 30.0)
    c, a, b = COEFFICIENTS
    assert at10[0] == 0.0  # nothing moved: the rest pose
    assert at10[1] == pytest.approx(c + 5.0 * (a + 10.0 * b))
    assert at10[1] == at10[2]  # by the size of the motion, not its direction
    assert at10[3] > at10[2] and np.all(at30[1:] > at10[1:])


def test_the_bound_reaches_track_csv_and_openigtlink():
    lesions = [LesionResult(1, np.array([1.0, 2.0, 3.0]), np.array([0.0, 0.0, 5.0]),
                            bound_mm=0.42),
               LesionResult(2, np.array([4.0, 5.0, 6.0]), np.zeros(3), bound_mm=0.0)]
    ok = TrackingResult(lesions, "ok")
    rows = lesions_csv([(7, ok)]).splitlines()
    assert rows[0] == "frame,lesion_id,x,y,z,bound_mm,status,reason"
    assert rows[1] == "7,1,1.0000,2.0000,3.0000,0.420,ok,"
    msgs = bounds_messages(ok)
    assert len(msgs) == 1 and msgs[0].msg.string == "95 % within: Lesion1 0.4 mm, Lesion2 0.0 mm"
    slots = rest_slots(None)
    point = point_message(slots.rows(ok), slots, ok)
    assert point.metadata["Bound95"] == "Lesion1 0.4 mm, Lesion2 0.0 mm"
    nan = np.full(3, np.nan)
    refused = TrackingResult([LesionResult(1, nan, nan, "out_of_envelope")], "out_of_envelope")
    assert bounds_messages(refused) == [] and math.isnan(refused.lesions[0].bound_mm)
    assert lesions_csv([(8, refused)]).splitlines()[1].split(",")[5] == "nan"
