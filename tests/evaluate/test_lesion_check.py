"""Each lesion's self-check: the tracking network against its own FE teacher over the lesion
(biopsynav.evaluate.lesion_check), and the tracker's bounds that it widens."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from biopsynav.case import Case
from biopsynav.evaluate.lesion_check import run_lesion_check
from biopsynav.evaluate.placement import place_case_probe
from biopsynav.layout import LESION_CHECK
from biopsynav.tracker import Tracker
from biopsynav.tracker.bound import error_bound_mm

#: shallow pushes, inside the small test model's training envelope
DEPTHS = (2.0, 4.0)


@pytest.fixture(scope="module")
def checked(trained_case: Path, tmp_path_factory) -> tuple[Case, dict]:
    """A copy of the small trained case and its lesion check, made in this process."""
    case_dir = tmp_path_factory.mktemp("check") / "case"
    shutil.copytree(trained_case, case_dir)
    case = Case.load(case_dir)
    return case, run_lesion_check(case, workers=1, log=lambda _: None, depths_mm=DEPTHS)


def test_the_check_measures_the_network_against_its_teacher(checked):
    case, check = checked
    assert check["depths_mm"] == list(DEPTHS)
    assert set(check["lesions"]) == {str(les.id) for les in case.anatomy.lesions}
    answered = 0
    for lesion in check["lesions"].values():
        for miss, moved, rel, status in zip(lesion["miss_mm"], lesion["teacher_mm"],
                                            lesion["relative"], lesion["status"], strict=True):
            if status != "ok":
                assert miss is None and rel is None and ("net: " in status or "fem: " in status)
                continue
            answered += 1
            assert moved > 0.0 and miss >= 0.0 and rel == pytest.approx(miss / moved)
    assert answered >= len(DEPTHS)  # the test model answers shallow pushes
    written = json.loads((case.paths.model / LESION_CHECK).read_text())
    assert written["lesions"] == check["lesions"]


def test_the_teacher_gap_is_the_teacher_against_itself_on_a_finer_grid(checked):
    """Each lesion's teacher gap: the FE teacher and the same FE on a grid
    TEACHER_CHECK_REFINEMENT times finer, pushed TEACHER_CHECK_DEPTH_MM over the lesion; the
    distance of their lesion centres over the teacher's lesion motion."""
    from biopsynav.evaluate.lesion_check import (
        TEACHER_CHECK_DEPTH_MM,
        TEACHER_CHECK_REFINEMENT,
        finer_teacher,
    )
    from biopsynav.evaluate.simulation import evaluation_solver_settings
    from biopsynav.tracker.core import fem_engine

    case, check = checked
    assert check["teacher_check"] == {"depth_mm": TEACHER_CHECK_DEPTH_MM,
                                      "refinement": TEACHER_CHECK_REFINEMENT}
    settings = evaluation_solver_settings(case)
    fem, fine = fem_engine(case, settings), finer_teacher(case, settings)
    assert fine.case.grid.spacing == pytest.approx(case.grid.spacing / TEACHER_CHECK_REFINEMENT)
    gaps = [lesion["teacher_gap"] for lesion in check["lesions"].values()]
    assert any(g is not None for g in gaps)
    li = next(i for i, g in enumerate(gaps) if g is not None)
    placement = place_case_probe(case, li)
    moved = []
    for tracker in (fem, fine):
        tracker.set_rest_pose(placement.pose)
        moved.append(tracker.update(placement.pushed(TEACHER_CHECK_DEPTH_MM)).lesions[li]
                     .displacement)
    assert gaps[li] == pytest.approx(np.linalg.norm(moved[0] - moved[1])
                                     / np.linalg.norm(moved[0]), rel=1e-6)
    assert 0.0 < gaps[li] < 0.5  # two grids of one FE: near, never the same


def test_the_tracker_widens_its_bounds_by_the_check(checked):
    case, check = checked
    tracker = Tracker.load(case, engine="net")
    assert tracker.lesion_check is not None and "self-check" in tracker.bound_basis
    assert "finer grid" in tracker.bound_basis
    from biopsynav.info import case_summary

    assert case_summary(case.dir)["bounds"].startswith("widened by each lesion's self-check")
    li = next(i for i, les in enumerate(case.anatomy.lesions)
              if check["lesions"][str(les.id)]["status"][-1] == "ok")
    placement = place_case_probe(case, li)
    tracker.set_rest_pose(placement.pose)
    result = tracker.update(placement.pushed(DEPTHS[-1]))
    assert result.reliable
    lesion = result.lesions[li]
    rel = check["lesions"][str(lesion.id)]["relative"][-1]
    gap = check["lesions"][str(lesion.id)]["teacher_gap"]
    expected = error_bound_mm(lesion.displacement[None], DEPTHS[-1], np.array([rel]),
                              np.array([np.nan if gap is None else gap]))[0]
    assert lesion.bound_mm == pytest.approx(expected, rel=0.05)  # depth: the contact's mean


def test_a_model_trained_again_loses_its_check(checked, tmp_path):
    """The check is bound to the model's meta.json: another model ignores it, and says so."""
    case, _ = checked
    other = tmp_path / "case"
    shutil.copytree(case.dir, other)
    meta_path = other / "model" / "meta.json"
    meta = json.loads(meta_path.read_text())
    meta["iterations_done"] = meta.get("iterations_done", 0) + 1
    from biopsynav.inference.model_files import meta_checksum

    meta["checksum"] = meta_checksum(meta)
    meta_path.write_text(json.dumps(meta))
    tracker = Tracker.load(Case.load(other), engine="net")
    assert tracker.lesion_check is None and "without the lesion self-check" in tracker.bound_basis


def test_the_check_in_two_worker_processes_matches_one(checked, tmp_path):
    case, check = checked
    copy = tmp_path / "case"
    shutil.copytree(case.dir, copy)
    again = run_lesion_check(Case.load(copy), workers=2, log=lambda _: None, depths_mm=DEPTHS)
    for lesion_id, lesion in check["lesions"].items():
        got = again["lesions"][lesion_id]
        assert got["status"] == lesion["status"]
        assert [m is None for m in got["miss_mm"]] == [m is None for m in lesion["miss_mm"]]
        # the same pushes and engines (the FE factoring on another thread count): the same
        # answers to far below the check's millimetres
        assert np.allclose([m for m in got["miss_mm"] if m is not None],
                           [m for m in lesion["miss_mm"] if m is not None], atol=1e-4)
        assert (got["teacher_gap"] is None) == (lesion["teacher_gap"] is None)
        if got["teacher_gap"] is not None:
            assert got["teacher_gap"] == pytest.approx(lesion["teacher_gap"], abs=1e-5)
