"""The force range calibrated for the breast at hand ([probe] calibrate_force)."""

from __future__ import annotations

import math
import os
import shutil
import signal

import numpy as np
import pytest

from biopsynav.config import load_config, save_config
from biopsynav.dataset import calibrate
from biopsynav.dataset.calibrate import best_force, next_force
from biopsynav.dataset.generate import format_run_summary, generate_case
from biopsynav.dataset.store import open_store, protocol_dict
from biopsynav.errors import BiopsynavError


def test_search_steps_stay_in_the_bracket():
    # a response d = 10 f (linear): one proportional step lands on the target
    assert next_force([(1.0, 10.0)], 35.0) == pytest.approx(3.5)
    # a failed solve is beyond any depth: halve, then bisect between short and failed
    assert next_force([(4.0, math.inf)], 35.0) == pytest.approx(2.0)
    step = next_force([(4.0, math.inf), (2.0, 14.0)], 35.0)
    assert step == pytest.approx(math.sqrt(8.0))  # 5 N proposed, outside (2, 4): bisected
    # d = f^2: the secant slope 2 is found from two points
    assert next_force([(1.0, 1.0), (2.0, 4.0)], 36.0) == pytest.approx(6.0)
    assert next_force([(3.0, 30.0), (3.1, math.inf)], 35.0) is None  # bracket closed
    assert best_force([(3.0, 30.0), (3.1, math.inf)], 35.0) == (3.0, 30.0)
    assert best_force([(4.0, 36.0), (3.0, 30.0)], 35.0) == (4.0, 36.0)
    with pytest.raises(BiopsynavError, match="every force tried"):
        best_force([(4.0, math.inf), (2.0, 50.0)], 35.0)


def test_a_round_stops_once_its_quantile_can_only_be_a_failure():
    """failures_allowed is the count of failed pushes the QUANTILE depth survives: one more
    and it is inf whatever the unsolved pushes would give (so a round may stop there)."""
    for n in range(1, 120):
        allowed = calibrate.failures_allowed(n)
        for failed in range(n + 1):
            depths = np.concatenate([np.linspace(1.0, 40.0, n - failed), np.full(failed, np.inf)])
            assert math.isinf(calibrate.quantile_depth(depths)) == (failed > allowed), (n, failed)
    assert calibrate.failures_allowed(48) == 4 and calibrate.failures_allowed(6) == 0


@pytest.fixture()
def cancelled(monkeypatch) -> list:
    """The futures cancelled from outside their pool while the test runs: none should be (on
    Python 3.11 a future cancelled so in a pool that then breaks is an InvalidStateError
    traceback in the executor's thread, seen in CI)."""
    from concurrent.futures import Future

    calls, cancel = [], Future.cancel
    monkeypatch.setattr(Future, "cancel", lambda f: calls.append(f) or cancel(f))
    return calls


def test_a_failing_round_is_left_at_its_first_failure_too_many(base_case, monkeypatch,
                                                               cancelled):
    """At a force far too strong, a round of 6 pushes (no failure allowed) solved by one
    worker process stops at its first failed solve, the rest never sent (nothing cancelled);
    solving every push gives the same failed quantile."""
    from biopsynav.case import Case

    case = Case.load(base_case)
    case.cfg.probe.calibration_pushes = 6
    order = np.arange(6)[::-1]
    with calibrate.CalibrationSolves(case, workers=1) as solves:
        depths = solves.depths(calibrate.TEACHER, 40.0, order)
        solved = solves.count
        assert 0 < solved < 6  # left at the first failure: the rest unsolved
        assert np.isinf(depths[order[solved - 1]])  # the one that failed
        assert np.isfinite(depths[order[:solved - 1]]).all()
        assert np.isinf(depths[order[solved:]]).all()
        assert math.isinf(calibrate.quantile_depth(depths)) and not cancelled
        monkeypatch.setattr(calibrate, "failures_allowed", lambda n: n)
        every = solves.depths(calibrate.TEACHER, 40.0, order)
        assert solves.count - solved == 6 and math.isinf(calibrate.quantile_depth(every))
    np.testing.assert_array_equal(every[order[:solved]], depths[order[:solved]])


def test_two_workers_solve_a_round_to_the_bits_of_one(base_case):
    """A calibration round spread over two worker processes gives each push the same
    probe displacement, to the bit, as one worker: each solve runs on one thread whatever
    their number, so the rounds and the force found do not depend on it."""
    from biopsynav.case import Case

    case = Case.load(base_case)
    case.cfg.probe.calibration_pushes = 6
    order = np.arange(6)
    with calibrate.CalibrationSolves(case, 1) as one, calibrate.CalibrationSolves(case, 2) as two:
        alone, shared = (s.depths(calibrate.TEACHER, 1.5, order) for s in (one, two))
    assert np.isfinite(alone).all() and alone.min() > 0
    np.testing.assert_array_equal(alone, shared)
    assert one.count == two.count == 6


def _die(stage, index, force_n):
    os.kill(os.getpid(), signal.SIGKILL)


def _raise(stage, index, force_n):
    raise ValueError(f"no model for {stage}")


