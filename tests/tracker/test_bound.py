"""Each lesion's 95 % error bound (biopsynav.tracker.bound)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from biopsynav.igtl.replies import bounds_messages, offset_surface, point_message, rest_slots
from biopsynav.inference.model_files import meta_checksum
from biopsynav.layout import LESION_CHECK
from biopsynav.tracker.bound import (
    CHECK_FORMAT,
    CHECK_WEIGHT,
    COEFFICIENTS,
    TEACHER_WEIGHT,
    UNCHECKED_COEFFICIENTS,
    LesionCheck,
    error_bound_mm,
)
from biopsynav.tracker.csvtrack import lesions_csv
from biopsynav.tracker.result import LesionResult, TrackingResult
from tests.runs import BENCHMARKS

RESULT_FILE = BENCHMARKS / "results" / "error-bound.json"


def test_the_coefficients_are_those_the_benchmark_fitted():
    """The tracker's bound is the one benchmarks/error_bound.py fitted and checked: a refit
    that is not carried into the code (or a hand edit) fails here."""
    fitted = json.loads(RESULT_FILE.read_text())["figures"]
    assert COEFFICIENTS == pytest.approx((fitted["c"], fitted["a"], fitted["b"]), rel=1e-3,
                                         abs=1e-6)
    assert UNCHECKED_COEFFICIENTS == pytest.approx(
        (fitted["unchecked_c"], fitted["unchecked_a"], fitted["unchecked_b"]), rel=1e-3,
        abs=1e-6)
    assert CHECK_WEIGHT == fitted["weight"]
    assert TEACHER_WEIGHT == fitted["teacher_weight"]


def test_the_bound_grows_with_the_lesions_motion_and_the_push():
    d = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 5.0], [3.0, 4.0, 0.0], [0.0, 12.0, 0.0]])
    at10, at30 = error_bound_mm(d, 10.0), error_bound_mm(d, 30.0)
    c, a, b = UNCHECKED_COEFFICIENTS
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


def test_the_shell_is_the_surface_pushed_out_whichever_way_its_faces_wind():
    import trimesh

    sphere = trimesh.creation.icosphere(subdivisions=2, radius=4.0)
    v, f = np.asarray(sphere.vertices) + [1.0, 2.0, 3.0], np.asarray(sphere.faces)
    for faces in (f, f[:, ::-1]):
        shell = offset_surface(v, faces, 1.5)
        np.testing.assert_allclose(np.linalg.norm(shell - v, axis=1), 1.5, rtol=1e-12)
        np.testing.assert_allclose(np.linalg.norm(shell - [1.0, 2.0, 3.0], axis=1), 5.5,
                                   rtol=1e-4)  # outwards: vertex normals nearly radial
    np.testing.assert_array_equal(offset_surface(v, f, 0.0), v)  # at rest: the surface


def test_a_lesion_the_network_missed_or_whose_teacher_is_off_gets_a_wider_bound():
    """The self-check's relative miss widens the bound by k |d| r, the teacher gap by
    k_t |d| g; a lesion without either (NaN) is bounded by the unchecked coefficients."""
    d = np.array([[0.0, 0.0, 10.0]] * 5)
    bounds = error_bound_mm(d, 20.0, np.array([0.0, 0.2, 0.0, np.nan, 0.2]),
                            np.array([0.0, 0.0, 0.1, 0.1, np.nan]))
    c, a, b = COEFFICIENTS
    assert bounds[0] == pytest.approx(c + 10.0 * (a + 20.0 * b))
    assert bounds[1] == pytest.approx(bounds[0] + CHECK_WEIGHT * 10.0 * 0.2)
    assert bounds[2] == pytest.approx(bounds[0] + TEACHER_WEIGHT * 10.0 * 0.1)
    unchecked = error_bound_mm(d[:1], 20.0)[0]
    assert bounds[3] == pytest.approx(unchecked) and bounds[4] == pytest.approx(unchecked)
    assert error_bound_mm(np.zeros((1, 3)), 20.0, np.array([0.5]), np.array([0.1]))[0] == 0.0


def _write_check(folder: Path, meta: dict, lesions: dict, depths=(15.0, 25.0, 35.0)) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    (folder / LESION_CHECK).write_text(json.dumps(
        {"format": CHECK_FORMAT, "model_checksum": meta_checksum(meta),
         "depths_mm": list(depths), "lesions": lesions}))


def test_a_check_is_read_interpolated_and_held_beyond_its_depths(tmp_path):
    meta = {"fingerprint": "abc", "node_shape": [3, 3, 3]}
    _write_check(tmp_path, meta, {"1": {"relative": [0.1, 0.3, 0.2], "teacher_gap": 0.03},
                                  "2": {"relative": [None, 0.4, None], "teacher_gap": None},
                                  "3": {"relative": [None, None, None]}})
    check = LesionCheck.load(tmp_path, meta, [1, 2, 3, 4])  # lesion 4: not in the check
    assert check is not None
    assert check.relative_at(20.0)[:2] == pytest.approx([0.2, 0.4])
    assert check.relative_at(5.0)[0] == pytest.approx(0.1)  # held below the first depth
    assert check.relative_at(50.0)[0] == pytest.approx(0.2)  # ... and beyond the last
    assert np.isnan(check.relative_at(20.0)[2:]).all()
    assert check.teacher_gap[0] == pytest.approx(0.03) and np.isnan(check.teacher_gap[1:]).all()
    assert LesionCheck.load(tmp_path, meta, []).relative_at(20.0).shape == (0,)  # no lesions


@pytest.mark.parametrize("damage", ["stale", "format", "garbage", "not_json", "depths"])
def test_a_stale_or_damaged_check_is_not_used(tmp_path, damage):
    """A model trained again (another meta.json), another layout or a damaged file: the
    tracker bounds without the check rather than with the wrong one."""
    meta = {"fingerprint": "abc"}
    _write_check(tmp_path, {"fingerprint": "other"} if damage == "stale" else meta,
                 {"1": {"relative": [0.1, 0.2, 0.3]}},
                 depths=(25.0, 15.0, 35.0) if damage == "depths" else (15.0, 25.0, 35.0))
    path = tmp_path / LESION_CHECK
    if damage == "format":
        path.write_text(path.read_text().replace(f'"format": {CHECK_FORMAT}', '"format": 99'))
    elif damage == "garbage":
        path.write_text(json.dumps({"format": CHECK_FORMAT,
                                    "model_checksum": meta_checksum(meta),
                                    "depths_mm": "x", "lesions": []}))
    elif damage == "not_json":
        path.write_bytes(b"\x00{")
    assert LesionCheck.load(tmp_path, meta, [1]) is None
    assert LesionCheck.load(tmp_path / "absent", meta, [1]) is None


@pytest.mark.parametrize("content", [b"\x00{", b'{"depths_mm": "x", "lesions": []}', b"[1, 2]"])
def test_the_report_names_a_damaged_check(tmp_path, content):
    """The report shows the check's table; a damaged file is named, with the command that
    writes it again, never a traceback."""
    from biopsynav.errors import InputError
    from biopsynav.report.sections import lesion_check_blocks

    path = tmp_path / LESION_CHECK
    assert lesion_check_blocks(path) == []  # not made: nothing shown
    path.write_bytes(content)
    with pytest.raises(InputError) as err:
        lesion_check_blocks(path)
    assert LESION_CHECK in str(err.value) and "biopsynav evaluate" in str(err.value)


def test_fit_leaves_rows_without_a_teacher_gap_to_the_unchecked_bound(tmp_path, monkeypatch):
    """``benchmarks/error_bound.py``: a lesion whose self-check has no teacher gap (the finer
    grid gave no answer) is bounded by the tracker without the check; the fit keeps its rows
    for the coefficients without the check and leaves them out of those with it, instead of
    stopping."""
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import error_bound

    rows = [{"lesion": i, "status": {"net": "ok"}, "moved_mm": {"net": 10.0 + i},
             "depth_mm": 10.0 * (1 + i % 3), "tre_mm": {"net": 0.1 * (1 + i % 5)},
             "relative_miss": 0.01, "teacher_gap": None if i < 3 else 0.02} for i in range(20)]
    path = tmp_path / "bound-rows-x.json"
    path.write_text(json.dumps({"rows": rows}))
    got = error_bound.rows_of([path])
    assert got.shape == (20, 5) and np.isnan(got[:3, 4]).all() and np.isfinite(got[3:]).all()
    assert error_bound.check(error_bound.fit(got, 0.5, 0.5), 0.5, got, 0.5)["n"] == 17
    assert error_bound.check(error_bound.fit(got, 0.0), 0.0, got)["n"] == 20
    del rows[0]["teacher_gap"]  # neither in the row nor in a gap file: named, not guessed
    path.write_text(json.dumps({"rows": rows}))
    with pytest.raises(SystemExit, match="lesion 0 has no teacher gap"):
        error_bound.rows_of([path])
