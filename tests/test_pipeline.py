"""`biopsynav run`: the case folder is read once into a Case and handed down the stages."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import pytest

from biopsynav.layout import CASE_FILE

_reads: list[str] | None = None


def _count_case_toml_reads(event: str, args: tuple) -> None:
    """Audit hook: every opening of a case.toml for reading, while a test listens."""
    if _reads is None or event != "open" or not isinstance(args[0], (str, Path)):
        return
    mode = args[1] if len(args) > 1 and isinstance(args[1], str) else "r"
    if Path(args[0]).name == CASE_FILE and not set(mode) & set("wax+"):
        _reads.append(str(args[0]))


sys.addaudithook(_count_case_toml_reads)


def _small_settings(case: Path) -> None:
    from biopsynav.config import load_config, save_config
    from tests.runs import small_run_settings

    cfg = load_config(case)
    small_run_settings(cfg)
    save_config(case, cfg)


def test_run_reads_case_toml_once_and_runs_every_stage(base_case, tmp_path):
    global _reads
    from biopsynav.cli import main

    case = tmp_path / "case"
    shutil.copytree(base_case, case)
    _small_settings(case)
    (case / "grid.npz").unlink()  # stage 1 rebuilds anatomy and grid as well
    _reads = []
    try:
        assert main(["run", str(case), "--workers", "1"]) == 0
        reads = list(_reads)
    finally:
        _reads = None
    assert len(reads) == 1, reads
    for rel in ("grid.npz", "dataset.zarr", "model/meta.json", "eval/table1.json",
                "eval/table2.json", "report.html"):
        assert (case / rel).exists(), rel
    # the same, with every stage up to date: still one read
    _reads = []
    try:
        assert main(["run", str(case)]) == 0
        assert len(_reads) == 1, _reads
    finally:
        _reads = None


def test_the_run_estimate_scales_with_the_work_and_the_machine(base_case):
    """The expected minutes follow the stages' work (iterations, samples) and the speed
    probes; the probe itself measures a finite step."""
    import dataclasses

    from biopsynav.case import Case
    from biopsynav.reference_registry import chosen_reference
    from biopsynav.runtime import (
        FE_EXPONENT,
        LESION_CHECK,
        PHANTOM_ACTIVE_CELLS,
        PHANTOM_PUSH_MINUTES,
        REFERENCE,
        REFINE_PUSH_MINUTES,
        TRAINING_STEP_FACTOR,
        estimate_run,
        lesion_check_minutes,
        probe_seconds,
    )

    case = Case.load(base_case)
    ref = REFERENCE["probe_s"]
    # the phantom's default ("auto") truth is its stored one: no solves, whatever the pushes
    assert chosen_reference(case)[0] == "stored"
    stored = estimate_run(case, (ref, ref), workers=2).minutes["evaluate and report"]
    case.cfg.evaluate = dataclasses.replace(case.cfg.evaluate, reference="fine_grid")
    same = estimate_run(case, (ref, ref), workers=2)
    assert same.slowness == pytest.approx(1.0)
    assert same.minutes["evaluate and report"] > stored
    # a training: its iterations at the probe's step, times what an iteration costs beyond it
    assert same.minutes["train"] == pytest.approx(
        case.cfg.network.iterations * ref * TRAINING_STEP_FACTOR / 60.0)
    slow = estimate_run(case, (2.0 * ref, 2.0 * ref), workers=2)
    assert slow.slowness == pytest.approx(2.0)
    assert slow.total == pytest.approx(2.0 * same.total)
    case.cfg.network = dataclasses.replace(case.cfg.network,
                                           iterations=2 * case.cfg.network.iterations)
    case.cfg.dataset = dataclasses.replace(case.cfg.dataset, n_train=2 * case.cfg.dataset.n_train,
                                           n_test=2 * case.cfg.dataset.n_test)
    double = estimate_run(case, (ref, ref), workers=2)
    for stage in ("train", "generate"):
        assert double.minutes[stage] == pytest.approx(2.0 * same.minutes[stage])
    pushes = []
    for samples in (500, 1000):  # the rigid pushes: their count, not the cells
        case.cfg.refine = dataclasses.replace(case.cfg.refine, samples=samples)
        pushes.append(estimate_run(case, (ref, ref), workers=2).minutes["refine pushes"])
    # the built-in phantom at its own measured cost (by its cells^1.3), any other anatomy at
    # the breasts' median
    phantom = PHANTOM_PUSH_MINUTES * (case.grid.active_cells.sum() / PHANTOM_ACTIVE_CELLS) \
        ** FE_EXPONENT
    is_phantom = case.cfg.anatomy.source == "phantom"
    per_1000 = phantom if is_phantom else REFINE_PUSH_MINUTES
    assert pushes == pytest.approx([0.5 * per_1000, per_1000])
    case.cfg.anatomy = dataclasses.replace(case.cfg.anatomy,
                                           source="labelmap" if is_phantom else "phantom")
    other = estimate_run(case, (ref, ref), workers=2).minutes["refine pushes"]
    assert other == pytest.approx(phantom + REFINE_PUSH_MINUTES - per_1000)
    assert double.minutes["evaluate and report"] == same.minutes["evaluate and report"]
    case.cfg.evaluate = dataclasses.replace(case.cfg.evaluate, deformations_per_lesion=2
                                            * case.cfg.evaluate.deformations_per_lesion)
    # Table 2's solves double; each lesion's self-check stays: its lesions and cells^1.3
    check = lesion_check_minutes(case)
    assert check == pytest.approx(
        LESION_CHECK["minutes"] * len(case.anatomy.lesions) / LESION_CHECK["lesions"]
        * (case.grid.active_cells.sum() / LESION_CHECK["active_cells"]) ** FE_EXPONENT)
    evaluation = estimate_run(case, (ref, ref), workers=2).minutes["evaluate and report"]
    assert evaluation == pytest.approx(2.0 * same.minutes["evaluate and report"] - check)
    assert "expected on this machine today: about" in same.line()
    assert 0.0 < probe_seconds(case) < 60.0



def test_deeper_training_pushes_are_expected_to_cost_more(base_case):
    """``[probe] train_depth_exponent`` below 1 draws deeper training pushes: the estimate
    prices each at :func:`depth_cost_factor` (more than 1, the more the smaller the
    exponent), the held-out pushes at the uniform cost."""
    import dataclasses

    from biopsynav.case import Case
    from biopsynav.runtime import REFERENCE, depth_cost_factor, estimate_run

    assert depth_cost_factor(1.0, 35.0) == pytest.approx(1.0)
    assert 1.0 < depth_cost_factor(0.7, 35.0) < depth_cost_factor(0.5, 35.0)
    case = Case.load(base_case)
    ref = REFERENCE["probe_s"]
    case.cfg.probe = dataclasses.replace(case.cfg.probe, rigid_share=1.0, train_depth_exponent=1.0)
    uniform = estimate_run(case, (ref, ref), workers=2).minutes["generate"]
    case.cfg.probe = dataclasses.replace(case.cfg.probe, train_depth_exponent=0.7)
    deep = estimate_run(case, (ref, ref), workers=2).minutes["generate"]
    n_train, n_test = case.cfg.dataset.n_train, case.cfg.dataset.n_test
    factor = depth_cost_factor(0.7, case.cfg.probe.max_push_mm)
    assert deep == pytest.approx(uniform * (n_train * factor + n_test) / (n_train + n_test))

def test_the_estimate_follows_the_fe_processes_and_prices_the_p2_teacher(base_case,
                                                                         monkeypatch):
    """``run --workers 1`` on 2 cores doubles the FE stages (not the trainings); the P2
    teacher's refine pushes cost :func:`p2_push_seconds` each, shared by the processes."""
    import dataclasses

    from biopsynav import runtime
    from biopsynav.case import Case

    monkeypatch.setattr(runtime.os, "cpu_count", lambda: 2)
    case = Case.load(base_case)
    case.cfg.refine = dataclasses.replace(case.cfg.refine, samples=40, teacher="grid")
    case.cfg.evaluate = dataclasses.replace(case.cfg.evaluate, reference="fine_grid")
    ref = runtime.REFERENCE["probe_s"]
    two = runtime.estimate_run(case, (ref, ref), workers=2)
    assert runtime.estimate_run(case, (ref, ref)).minutes == two.minutes  # 0: one a core
    one = runtime.estimate_run(case, (ref, ref), workers=1)
    for stage in ("generate", "refine pushes"):
        assert one.minutes[stage] == pytest.approx(2.0 * two.minutes[stage])
    assert one.minutes["train"] == two.minutes["train"]
    assert one.minutes["evaluate and report"] > 1.5 * two.minutes["evaluate and report"]
    assert runtime.estimate_run(case, (ref, ref), workers=8).minutes == two.minutes
    case.cfg.refine = dataclasses.replace(case.cfg.refine, teacher="p2")
    p2 = runtime.estimate_run(case, (2 * ref, ref), workers=1).minutes["refine pushes"]
    a, b = runtime.P2_PUSH_S  # twice as slow: twice the seconds, capped at the same limit
    assert p2 == pytest.approx(40 * runtime.p2_push_seconds(case.cfg.refine.max_push_mm,
                                                             (2 * a, b)) / 60.0)
    seconds = runtime.p2_push_seconds(case.cfg.refine.max_push_mm)
    # deeper pushes cost more, none more than the push's time limit
    from biopsynav.dataset.converged import PUSH_LIMIT_S

    assert 0.0 < runtime.p2_push_seconds(10.0) < seconds < PUSH_LIMIT_S
    assert runtime.p2_push_seconds(500.0) == pytest.approx(PUSH_LIMIT_S, rel=0.1)
    limited = runtime.estimate_run(case, (ref, ref), workers=2).minutes["refine pushes"]
    case.cfg.refine = dataclasses.replace(case.cfg.refine, teacher_push_limit_s=0.0)  # none
    assert runtime.estimate_run(case, (ref, ref), workers=2).minutes["refine pushes"] > limited


