"""Multi-fidelity training (``[refine]``): the case's network trained further on a finer
teacher's rigid pushes in ``CASE_DIR/refine``, and the tracker using that model."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest

from biopsynav.case import Case
from biopsynav.config import CaseConfig, config_from_dict, load_config, save_config
from biopsynav.errors import InputError
from biopsynav.refine import refined_config


def test_the_refine_configuration_derives_from_the_case():
    cfg = CaseConfig()
    cfg.case.name = "p1"
    cfg.refine.samples, cfg.refine.held_out, cfg.refine.max_push_mm = 30, 5, 28.0
    out = refined_config(cfg)
    assert out.probe.rigid_share == 1.0 and out.probe.max_push_mm == 28.0
    assert out.probe.lesion_share == cfg.refine.lesion_share
    cfg.refine.lesion_share = 0.5
    assert refined_config(cfg).probe.lesion_share == 0.5
    assert not out.probe.calibrate_force
    assert (out.dataset.n_train, out.dataset.n_test) == (25, 5)
    assert out.dataset.teacher_refine == cfg.refine.teacher_refine == 1.0  # the case grid
    assert out.dataset.teacher_extrapolation == cfg.refine.extrapolation == 0.0
    assert out.tracker.fem_contact == "elastic"  # its rigid pushes: elastic contact
    cfg.refine.teacher_refine, cfg.refine.extrapolation = 1.46, 2.0
    out = refined_config(cfg)
    assert (out.dataset.teacher_refine, out.dataset.teacher_extrapolation) == (1.46, 2.0)
    with pytest.raises(InputError, match="extrapolation"):
        config_from_dict({"refine": {"teacher_refine": 1.0, "extrapolation": 2.0}})
    assert out.network.init_from == "../model"
    assert out.network.iterations == cfg.refine.iterations
    assert out.refine.samples == 0  # the refine case does not refine again
    assert out.grid == cfg.grid and out.solver == cfg.solver
    assert out.material.tissues == cfg.material.tissues
    # the mixed recipe: force patches with one law, the refine teacher with its own
    assert (cfg.material.model, cfg.refine.material_model) == (
        "neo-hookean", "neo-hookean-split-sri-inner")
    assert out.material.model == out.refine.material_model == "neo-hookean-split-sri-inner"
    cfg.refine.fictitious_stiffness = 0.05  # the refine teacher's, the force patches' kept
    out = refined_config(cfg)
    assert (cfg.material.fictitious_stiffness, out.material.fictitious_stiffness) == (0.0, 0.05)
    assert out.refine.fictitious_stiffness == 0.05
    assert cfg.probe.rigid_share == 0.0 and cfg.network.init_from == ""  # the case's untouched


def test_held_out_must_leave_training_samples():
    with pytest.raises(InputError, match="held_out"):
        config_from_dict({"refine": {"samples": 5, "held_out": 5}})
    assert config_from_dict({"refine": {"samples": 0, "held_out": 10}}).refine.samples == 0


@pytest.fixture(scope="module")
def refined(trained_case, tmp_path_factory):
    """The trained coarse phantom case with [refine] 4 samples (1 held out) of pushes to
    10 mm of the extrapolated 5 mm teacher, trained further for 4 iterations by `biopsynav
    refine`."""
    from biopsynav.cli import main

    case = tmp_path_factory.mktemp("refine") / "case"
    shutil.copytree(trained_case, case)
    cfg = load_config(case)
    cfg.refine.samples, cfg.refine.held_out = 4, 1
    cfg.refine.iterations, cfg.refine.max_push_mm = 4, 10.0
    cfg.refine.teacher_refine, cfg.refine.extrapolation = 1.46, 2.0
    save_config(case, cfg)
    with pytest.raises(InputError, match="refine"):
        Case.load(case).tracking_model  # noqa: B018  (not trained further yet)
    assert main(["refine", str(case), "--workers", "1"]) == 0
    return case


def test_refine_trains_the_case_network_further_on_fine_rigid_pushes(refined):
    fine = refined / "refine"
    summary = json.loads((fine / "dataset_summary.json").read_text())
    assert summary["count"] == 4 and summary["rigid_pushes"] == 4
    assert 0 < summary["max_probe_disp_mm"] <= 10.0 + 1e-6
    meta = json.loads((fine / "model" / "meta.json").read_text())
    base = json.loads((refined / "model" / "meta.json").read_text())
    assert meta["teacher"]["teacher_refine"] == 1.46 and meta["teacher"]["rigid_share"] == 1.0
    assert meta["teacher"]["teacher_extrapolation"] == 2.0
    assert meta["training"]["init_from"]["checksum"] == base["checksum"]
    assert meta["fingerprint"] == base["fingerprint"]  # same anatomy and grid


def test_the_tracker_uses_the_refined_model(refined):
    from biopsynav.info import model_teacher
    from biopsynav.tracker import Tracker

    case = Case.load(refined)
    assert case.tracking_model == refined / "refine" / "model"
    tracker = Tracker.load(case)
    assert tracker._surrogate.model_dir == refined / "refine" / "model"
    assert "started from the model" in model_teacher(case)


def test_refine_again_is_up_to_date_and_off_means_the_case_model(refined, capsys):
    from biopsynav.cli import main

    meta = refined / "refine" / "model" / "meta.json"
    before = meta.stat().st_mtime_ns
    assert main(["refine", str(refined)]) == 0
    assert meta.stat().st_mtime_ns == before and "up to date" in capsys.readouterr().out
    cfg = load_config(refined)
    cfg.refine.samples = 0
    assert Case(refined, cfg, None, None).tracking_model == refined / "model"


def test_refine_needs_the_case_network_first(base_case, tmp_path):
    from biopsynav.pipeline import refine_stage

    case_dir = tmp_path / "case"
    shutil.copytree(base_case, case_dir)
    case = Case.load(case_dir)
    case.cfg.refine.samples = 4
    with pytest.raises(InputError, match="train it first"):
        refine_stage(case, workers=1)
    assert not (case_dir / "refine").exists()


def test_table1_covers_the_refined_model_too(refined):
    from biopsynav.cli import main

    assert main(["evaluate", str(refined), "--table1-only"]) == 0
    base = json.loads((refined / "eval" / "table1.json").read_text())
    fine = json.loads((refined / "refine" / "eval" / "table1.json").read_text())
    assert base["n_samples"] == 2 and fine["n_samples"] == 1  # each its own held-out pushes
    # the chain's case network (force patches) honours the contact points: trained and
    # evaluated through the contact projection; the refined one (rigid pushes, elastic
    # contact: points that lag the face) without it
    assert json.loads((refined / "model" / "meta.json").read_text())["baseline"]["projection"]
    assert base["contact_projection"] is True and fine["contact_projection"] is False


def test_the_report_names_the_refined_model(refined):
    from biopsynav.cli import main

    assert main(["evaluate", str(refined), "--table1-only"]) == 0
    assert main(["report", str(refined)]) == 0
    text = " ".join((refined / "report.md").read_text().split())
    assert "trained further on" in text
    assert "([refine], law neo-hookean-split-sri-inner, refine/eval)" in text  # its teacher
    assert "the case grid's force patches, law neo-hookean." in text  # Table 1's teacher
    from biopsynav.report.sections import refined_table1_blocks

    cfg = load_config(refined)
    cfg.refine.fictitious_stiffness = 0.05
    note = refined_table1_blocks(refined, cfg)[0].text
    assert "law neo-hookean-split-sri-inner (fictitious stiffness 0.05), refine/eval" in note
    assert note.endswith("law neo-hookean.")


def test_the_refine_folder_is_a_case_of_its_own(refined, capsys):
    from biopsynav.cli import main

    fine = Case.load(refined / "refine")
    assert fine.fingerprint() == Case.load(refined).fingerprint()
    assert fine.tracking_model == refined / "refine" / "model"
    assert main(["info", str(refined / "refine")]) == 0
    assert "-refine" in capsys.readouterr().out


def test_the_fe_engine_and_the_truth_follow_the_fine_teacher(refined):
    """The FE engine (track --engine fem, Table 2's FE column) solves on the fine teacher's
    grid, and a fine-grid truth no finer than that teacher is refused."""
    from biopsynav import reference_registry
    from biopsynav.tracker.core import fem_engine, fem_solver_settings

    case = Case.load(refined)
    tracker = fem_engine(case, None)
    assert tracker._teacher is not None and tracker._teacher.coarse is not None
    assert len(tracker._fem_model.hexes) > 2 * case.grid.active_cells.sum()
    # [tracker] spring_budget is for the case grid: the finer teacher's solves (1.46 times
    # finer) get as many times more
    settings = fem_solver_settings(case)
    assert fem_engine(case, settings)._fem_settings.first_attempt_budget == math.ceil(
        1.46 * settings.first_attempt_budget)
    case.cfg.evaluate.reference, case.cfg.evaluate.reference_refinement = "fine_grid", 2.0
    with pytest.raises(InputError, match="no finer than the network.s teacher"):
        reference_registry.check_reference(case)


def test_the_tracking_teacher_law_is_the_refine_law_and_the_case_network_keeps_its_own(
        refined):
    """The mixed recipe: force patches (and Table 1) with [material] model, the refine
    teacher with [refine] material_model; the FE engine, and the contact compliance behind
    the tracker's elastic input and linear baseline, use the latter."""
    from biopsynav.contact.greens import ContactCompliance
    from biopsynav.refine import fine_case
    from biopsynav.tracker.core import Tracker, fem_engine

    case = Case.load(refined)
    assert (case.cfg.material.model, case.cfg.refine.material_model) == (
        "neo-hookean", "neo-hookean-split-sri-inner")
    assert Case.load(refined / "refine").cfg.material.model == "neo-hookean-split-sri-inner"
    assert fem_engine(case, None)._fem_model.material == "neo-hookean-split-sri-inner"
    case.cfg.refine.fictitious_stiffness = 0.05
    assert fem_engine(case, None)._fem_model.fictitious == 0.05
    case.cfg.refine.fictitious_stiffness = 0.0
    compliance = Tracker.load(case, "net")._contact_compliance()
    refine_law = ContactCompliance.from_case(fine_case(case))
    patch_law = ContactCompliance.from_case(case)
    assert not np.allclose(refine_law.zt, patch_law.zt, rtol=1e-3)  # the laws differ at rest
    np.testing.assert_allclose(compliance.zt, refine_law.zt, rtol=1e-6)
    case.cfg.refine.samples = 0  # the case network alone: its own teacher's law throughout
    assert fem_engine(case, None)._fem_model.material == "neo-hookean"
    assert fem_engine(case, None)._fem_model.fictitious == 0.0


def test_run_refuses_a_truth_no_finer_than_the_refine_teacher_before_any_work(base_case,
                                                                             tmp_path):
    from biopsynav.cli import main

    case = tmp_path / "case"
    shutil.copytree(base_case, case)
    cfg = load_config(case)
    cfg.refine.samples = 4
    cfg.refine.teacher_refine, cfg.refine.extrapolation = 1.46, 2.0
    cfg.evaluate.reference, cfg.evaluate.reference_refinement = "fine_grid", 2.0
    save_config(case, cfg)
    assert main(["run", str(case)]) == 2
    assert not (case / "dataset.zarr").exists()


def test_a_damaged_refine_case_toml_is_rewritten_and_the_fine_data_kept(refined, capsys):
    from biopsynav.cli import main

    toml = refined / "refine" / "case.toml"
    toml.write_text(toml.read_text()[:200])  # truncated
    meta = refined / "refine" / "model" / "meta.json"
    before = meta.stat().st_mtime_ns
    assert main(["refine", str(refined)]) == 0
    assert load_config(refined / "refine") == refined_config(load_config(refined))
    summary = json.loads((refined / "refine" / "dataset_summary.json").read_text())
    assert summary["count"] == 4 and meta.stat().st_mtime_ns == before


def test_a_refine_table_written_before_extrapolation_keeps_its_fitted_teacher():
    """A case.toml of 2026-11-26 names [refine] teacher_refine (every key was
    written) but not extrapolation: it reads as 0, so its fine data keep their protocol; a
    table without teacher_refine takes today's default teacher (the case grid, elastic
    contact)."""
    old = config_from_dict({"refine": {"samples": 60, "teacher_refine": 2}})
    assert (old.refine.teacher_refine, old.refine.extrapolation) == (2.0, 0.0)
    assert refined_config(old).dataset.teacher_extrapolation == 0.0
    new = config_from_dict({"refine": {"samples": 60}})
    assert (new.refine.teacher_refine, new.refine.extrapolation) == (1.0, 0.0)
    both = config_from_dict({"refine": {"samples": 60, "teacher_refine": 1.46,
                                        "extrapolation": 2.0}})
    assert both.refine.extrapolation == 2.0


def test_refine_by_default_learns_the_case_grid_with_elastic_contact(trained_case, tmp_path):
    """With [refine]'s defaults the teacher is the case grid with elastic contact: its rigid
    pushes train the network further without the contact projection, the model says so, and
    the tracker answers with it, unprojected."""
    from biopsynav.cli import main
    from biopsynav.evaluate.placement import place_probe
    from biopsynav.tracker import Tracker

    case_dir = tmp_path / "case"
    shutil.copytree(trained_case, case_dir)
    cfg = load_config(case_dir)
    cfg.refine.samples, cfg.refine.held_out = 4, 1
    cfg.refine.iterations, cfg.refine.max_push_mm = 4, 10.0
    save_config(case_dir, cfg)
    assert main(["refine", str(case_dir), "--workers", "1"]) == 0
    meta = json.loads((case_dir / "refine" / "model" / "meta.json").read_text())
    teacher = meta["teacher"]
    assert (teacher["teacher_refine"], teacher["teacher_extrapolation"]) == (1, 0.0)
    assert (teacher["fem_contact"], teacher["contact_stiffness"]) == ("elastic", 14.0)
    assert meta["baseline"]["elastic_contact"] is True and "projection" not in meta["baseline"]
    case = Case.load(case_dir)
    tracker = Tracker.load(case)
    assert not tracker._surrogate.projects(case.cfg.network.contact_projection)
    placement = place_probe(case.anatomy, 0)
    tracker.set_rest_pose(placement.pose)
    res = tracker.update(placement.pushed(6.0))
    assert res.status == "ok", res.reason
    assert np.linalg.norm(res.lesions[0].displacement) > 0.1


def test_more_refine_samples_grow_the_fine_data_set_in_place(refined, tmp_path, capsys):
    """Raising [refine] samples keeps the solved fine pushes (rigid: the same as training
    and as held-out samples), solves only the new ones and trains again on all."""
    import zarr

    from biopsynav.cli import main

    case = tmp_path / "case"
    shutil.copytree(refined, case)
    fine = case / "refine"
    before = zarr.open_group(str(fine / "dataset.zarr"), mode="r")["targets"][:4]
    meta = fine / "model" / "meta.json"
    trained_at = meta.stat().st_mtime_ns
    cfg = load_config(case)
    cfg.refine.samples = 6
    cfg.dataset.max_failure_share = 1.0  # this coarse grid's fine pushes are often redrawn
    save_config(case, cfg)
    assert main(["refine", str(case), "--workers", "1"]) == 0
    assert "4 solved samples kept" in capsys.readouterr().err
    summary = json.loads((fine / "dataset_summary.json").read_text())
    assert summary["count"] == 6 and summary["computed_this_run"] == 2
    after = zarr.open_group(str(fine / "dataset.zarr"), mode="r")
    assert (after.attrs["n_train"], after.attrs["n_test"]) == (5, 1)
    assert (after["targets"][:4] == before).all()
    assert meta.stat().st_mtime_ns > trained_at
