"""benchmarks/table1_patches.py: the paper's force patches for a case's own teacher."""

from __future__ import annotations

import pytest

from biopsynav.config import CaseConfig, config_from_dict, load_config, save_config
from biopsynav.recipes import recipe_overrides
from tests.runs import BENCHMARKS


def test_the_scratch_case_draws_force_patches_with_the_case_s_own_law(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import table1_patches

    case, out = tmp_path / "case", tmp_path / "out"
    case.mkdir(), out.mkdir()
    save_config(case, config_from_dict(recipe_overrides("pushes")))
    table1_patches.patches_config(case, out, 120)
    pushes, patches, defaults = load_config(case), load_config(out), CaseConfig()
    assert pushes.probe.rigid_share == 1.0 and not pushes.probe.calibrate_force
    assert patches.probe.rigid_share == defaults.probe.rigid_share == 0.0
    assert patches.probe.calibrate_force == defaults.probe.calibrate_force
    assert (patches.dataset.n_train, patches.dataset.n_test) == (1, 120)
    assert patches.material.model == pushes.material.model == "neo-hookean-split-sri-inner"
    assert patches.grid == pushes.grid and patches.dataset.seed == pushes.dataset.seed


def test_a_case_without_a_model_or_no_samples_is_refused_before_any_work(tmp_path, capsys,
                                                                          monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import table1_patches

    (tmp_path / "case").mkdir()
    for args, words in (([str(tmp_path / "case")], "no trained model"),
                        ([str(tmp_path / "case"), "--samples", "0"], "at least 1")):
        with pytest.raises(SystemExit) as exc:
            table1_patches.main([*args, "--workdir", str(tmp_path / "work")])
        assert exc.value.code == 2 and words in capsys.readouterr().err
    assert not (tmp_path / "work").exists()
