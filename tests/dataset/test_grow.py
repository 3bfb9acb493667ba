"""A data set grown in place when only its sizes change (biopsynav.dataset.grow)."""

from __future__ import annotations

import shutil

import numpy as np
import pytest
import zarr
from dataset_helpers import N_TEST, N_TRAIN, edit_config

from biopsynav.case import Case
from biopsynav.dataset import grow
from biopsynav.dataset.generate import generate_case
from biopsynav.dataset.store import RESIZE_ATTR, open_store
from biopsynav.errors import FingerprintError, InputError


def attrs_of(n_train: int, n_test: int) -> dict:
    return {"n_train": n_train, "n_test": n_test}


def test_old_held_out_samples_are_solved_again_only_when_their_push_changes(base_case):
    """Held-out samples below the new n_train become training samples: kept when the push is
    the same in both roles (rigid, or the held-out force law), solved again otherwise."""
    cfg = Case.load(base_case).cfg
    assert cfg.probe.train_force_exponent != 1.0  # training forces differ from held-out ones
    assert grow.samples_to_solve_again(cfg, attrs_of(14, 2), 20) == [14, 15]
    assert grow.samples_to_solve_again(cfg, attrs_of(14, 2), 14) == []  # more held out only
    assert grow.samples_to_solve_again(cfg, attrs_of(14, 4), 16) == [14, 15]
    cfg.probe.train_force_exponent = 1.0
    assert grow.samples_to_solve_again(cfg, attrs_of(14, 2), 20) == []
    cfg.probe.train_force_exponent, cfg.probe.rigid_share = 0.5, 1.0
    assert grow.samples_to_solve_again(cfg, attrs_of(14, 2), 20) == []


def test_shrinking_is_refused():
    assert grow.growth_refusal(attrs_of(14, 2), 14, 2) is None
    assert grow.growth_refusal(attrs_of(14, 2), 16, 1) is None  # no solved sample dropped
    assert "never shrinks" in grow.growth_refusal(attrs_of(14, 2), 13, 3)
    assert "never shrinks" in grow.growth_refusal(attrs_of(14, 4), 15, 1)


def test_a_grown_data_set_equals_one_generated_at_that_size(reference, tmp_path,
                                                          assert_same_dataset, capsys):
    """Raising n_train and n_test keeps the stored training samples, solves the old held-out
    ones again as training samples (their force law changes) and adds the rest: the same
    arrays and failure log as a data set generated at the new size from the start."""
    grown, fresh = tmp_path / "grown", tmp_path / "fresh"
    shutil.copytree(reference, grown)
    shutil.copytree(reference, fresh)
    shutil.rmtree(fresh / "dataset.zarr")
    before = zarr.open_group(str(grown / "dataset.zarr"), mode="r")["targets"][:N_TRAIN]
    for case in (grown, fresh):
        edit_config(case, dataset={"n_train": N_TRAIN + 2, "n_test": N_TEST + 1})
    summary = generate_case(grown, workers=1, progress=False)
    assert summary["computed_this_run"] == 5  # 2 solved again, 3 new
    assert f"{N_TRAIN + N_TEST - 2} solved samples kept" in summary["grown"]
    assert "grown from" in capsys.readouterr().err
    generate_case(fresh, workers=1, progress=False)
    assert_same_dataset(grown, fresh)
    after = zarr.open_group(str(grown / "dataset.zarr"), mode="r")
    assert np.array_equal(after["targets"][:N_TRAIN], before)
    assert RESIZE_ATTR not in after.attrs