def test_a_fine_grid_truth_is_expected_to_cost_its_solves(base_case):
    """With the fine-grid truth the evaluation's estimate is the measured fine-grid run's,
    scaled by the rounds of lesions on the cores (a lesion is one task: one lesion on two
    cores costs what two do, the single-tumour patient's case), the pushes and the fine
    grid's cells^1.3; a stored truth keeps its own."""
    import dataclasses

    from biopsynav.case import Case
    from biopsynav.runtime import (
        FE_EXPONENT,
        FINE_GRID_TABLE2,
        evaluated_lesions,
        evaluation_minutes,
    )

    case = Case.load(base_case)
    minutes = []
    for refinement in (1.5, 3.0):
        case.cfg.evaluate = dataclasses.replace(case.cfg.evaluate, reference="fine_grid",
                                                reference_refinement=refinement)
        minutes.append(evaluation_minutes(case, cores=2))
    assert minutes[1] == pytest.approx(minutes[0] * 8.0 ** FE_EXPONENT)
    rounds = -(-evaluated_lesions(case) // 2)
    cells = (case.grid.active_cells.sum() * 27.0 / (FINE_GRID_TABLE2["active_cells"] * 8.0))
    assert minutes[1] == pytest.approx(
        FINE_GRID_TABLE2["minutes"] * cells ** FE_EXPONENT * rounds / FINE_GRID_TABLE2["rounds"]
        * case.cfg.evaluate.deformations_per_lesion / FINE_GRID_TABLE2["pushes_per_lesion"])
    case.cfg.evaluate = dataclasses.replace(case.cfg.evaluate, reference="stored")
    assert evaluation_minutes(case) != pytest.approx(minutes[1])
    by_lesions = []
    for n in (1, 2):
        case.cfg.evaluate = dataclasses.replace(case.cfg.evaluate, max_lesions=n,
                                                reference="fine_grid")
        by_lesions.append(evaluation_minutes(case, cores=2))
    assert evaluated_lesions(case) == 2
    assert by_lesions[0] == pytest.approx(by_lesions[1]), "one lesion keeps one core busy"
    assert evaluation_minutes(case, cores=1) == pytest.approx(2 * by_lesions[1])


def test_what_remains_is_rescaled_by_what_the_stages_took():
    """The data stage taking twice its estimate doubles the evaluation's FE solves ahead (not
    the rigid pushes); the training taking half halves the training ahead; a stage that was
    up to date rescales nothing."""
    from biopsynav.runtime import Estimate, remaining_minutes

    est = Estimate({"generate": 2.0, "train": 10.0, "refine pushes": 3.0,
                    "refine training": 2.0, "evaluate and report": 1.0}, 1.0)
    assert remaining_minutes(est, {}) == pytest.approx(18.0)
    assert remaining_minutes(est, {"anatomy and grid": 1.0, "training data": 240.0}) == \
        pytest.approx(10.0 + 3.0 + 2.0 + 2.0)
    assert remaining_minutes(est, {"training data": 240.0, "network training": 300.0}) == \
        pytest.approx(3.0 + 1.0 + 2.0)
    assert remaining_minutes(est, {"training data": 0.5}) == pytest.approx(16.0)
    assert remaining_minutes(est, {"training data": 240.0, "network training": 300.0,
                                   "refine": 600.0, "evaluation": 60.0}) == 0.0


def test_a_refined_model_counts_for_the_evaluation_only_while_refine_is_asked(base_case,
                                                                              tmp_path):
    """A refine/model left from an earlier [refine] does not make Table 2 stale once
    [refine] samples = 0."""
    from biopsynav.case import Case
    from biopsynav.pipeline import _refined_meta

    case = Case.load(base_case)
    case.cfg.refine.samples = 0
    assert _refined_meta(case) == ()
    case.cfg.refine.samples = 40
    assert _refined_meta(case) == (case.dir / "refine" / "model" / "meta.json",)


def test_the_stage_table_ends_with_the_whole_run():
    from biopsynav.runtime import stage_table

    table = stage_table({"training data": 120.0, "network training": 600.0})
    lines = table.splitlines()
    assert lines[0].startswith("stage") and lines[-1].split() == ["whole", "run", "12.0"]
    assert lines[1].split()[-1] == "2.0" and lines[2].split()[-1] == "10.0"
