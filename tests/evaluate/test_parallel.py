"""Table 2's fine-grid ground truth and FE teacher solved in worker processes give the records
of a run that solves them push by push in this process."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from biopsynav.case import Case
from biopsynav.evaluate.simulation import run_simulation


@pytest.fixture(scope="module")
def small_table2_case(coarse_phantom) -> Case:
    """The coarse phantom with Table 2 cut to two lesions of two pushes on a 1.5x finer grid."""
    cfg = dataclasses.replace(coarse_phantom.cfg, evaluate=dataclasses.replace(
        coarse_phantom.cfg.evaluate, max_lesions=2, deformations_per_lesion=2,
        reference_refinement=1.5, reference="fine_grid"))
    return Case(coarse_phantom.dir, cfg, coarse_phantom.anatomy, coarse_phantom.grid)


def test_the_ground_truth_and_teacher_in_two_processes_are_those_of_this_process(small_table2_case):
    said: list[str] = []
    said_alone: list[str] = []
    alone = run_simulation(small_table2_case, methods=("fem", "rigid"), log=said_alone.append,
                           workers=1, keep=False)
    shared = run_simulation(small_table2_case, methods=("fem", "rigid"), log=said.append,
                            workers=2, keep=False)
    # solved here, each push is announced before its solve (a deep one can take minutes);
    # solved beforehand in the workers, none is
    announced = [line for line in said_alone if ": push " in line]
    assert len(announced) == 4 and announced[-1].endswith(" mm) ..."), said_alone
    assert "push 2 of 2" in announced[-1]
    assert not [line for line in said if ": push " in line], said
    assert any("ground truth: 4 pushes of 2 lesions solved in 2 processes" in line
               for line in said), said
    assert any("FE teacher: 4 pushes of 2 lesions solved in 2 processes" in line
               for line in said), said
    assert alone["placements"] == shared["placements"]
    assert len(alone["records"]) == len(shared["records"]) == 2 * 2 * 3  # + the reference's
    for a, b in zip(alone["records"], shared["records"], strict=True):
        assert (a["lesion"], a["push"], a["method"], a["status"]) == \
            (b["lesion"], b["push"], b["method"], b["status"])
        if a["tre_mm"] is None:
            assert b["tre_mm"] is None
        else:  # one Pardiso thread against two: round-off
            assert b["tre_mm"] == pytest.approx(a["tre_mm"], abs=1e-6)
    def facts(result: dict) -> dict:  # without the build time in the description
        return {k: v for k, v in result["reference"].items() if k != "description"}

    assert facts(shared) == facts(alone)


def test_the_ground_truth_is_kept_and_served_to_the_next_evaluation(small_table2_case,
                                                                     tmp_path):
    """A second evaluation serves the fine-grid truth from eval/table2_fine_grid_answers.json
    (the same records, no solve); a malformed lesion there is solved again."""
    case = dataclasses.replace(small_table2_case, dir=tmp_path)
    first: list[str] = []
    solved = run_simulation(case, methods=("rigid",), log=first.append, workers=1)
    kept_file = case.paths.table2_fine_grid_cache
    assert kept_file.is_file() and any(": push 2 of 2" in line for line in first)
    again: list[str] = []
    served = run_simulation(case, methods=("rigid",), log=again.append, workers=2)
    assert any("ground truth: 2 of 2 lesions kept from an earlier evaluation" in line
               for line in again), again
    assert not [line for line in again if ": push " in line or "solved in" in line], again
    assert served["records"] == solved["records"]  # the reference's own solve times included
    assert served["reference"]["kept_lesions"] == 2 and "kept_lesions" not in solved["reference"]
    assert "2 lesions' answers kept from an earlier evaluation" in \
        served["reference"]["description"]
    stored = json.loads(kept_file.read_text())
    (lesions,) = stored["truths"].values()
    lesions[next(iter(lesions))]["pushes"] = {"x": {"status": "ok"}}
    kept_file.write_text(json.dumps(stored))
    said: list[str] = []
    again = run_simulation(case, methods=("rigid",), log=said.append, workers=1)
    assert any("1 of 2 lesions kept" in line for line in said), said

    def untimed(result: dict) -> list:  # that lesion's truth solved again: its own times
        return [{k: v for k, v in r.items() if k not in ("time_ms", "tre_mm")}
                for r in result["records"]]

    assert untimed(again) == untimed(solved)
    for a, b in zip(again["records"], solved["records"], strict=True):  # factored on two
        assert (a["tre_mm"] is None and b["tre_mm"] is None) or \
            a["tre_mm"] == pytest.approx(b["tre_mm"], abs=1e-9)  # threads: round-off


def test_the_kept_truth_is_keyed_by_what_it_depends_on(small_table2_case, tmp_path):
    """Another setting outside [network], [igtl] and [case] is another truth; the file keeps
    the four written last; a damaged or foreign file holds none."""
    from biopsynav.evaluate.kept import KeptTruth, truth_key
    from biopsynav.evaluate.simulation import evaluation_solver_settings

    case = small_table2_case
    settings = evaluation_solver_settings(case)
    key = truth_key(case, 1.5, settings)
    net = dataclasses.replace(case.cfg.network, iterations=case.cfg.network.iterations + 1)
    assert truth_key(dataclasses.replace(case, cfg=dataclasses.replace(case.cfg, network=net)),
                     1.5, settings) == key
    solver = dataclasses.replace(case.cfg.solver, max_iterations=41)
    assert truth_key(dataclasses.replace(case, cfg=dataclasses.replace(case.cfg, solver=solver)),
                     1.5, settings) != key
    assert truth_key(case, 2.0, settings) != key
    path = tmp_path / "kept.json"
    rest = np.eye(4)
    KeptTruth(path, key).keep(rest, [], 7, [])
    assert KeptTruth(path, key).answers(rest, []) == (7, [])
    assert KeptTruth(path, "another").answers(rest, []) is None
    for other in ("quick", "a", "b"):  # the file keeps the KEPT_TRUTHS written last
        KeptTruth(path, other).keep(rest, [], 3, [])
        assert KeptTruth(path, key).answers(rest, []) == (7, [])
    KeptTruth(path, "c").keep(rest, [], 5, [])
    assert KeptTruth(path, key).answers(rest, []) is None
    assert KeptTruth(path, "quick").answers(rest, []) == (3, [])
    assert KeptTruth(path, "c").answers(rest, []) == (5, [])
    path.write_text(path.read_text()[:20])
    assert KeptTruth(path, key).answers(rest, []) is None


def test_a_negative_worker_count_is_refused_before_any_work(coarse_phantom, capsys):
    from biopsynav.cli import main

    eval_dir = coarse_phantom.dir / "eval"
    before = sorted(p.name for p in eval_dir.iterdir()) if eval_dir.is_dir() else []
    assert main(["evaluate", str(coarse_phantom.dir), "--workers", "-2"]) == 2
    err = capsys.readouterr().err
    assert "--workers: must be >= 0 (0: one per core), got -2" in err and "Traceback" not in err
    after = sorted(p.name for p in eval_dir.iterdir()) if eval_dir.is_dir() else []
    assert after == before