def test_an_interrupted_growth_is_finished_by_the_next_run(reference, tmp_path, monkeypatch,
                                                          assert_same_dataset):
    """Killed after the plan was written and before the arrays changed: a read-only reader is
    told to run generate, and generate finishes the growth and the samples."""
    grown, fresh = tmp_path / "grown", tmp_path / "fresh"
    shutil.copytree(reference, grown)
    shutil.copytree(reference, fresh)
    shutil.rmtree(fresh / "dataset.zarr")
    for case in (grown, fresh):
        edit_config(case, dataset={"n_train": N_TRAIN + 1, "n_test": N_TEST})

    def killed(store):
        raise KeyboardInterrupt

    monkeypatch.setattr(grow, "finish_growth", killed)
    with pytest.raises(KeyboardInterrupt):
        generate_case(grown, workers=1, progress=False)
    monkeypatch.undo()
    with pytest.raises(InputError, match="interrupted; run `biopsynav generate`"):
        open_store(grown / "dataset.zarr", mode="r")
    assert generate_case(grown, workers=1, progress=False)["computed_this_run"] == 2
    generate_case(fresh, workers=1, progress=False)
    assert_same_dataset(grown, fresh)


def test_a_smaller_data_set_is_refused_and_the_store_left_as_it_was(reference, tmp_path):
    case = tmp_path / "case"
    shutil.copytree(reference, case)
    edit_config(case, dataset={"n_train": N_TRAIN - 1})
    with pytest.raises(FingerprintError, match=r"never shrinks.*--overwrite"):
        generate_case(case, workers=1, progress=False)
    g = zarr.open_group(str(case / "dataset.zarr"), mode="r")
    assert g.attrs["n_train"] == N_TRAIN and g["done"].shape == (N_TRAIN + N_TEST,)
    assert RESIZE_ATTR not in g.attrs


def test_a_data_set_of_another_protocol_is_not_grown(reference, tmp_path):
    """Sizes and another key changed: refused as before, naming both, nothing resized."""
    case = tmp_path / "case"
    shutil.copytree(reference, case)
    edit_config(case, dataset={"n_train": N_TRAIN + 2}, probe={"f_max_n": 2.0})
    with pytest.raises(FingerprintError, match=r"f_max_n.*n_train|n_train.*f_max_n"):
        generate_case(case, workers=1, progress=False)
    assert zarr.open_group(str(case / "dataset.zarr"), mode="r")["done"].shape == \
        (N_TRAIN + N_TEST,)


@pytest.mark.parametrize("plan", [{"n_train": "many", "n_test": 2, "solve_again": []},
                                  {"n_train": N_TRAIN + 1, "n_test": N_TEST},
                                  "garbage",
                                  {"n_train": N_TRAIN + 1, "n_test": N_TEST, "solve_again": [999],
                                   "protocol": {}, "protocol_fingerprint": "0"},
                                  {"n_train": 1, "n_test": 1, "solve_again": [],
                                   "protocol": {}, "protocol_fingerprint": "0"}])
def test_a_damaged_growth_plan_is_one_clear_error_and_loses_nothing(reference, tmp_path, plan):
    case = tmp_path / "case"
    shutil.copytree(reference, case)
    zarr.open_group(str(case / "dataset.zarr"), mode="r+").attrs[RESIZE_ATTR] = plan
    with pytest.raises(InputError, match=r"growth plan \('resizing'\).*--overwrite"):
        generate_case(case, workers=1, progress=False)
    g = zarr.open_group(str(case / "dataset.zarr"), mode="r")
    assert g["done"].shape == (N_TRAIN + N_TEST,) and bool(g["done"][...].all())
    assert g.attrs["n_train"] == N_TRAIN


def test_a_read_only_reader_of_a_damaged_growth_plan_is_told_to_run_generate(reference,
                                                                            tmp_path):
    case = tmp_path / "case"
    shutil.copytree(reference, case)
    zarr.open_group(str(case / "dataset.zarr"), mode="r+").attrs[RESIZE_ATTR] = "garbage"
    with pytest.raises(InputError, match=r"growing the data set \(its plan, 'resizing', is "
                                         r"damaged\) was interrupted; run `biopsynav generate`"):
        open_store(case / "dataset.zarr", mode="r")
    assert zarr.open_group(str(case / "dataset.zarr"), mode="r")["done"].shape == \
        (N_TRAIN + N_TEST,)