def test_a_worker_that_dies_or_errs_is_one_line_naming_the_calibration(base_case, monkeypatch,
                                                                        cancelled):
    """A calibration worker killed (out of memory, say) or raising is said in one line that
    names the force calibration, never a traceback from the pool."""
    from biopsynav.case import Case

    case = Case.load(base_case)
    case.cfg.probe.calibration_pushes = 4
    for task, words in ((_die, "a worker process died"),
                        (_raise, "a solve failed in its worker: ValueError: no model for")):
        monkeypatch.setattr(calibrate, "calibration_depth", task)  # sent to the worker by name
        with calibrate.CalibrationSolves(case, 1) as solves:
            with pytest.raises(BiopsynavError, match=f"force calibration: {words}"):
                solves.depths(calibrate.TEACHER, 1.0, np.arange(4))
            assert not cancelled  # the queued solves are left to the pool


def test_generation_calibrates_once_records_it_and_draws_within_it(base_case, tmp_path,
                                                                    monkeypatch):
    case_dir = tmp_path / "case"
    shutil.copytree(base_case, case_dir)
    cfg = load_config(case_dir)
    cfg.probe.calibrate_force = True
    cfg.probe.calibration_pushes = 6  # fewer: the same search
    cfg.probe.train_force_scale = 1.5  # training forces beyond the calibrated range
    cfg.probe.f_max_n = 40.0  # far too strong a first guess: the search must come down
    cfg.dataset.n_train, cfg.dataset.n_test = 6, 2
    save_config(case_dir, cfg)
    summary = generate_case(case_dir, workers=1, progress=False)
    found = summary["force_calibration"]
    assert found["f_max_n"] < 40.0 and found["pushes"] == 6
    # the search comes down from 40 N through three failed rounds and ends within tolerance
    # (5.38 N, 34.81 mm for 35 mm, 2026-12-02): no failed last round excuses a miss
    assert abs(found["quantile_depth_mm"] - cfg.probe.max_push_mm) \
        <= calibrate.TOLERANCE * cfg.probe.max_push_mm
    assert found["rounds"][-1] == pytest.approx([found["f_max_n"], found["quantile_depth_mm"]],
                                                abs=1e-4)  # the rounds are kept rounded
    store = open_store(case_dir / "dataset.zarr")
    assert store.group.attrs["force_calibration"] == found
    force = store.read_meta()["force_n"]  # training: up to train_force_scale times the range
    assert force[6:].max() <= found["f_max_n"] + 1e-9
    assert force[:6].max() <= cfg.probe.train_force_scale * found["f_max_n"] + 1e-9
    assert load_config(case_dir).probe.f_max_n == 40.0, "case.toml is left as the user wrote it"
    assert "calibration_pushes" not in protocol_dict(cfg, 6, 2)["probe"]  # recorded instead
    text = format_run_summary(summary)  # what `biopsynav generate` prints
    training = cfg.probe.train_force_scale * found["f_max_n"]
    assert f"up to {found['f_max_n']:.2f} N (training pushes up to {training:.2f} N), " \
        "calibrated (6 pushes" in text
    assert text.startswith(f"data set: 8 of 8 samples (6 training, 2 held out) in {case_dir}")
    assert "{" not in text and str(case_dir / "dataset.png") in text

    def refuse(case):
        raise AssertionError("calibrated again")

    monkeypatch.setattr(calibrate, "calibrate_force", refuse)
    again = generate_case(case_dir, workers=1, progress=False)
    assert again["force_calibration"] == found and again["computed_this_run"] == 0


def test_a_refined_teacher_starts_its_search_from_the_case_grid(base_case, tmp_path,
                                                              monkeypatch):
    """With [dataset] teacher_refine = 2 the search runs on the case grid first and the
    teacher's own rounds start from its answer. The teacher's search is held to two rounds
    (its first force may fail on the finer grid and the second halve it; the rounds after
    are the plain search's, tested above) and each round to 4 pushes instead of ``[probe]
    calibration_pushes``, which keeps this test at a fraction of its time."""
    from biopsynav.case import Case

    searches = []
    search = calibrate.search_force

    def teacher_once(*args):
        if searches:
            monkeypatch.setattr(calibrate, "MAX_ROUNDS", 2)
        searches.append(args[2])  # its first force
        return search(*args)

    monkeypatch.setattr(calibrate, "search_force", teacher_once)
    case_dir = tmp_path / "case"
    shutil.copytree(base_case, case_dir)
    cfg = load_config(case_dir)
    cfg.dataset.teacher_refine = 2
    cfg.probe.calibration_pushes = 4
    save_config(case_dir, cfg)
    found = calibrate.calibrate_force(Case.load(case_dir))
    coarse = found["case_grid_rounds"]
    assert coarse and found["rounds"][0][0] == pytest.approx(
        calibrate.best_force([(f, d if d is not None else math.inf) for f, d in coarse],
                             cfg.probe.max_push_mm)[0], rel=1e-3)
    assert found["rounds"][0][0] != cfg.probe.f_max_n  # not case.toml's first guess
    assert len(searches) == 2 and len(found["rounds"]) <= 2
