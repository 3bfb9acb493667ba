"""Table 1 of a data set of both kinds of sample (the ``pushes-patches`` recipe): each held-out
sample classed as generation drew it, and each kind's figures."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from biopsynav.network.data import Dataset
from biopsynav.network.evaluate import held_out_rigid, kind_figures
from biopsynav.probe import is_rigid_sample
from biopsynav.report.sections import kind_table1_rows


def dataset_with(protocol: dict, test_idx: range) -> Dataset:
    """A data set's bookkeeping alone (no fields): ``protocol`` and held-out indices."""
    empty = torch.zeros(0)
    return Dataset(inputs=empty, targets=empty, active=empty, train_idx=torch.arange(0),
                   test_idx=torch.tensor(list(test_idx)), fingerprint="", node_shape=(1, 1, 1),
                   path=Path("unused.zarr"), attrs={"protocol": protocol})


def test_held_out_samples_are_classed_as_generation_drew_them():
    from biopsynav.config import config_from_dict
    from biopsynav.dataset.store import protocol_dict
    from biopsynav.recipes import recipe_overrides

    cfg = config_from_dict(recipe_overrides("pushes-patches"), "pushes-patches")
    protocol = protocol_dict(cfg, cfg.dataset.n_train, cfg.dataset.n_test)
    held_out = range(cfg.dataset.n_train, cfg.dataset.n_train + cfg.dataset.n_test)
    rigid = held_out_rigid(dataset_with(protocol, held_out))
    assert rigid.tolist() == [is_rigid_sample(cfg.probe, i) for i in held_out]
    assert int(rigid.sum()) == 50 and rigid.size == 80  # the pushes recipe's 50 held out


def test_a_mixed_set_of_kinds_drawn_by_chance_is_not_split():
    """Data sets of both kinds made before the kinds were placed (no ``mixed_draws``) are
    reported over both together, never split by the wrong rule."""
    protocol = {"probe": {"rigid_share": 0.55}, "dataset": {"seed": 3}}
    assert held_out_rigid(dataset_with(protocol, range(600, 680))) is None


def test_a_data_set_of_one_kind_has_no_split():
    for share in (0.0, 1.0):
        protocol = {"probe": {"rigid_share": share}, "dataset": {"seed": 0}}
        assert held_out_rigid(dataset_with(protocol, range(10))) is None
    assert held_out_rigid(dataset_with({}, range(10))) is None  # force patches, old protocol


def test_each_kinds_figures_are_its_own_samples():
    e = np.array([0.1, 0.3, 2.0, 4.0])
    rigid = np.array([False, False, True, True])
    out = kind_figures(e, rigid)
    assert out["force_patches"]["mean_e_mm"] == 0.2 and out["force_patches"]["n_samples"] == 2
    assert out["rigid_pushes"]["max_e_mm"] == 4.0 and out["rigid_pushes"]["mean_e_mm"] == 3.0
    assert set(kind_figures(e, np.zeros(4, bool))) == {"force_patches"}


def test_the_report_puts_the_papers_figures_beside_the_force_patches_alone():
    t1 = {"by_kind": kind_figures(np.array([0.04, 0.06, 0.5]), np.array([False, False, True]))}
    patches, pushes = kind_table1_rows(t1)
    assert "force patches" in patches[0] and patches[1].startswith("0.05 / 0.06 (2)")
    assert patches[2].startswith("0.052 / 0.266")
    assert "rigid" in pushes[0] and pushes[2] == "-"
    assert kind_table1_rows({"mean_e_mm": 0.1}) == []
