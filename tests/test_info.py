"""``biopsynav info``: what taught the trained model, and models written before that was
recorded (they load and track as they are)."""

from __future__ import annotations

import json
import shutil

import numpy as np

from biopsynav.evaluate.placement import place_probe
from biopsynav.inference.model_files import meta_checksum
from biopsynav.info import case_summary, format_summary
from biopsynav.tracker import Tracker


def test_info_names_the_teacher(trained_case):
    s = case_summary(trained_case)
    assert s["model_teacher"].startswith("case grid (15 mm cells), neo-hookean, "
                                         "force patches")
    assert "teacher   case grid" in format_summary(s)
    text = format_summary(s)  # the FE engine's contact and the [refine] stage (off here)
    assert "contact   elastic: each contact point on a spring of beta E A / h, beta 14" in text
    assert "refine    off" in text
    # evaluated with --table1-only: no lesion self-check, and info says the bounds lack it
    assert "bounds    95 % bounds without the lesion self-check" in text


def test_info_names_the_refine_teacher_and_its_contact():
    from biopsynav.config import config_from_dict
    from biopsynav.info import contact_words, refine_words, teacher_words

    cfg = config_from_dict({})
    assert refine_words(cfg) == ("1000 rigid pushes (20 held out) of the case grid, "
                                 "neo-hookean-split-sri-inner, to 35 mm, 16000 iterations")
    cfg.refine.fictitious_stiffness = 0.05
    assert "neo-hookean-split-sri-inner (fictitious stiffness 0.05), to 35 mm" in refine_words(cfg)
    cfg.refine.teacher = "p2"
    assert refine_words(cfg) == ("1000 rigid pushes (20 held out) of P2 tetrahedra (4 mm near "
                                 "the probe, 10 mm elsewhere), to 35 mm, 16000 iterations")
    assert contact_words(config_from_dict({"tracker": {"fem_contact": "points"}})) == (
        "points: the contact points met")
    words = teacher_words({"teacher_refine": 1, "rigid_share": 1.0, "material_model":
                           "neo-hookean", "fem_contact": "elastic", "contact_stiffness": 10.0},
                          7.3)
    assert words.endswith("100% rigid-probe pushes (elastic contact, beta 10)")


def test_a_model_from_before_teachers_were_recorded_still_loads_and_tracks(trained_case,
                                                                           tmp_path):
    case_dir = tmp_path / "case"
    shutil.copytree(trained_case, case_dir)
    meta_path = case_dir / "model" / "meta.json"
    meta = json.loads(meta_path.read_text())
    del meta["teacher"]
    meta["checksum"] = meta_checksum(meta)
    meta_path.write_text(json.dumps(meta))
    assert "not recorded" in case_summary(case_dir)["model_teacher"]
    tracker = Tracker.load(case_dir, engine="net")
    placement = place_probe(tracker.case.anatomy, 0)
    assert tracker.set_rest_pose(placement.pose) > 0
    result = tracker.update(placement.pushed(5.0))
    assert result.status == "ok"
    assert np.isfinite([les.displacement for les in result.lesions]).all()


def test_info_names_the_model_a_training_started_from(trained_case, tmp_path):
    case_dir = tmp_path / "case"
    shutil.copytree(trained_case, case_dir)
    meta_path = case_dir / "model" / "meta.json"
    meta = json.loads(meta_path.read_text())
    meta["training"]["init_from"] = {"path": "/data/coarse/model", "checksum": "sha256:0",
                                     "teacher": {"material_model": "neo-hookean",
                                                 "rigid_share": 0.0, "teacher_refine": 1}}
    meta["teacher"]["teacher_refine"] = 3
    meta["checksum"] = meta_checksum(meta)
    meta_path.write_text(json.dumps(meta))
    words = case_summary(case_dir)["model_teacher"]
    assert words.startswith("grid of 5 mm cells fitted to the case grid")
    assert words.endswith("started from the model in /data/coarse/model, taught by case grid "
                          "(15 mm cells), neo-hookean, force patches")


def test_info_names_a_converged_teacher_not_the_grid():
    from biopsynav.info import teacher_words

    words = teacher_words({"teacher": "p2", "teacher_refine": 1, "rigid_share": 1.0,
                           "material_model": "neo-hookean-split-sri-inner",
                           "teacher_protocol": {"size_mm": 10.0, "fine_mm": 4.0,
                                                "probe": "rigid face"}}, 7.3)
    assert words == ("P2 tetrahedra (4 mm near the probe, 10 mm elsewhere) fitted to the case "
                     "grid, rigid-probe pushes (rigid face)")
    assert teacher_words({"teacher": "ngsolve"}, 7.3).startswith("the 'ngsolve' teacher")
    assert teacher_words({"teacher": "grid", "teacher_refine": 1}, 7.3).startswith("case grid")


def test_info_names_an_extrapolated_teacher():
    from biopsynav.info import teacher_words

    words = teacher_words({"teacher_refine": 1.46, "teacher_extrapolation": 2.0,
                           "material_model": "neo-hookean", "rigid_share": 1.0}, 7.3)
    assert words.startswith("grid of 5 mm cells fitted to the case grid, extrapolated from "
                            "the case grid (order 2), neo-hookean, 100% rigid-probe pushes")
    assert teacher_words({"teacher_refine": 2}, 7.3).startswith("grid of 3.65 mm cells")


def test_info_names_the_prior_the_case_network_started_from(trained_case, tmp_path):
    case_dir = tmp_path / "case"
    shutil.copytree(trained_case, case_dir)
    assert "prior" not in case_summary(case_dir)["model_teacher"]  # trained from scratch
    meta_path = case_dir / "model" / "meta.json"
    meta = json.loads(meta_path.read_text())
    meta["training"]["prior"] = {"name": "ucdavis-breast3", "checksum": "0" * 64}
    meta["checksum"] = meta_checksum(meta)
    meta_path.write_text(json.dumps(meta))
    assert case_summary(case_dir)["model_teacher"].endswith(
        "the case network started from the packaged network 'ucdavis-breast3'")
