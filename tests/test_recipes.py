"""Recipes (biopsynav.recipes): the case.toml values ``init --recipe`` and ``demo --recipe``
write, and a run of the ``pushes`` recipe from the command line."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from biopsynav.config import CaseConfig, config_from_dict, load_config
from biopsynav.errors import InputError
from biopsynav.recipes import RECIPES, recipe_overrides


def test_an_unknown_recipe_is_refused_naming_the_recipes_there_are():
    with pytest.raises(InputError) as err:
        recipe_overrides("force")
    assert "chain" in str(err.value) and "pushes" in str(err.value)


def test_every_recipe_is_a_valid_case_toml_and_chain_is_the_defaults():
    for name in RECIPES:
        config_from_dict(recipe_overrides(name), f"recipe {name}")
    assert config_from_dict(recipe_overrides("chain"), "chain") == CaseConfig()


def test_the_pushes_recipe_draws_the_chains_refine_pushes():
    """Its data set has the protocol of the chain's [refine] pushes (law, places, tilts,
    seed) but for its training pushes' deeper depths (``train_depth_exponent`` 0.7), so a
    held-out sample of either is the same push; and nothing else runs."""
    from biopsynav.dataset.store import protocol_dict
    from biopsynav.refine import refined_config

    pushes = config_from_dict(recipe_overrides("pushes"), "pushes")
    chain_refine = refined_config(CaseConfig())
    recipe = protocol_dict(pushes, 1000, 20)
    assert recipe["probe"].pop("train_depth_exponent") == 0.7
    assert recipe == protocol_dict(chain_refine, 1000, 20)
    assert pushes.refine.samples == 0 and not pushes.probe.calibrate_force
    assert pushes.network.init_from == "" and pushes.network.prior == "none"


def test_the_pushes_patches_recipe_draws_the_pushes_recipes_pushes_among_force_patches(base_case):
    """One law for both kinds (the pushes'); its training and held-out rigid pushes are the
    pushes recipe's, in order; its force patches calibrated per breast; nothing else runs."""
    from biopsynav.case import Case
    from biopsynav.probe import is_rigid_sample, push_for_sample, rigid_count

    mixed = config_from_dict(recipe_overrides("pushes-patches"), "pushes-patches")
    pushes = config_from_dict(recipe_overrides("pushes"), "pushes")
    assert 0.0 < mixed.probe.rigid_share < 1.0 and mixed.probe.calibrate_force
    assert mixed.material == pushes.material and mixed.refine.samples == 0
    assert mixed.network == pushes.network
    n_train, total = mixed.dataset.n_train, mixed.dataset.n_train + mixed.dataset.n_test
    assert rigid_count(mixed.probe.rigid_share, n_train) == pushes.dataset.n_train
    assert rigid_count(mixed.probe.rigid_share, total) == \
        pushes.dataset.n_train + pushes.dataset.n_test
    anatomy, seed = Case.load(base_case).anatomy, mixed.dataset.seed
    rigid = [i for i in range(n_train - 8, n_train + 8) if is_rigid_sample(mixed.probe, i)]
    numbers = [rigid_count(mixed.probe.rigid_share, i) for i in rigid]
    assert numbers == list(range(numbers[0], numbers[0] + len(rigid)))
    for index, number in zip(rigid, numbers, strict=True):  # around the train/held-out boundary
        a = push_for_sample(anatomy, mixed.probe, seed, index, 0)
        b = push_for_sample(anatomy, pushes.probe, seed, number, 0)
        assert a.vertex == b.vertex and a.push_mm == b.push_mm > 0.0
        assert (index < n_train) == (number < pushes.dataset.n_train)
        np.testing.assert_array_equal(a.direction, b.direction)
    patch = next(i for i in range(n_train - 8, n_train) if not is_rigid_sample(mixed.probe, i))
    patch = push_for_sample(anatomy, mixed.probe, seed, patch, 0)
    assert patch.push_mm == 0.0 and patch.force_n > 0.0


def test_quick_demo_keeps_the_recipes_choice_of_refine():
    from biopsynav.pipeline import demo_overrides

    assert demo_overrides("pushes", quick=True)["refine"] == {"samples": 0}
    assert demo_overrides("chain", quick=True)["refine"]["samples"] > 0
    assert demo_overrides("pushes", quick=False)["probe"]["rigid_share"] == 1.0


def test_the_estimate_prices_a_data_set_of_rigid_pushes_as_rigid_pushes(base_case):
    from biopsynav.case import Case
    from biopsynav.runtime import (
        REFERENCE,
        estimate_run,
        push_minutes_per_1000,
        rigid_push_minutes,
    )

    case = Case.load(base_case)
    ref = REFERENCE["probe_s"]
    n = case.cfg.dataset.n_train + case.cfg.dataset.n_test
    case.cfg.probe = dataclasses.replace(case.cfg.probe, rigid_share=1.0)
    assert estimate_run(case, (ref, ref), workers=2).minutes["generate"] == pytest.approx(
        rigid_push_minutes(n, 1.0, 1.0, push_minutes_per_1000(case)))


def test_init_writes_the_recipe_and_run_trains_the_tracking_network_on_pushes(tmp_path):
    """``init --recipe pushes`` writes its values (what the user reads in case.toml); ``run``
    then solves rigid pushes, trains the one network the tracker uses, and Table 1 measures
    it on its held-out pushes, with no refine stage."""
    from biopsynav.cli import main
    from biopsynav.config import save_config
    from tests.runs import small_run_settings

    case = tmp_path / "case"
    assert main(["init", str(case), "--phantom", "--cell-size", "15", "--recipe", "pushes"]) == 0
    cfg = load_config(case)
    assert cfg.probe.rigid_share == 1.0 and cfg.refine.samples == 0
    assert cfg.material.model == "neo-hookean-split-sri-inner"
    cfg.dataset.n_train, cfg.dataset.n_test = 10, 4
    small_run_settings(cfg)
    save_config(case, cfg)
    assert main(["run", str(case), "--workers", "1"]) == 0
    summary = json.loads((case / "dataset_summary.json").read_text())
    assert summary["rigid_pushes"] == summary["count"] == 14
    assert summary["force_calibration"] is None
    table1 = json.loads((case / "eval" / "table1.json").read_text())
    assert table1["n_samples"] == 4 and table1["mean_e_mm"] > 0.0
    assert not (case / "refine").exists()
    assert "held-out samples are rigid-probe pushes" in (case / "report.md").read_text()


def test_a_pushes_patches_run_measures_each_kind_of_held_out_sample(tmp_path):
    """``init --recipe pushes-patches`` then ``run``: one data set of rigid pushes and calibrated
    force patches, one network, and Table 1 over both and for each kind (table1.json, the
    report)."""
    from biopsynav.cli import main
    from biopsynav.config import save_config
    from tests.runs import small_run_settings

    case = tmp_path / "case"
    assert main(["init", str(case), "--phantom", "--cell-size", "15",
                 "--recipe", "pushes-patches"]) == 0
    cfg = load_config(case)
    cfg.dataset.n_train, cfg.dataset.n_test = 10, 8
    cfg.probe.calibration_pushes = 4
    small_run_settings(cfg)
    save_config(case, cfg)
    assert main(["run", str(case), "--workers", "1"]) == 0
    summary = json.loads((case / "dataset_summary.json").read_text())
    assert 0 < summary["rigid_pushes"] < summary["count"] == 18
    assert summary["force_calibration"]["pushes"] == 4
    table1 = json.loads((case / "eval" / "table1.json").read_text())
    kinds = table1["by_kind"]
    assert set(kinds) == {"force_patches", "rigid_pushes"}, kinds
    assert sum(k["n_samples"] for k in kinds.values()) == table1["n_samples"] == 8
    e = np.array(table1["e_per_sample_mm"])
    assert min(k["mean_e_mm"] for k in kinds.values()) >= e.min() > 0.0
    report = (case / "report.md").read_text()
    assert "force patches (the paper's test set): mean / max e" in report
    assert "held-out samples are of two kinds" in report
