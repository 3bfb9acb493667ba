import pytest

from biopsynav.config import (
    CaseConfig,
    config_from_dict,
    load_config,
    reference_markdown,
    save_config,
)
from biopsynav.errors import InputError


def test_defaults_round_trip(tmp_path):
    cfg = CaseConfig()
    save_config(tmp_path, cfg)
    assert load_config(tmp_path) == cfg
    assert "# biopsynav case. Units: mm, N, MPa" in (tmp_path / "case.toml").read_text()


@pytest.mark.parametrize("data, message", [
    ({"grid": {"cell_sise_mm": 5.0}}, "unknown key 'cell_sise_mm' in [grid]"),
    ({"gird": {}}, "unknown section [gird]"),
    ({"grid": {"cell_size_mm": -1.0}}, "below its minimum"),
    ({"grid": {"cell_size_mm": "big"}}, "must be of type float"),
    ({"dataset": {"n_train": 1.5}}, "must be an integer"),
    ({"material": {"model": "linear"}}, "must be one of"),
    ({"material": {"tissues": {"fat": {"E_mpa": -1, "nu": 0.4}}}}, "E_mpa must be in"),
    ({"material": {"tissues": {"fat": {"E_mpa": 1e-3, "nu": 0.5}}}}, "nu must be in"),
    ({"anatomy": {"chest_wall": "plane:1,2,3"}}, "six numbers"),
    ({"anatomy": {"chest_wall": "bottom"}}, "chest_wall must be"),
    ({"anatomy": {"tissue_labels": {"1": "bone"}}}, "unknown tissue 'bone'"),
    ({"igtl": {"listen": "localhost"}}, "HOST:PORT"),
    ({"probe": {"footprint_mm": [50.0]}}, "two positive lengths"),
    ({"dataset": {"contact_input": "nearest"}}, "must be one of"),
    ({"solver": {"indefinite_tangent": "cholesky"}}, "indefinite_tangent must be one of"),
    ({"probe": {"max_chest_compression": 1.5}}, "max_chest_compression"),
    ({"probe": {"max_chest_compression": "half"}}, "max_chest_compression"),
    ({"dataset": {"newton_budget": -1}}, "below its minimum"),
    ({"igtl": {"stall_timeout_s": 0.0}}, "below its minimum"),
    ({"network": {"weight_decay": -0.1}}, "below its minimum"),
    ({"network": {"loss": "huber"}}, "must be one of"),
    ({"network": {"features": "cubic"}}, "must be one of"),
    ({"network": {"precision": "fp16"}}, "must be one of"),
    ({"network": {"precision": 16}}, "precision"),
    ({"network": {"weight_decay": "strong"}}, "weight_decay"),
    ({"igtl": {"inference_threads": -1}}, "below its minimum"),
    ({"igtl": {"inference_threads": 1.5}}, "must be an integer"),
    ({"probe": {"max_push_mm": -5.0}}, "below its minimum"),
    ({"dataset": {"teacher_push_limit_s": -1.0}}, "below its minimum"),
    ({"refine": {"teacher_push_limit_s": "long"}}, "must be of type float"),
    ({"refine": {"teacher_fine_mm": 12.0}}, "teacher_fine_mm (12 mm"),
    ({"evaluate": {"p2_fine_mm": 8.0, "p2_size_mm": 6.0}}, "p2_fine_mm (8 mm"),
    ({"probe": {"max_push_mm": "deep"}}, "max_push_mm"),
    ({"probe": {"footprint_mm": [float("inf"), 10.0]}}, "two positive lengths"),
    ({"probe": {"footprint_mm": [True, 10.0]}}, "two positive lengths"),
    ({"material": {"tissues": {"fat": {"E_mpa": True, "nu": 0.45}}}}, "not a boolean"),
    ({"material": {"tissues": {"fat": {"E_mpa": float("inf"), "nu": 0.45}}}}, "E_mpa must be"),
    ({"material": {"tissues": {"fat": {"E_mpa": 1e-3, "nu": float("nan")}}}}, "nu must be"),
    ({"probe": {"f_max_n": float("inf")}}, "must be a finite number"),
    ({"grid": {"cell_size_mm": float("nan")}}, "must be a finite number"),
    ({"igtl": {"listen": "::1:18945"}}, "needs brackets"),
    ({"anatomy": {"breast_labels": [1, 2.5]}}, "[anatomy] breast_labels holds 2.5"),
    ({"anatomy": {"chest_labels": [True]}}, "[anatomy] chest_labels holds True"),
    ({"anatomy": {"lesion_labels": [""]}}, "[anatomy] lesion_labels holds ''"),
    ({"anatomy": {"side": "middle"}}, "must be one of"),
    ({"anatomy": {"input_frame": "ijk"}}, "must be one of"),
    ({"anatomy": {"labelmap_smoothing_mm": -1.0}}, "below its minimum"),
    ({"anatomy": {"labelmap_spacing_mm": 50.0}}, "above its maximum"),
    ({"anatomy": {"lesion_radius_mm": 0.0}}, "below its minimum"),
    ({"probe": {"calibrate_force": "yes"}}, "must be true or false"),
    ({"probe": {"rigid_share": "half"}}, "rigid_share"),
    ({"probe": {"rigid_share": -0.1}}, "below its minimum"),
    ({"probe": {"rigid_max_tilt_deg": 95.0}}, "above its maximum"),
    ({"probe": {"lesion_share": -0.1}}, "below its minimum"),
    ({"probe": {"lesion_share": 1.5}}, "above its maximum"),
    ({"probe": {"lesion_share": "half"}}, "lesion_share"),
    ({"probe": {"lesion_reach_mm": -1.0}}, "below its minimum"),
    ({"refine": {"lesion_share": 2.0}}, "above its maximum"),
    ({"evaluate": {"reference": "oracle"}}, "must be one of"),
    ({"evaluate": {"p2_size_mm": 0.0}}, "below its minimum"),
    ({"evaluate": {"p2_fine_mm": "fine"}}, "p2_fine_mm"),
    ({"evaluate": {"p2_friction": "grease"}}, "must be one of"),
    ({"evaluate": {"p2_rim_mm": -1.0}}, "below its minimum"),
    ({"evaluate": {"p2_rim_mm": "fine"}}, "p2_rim_mm"),
    ({"evaluate": {"p2_edge_radius_mm": -1.0}}, "below its minimum"),
    ({"evaluate": {"p2_edge_radius_mm": 5.0}}, "p2_edge_radius_mm = 5 does not fit the probe"),
    ({"dataset": {"teacher_refine": 0}}, "below its minimum"),
    ({"dataset": {"teacher_refine": 5}}, "above its maximum"),
    ({"dataset": {"teacher_refine": "fine"}}, "teacher_refine"),
    ({"dataset": {"teacher_extrapolation": 2.0}}, "set teacher_refine > 1 too"),
    ({"dataset": {"teacher_extrapolation": -1.0}}, "below its minimum"),
    ({"refine": {"teacher_refine": 0.9}}, "below its minimum"),
    ({"tracker": {"contact_stiffness": 0.0}}, "below its minimum"),
    ({"tracker": {"contact_stiffness": "stiff"}}, "contact_stiffness"),
    ({"probe": {"train_force_exponent": 0.0}}, "below its minimum"),
    ({"probe": {"train_force_exponent": 1.5}}, "above its maximum"),
    ({"probe": {"train_force_exponent": "skewed"}}, "train_force_exponent"),
    ({"probe": {"train_depth_exponent": 0.0}}, "below its minimum"),
    ({"probe": {"train_depth_exponent": 1.5}}, "above its maximum"),
    ({"probe": {"train_depth_exponent": "deep"}}, "train_depth_exponent"),
    ({"probe": {"train_depth_exponent": float("nan")}}, "must be a finite number"),
    ({"probe": {"train_force_scale": 0.5}}, "below its minimum"),
    ({"probe": {"train_force_scale": 5.0}}, "above its maximum"),
    ({"probe": {"calibration_pushes": 2}}, "below its minimum"),
    ({"probe": {"calibration_pushes": 12.5}}, "must be an integer"),
    ({"probe": {"calibration_pushes": "many"}}, "calibration_pushes"),
    ({"probe": {"too_deep_redraw": "nowhere"}}, "must be one of"),
    ({"probe": {"too_deep_redraw": 1}}, "too_deep_redraw"),
    ({"tracker": {"spring_budget": -1}}, "below its minimum"),
    ({"tracker": {"spring_budget": 1.5}}, "must be an integer"),
    ({"tracker": {"spring_budget": "many"}}, "spring_budget"),
    ({"refine": {"teacher_refine": 1.0, "extrapolation": 2.0}}, "set [refine] teacher_refine > 1"),
    ({"dataset": {"teacher_min_fraction": 1.5}}, "above its maximum"),
    ({"dataset": {"teacher_min_fraction": "some"}}, "teacher_min_fraction"),
    ({"dataset": {"max_edge_stretch": -1.0}}, "below its minimum"),
    ({"dataset": {"max_edge_stretch": "loose"}}, "max_edge_stretch"),
    ({"dataset": {"max_edge_stretch": float("nan")}}, "must be a finite number"),
    ({"refine": {"batch_size": 0}}, "below its minimum"),
    ({"refine": {"batch_size": 2.5}}, "must be an integer"),
    ({"refine": {"batch_size": "big"}}, "batch_size"),
    ({"network": {"prior": "someone-else"}}, "prior"),
])
def test_bad_values_name_the_key(data, message):
    with pytest.raises(InputError) as err:
        config_from_dict(data, "case.toml")
    assert message in str(err.value)
    assert str(err.value).startswith("case.toml: ")


def test_bad_toml_file(tmp_path):
    (tmp_path / "case.toml").write_text("[grid\ncell_size_mm = 3")
    with pytest.raises(InputError, match="not valid TOML"):
        load_config(tmp_path)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no case.toml"):
        load_config(tmp_path / "empty")
    with pytest.raises(InputError, match="case folder does not exist"):
        load_config(tmp_path / "nothing")


def test_reference_documents_every_key():
    text = reference_markdown()
    cfg = CaseConfig().to_dict()
    for section, values in cfg.items():
        assert f"## [{section}]" in text
        for key in values:
            assert f"`{key}`" in text


def test_docs_case_toml_is_current():
    """docs/case_toml.md is generated: `python -m biopsynav.config > docs/case_toml.md`."""
    from pathlib import Path

    doc = Path(__file__).resolve().parents[1] / "docs" / "case_toml.md"
    assert doc.read_text(encoding="utf-8") == reference_markdown()


def test_atomic_writes_leave_readable_files_and_no_temporaries(tmp_path):
    import os

    from biopsynav.fileio import write_text_atomic

    path = write_text_atomic(tmp_path / "a" / "x.txt", "hello")
    assert path.read_text() == "hello"
    mask = os.umask(0)
    os.umask(mask)
    assert path.stat().st_mode & 0o777 == 0o666 & ~mask
    assert [p.name for p in path.parent.iterdir()] == ["x.txt"]


def test_a_streamed_write_that_fails_midway_keeps_the_previous_file(tmp_path):
    import numpy as np

    from biopsynav.fileio import load_npz, save_npz_atomic, write_atomic

    path = save_npz_atomic(tmp_path / "x.npz", a=np.arange(3.0))

    def half_then_fail(fh):
        fh.write(b"PK half a zip")
        raise RuntimeError("killed midway")

    with pytest.raises(RuntimeError, match="midway"):
        write_atomic(path, half_then_fail)
    assert load_npz(path, ["a"], "rebuild")["a"].tolist() == [0.0, 1.0, 2.0]
    assert [p.name for p in tmp_path.iterdir()] == ["x.npz"]


def test_truncated_case_toml_is_refused_and_an_older_one_still_loads(tmp_path):
    save_config(tmp_path, CaseConfig())
    path = tmp_path / "case.toml"
    text = path.read_text()
    path.write_text(text[: len(text) // 2])
    with pytest.raises(InputError, match="truncated"):
        load_config(tmp_path)
    path.write_text("")
    with pytest.raises(InputError, match="empty"):
        load_config(tmp_path)
    # a case.toml written before the end line existed (old second line, no end line) loads
    old = text.replace(text.splitlines()[1], "# Every key is documented in docs/case_toml.md.")
    path.write_text(old[: old.rindex("# end of case.toml")])
    assert load_config(tmp_path) == CaseConfig()


def test_a_case_toml_from_before_refine_keeps_its_own_model(tmp_path):
    """biopsynav writes every section: its own case.toml without [refine] is from before the
    stage existed, and reads as [refine] samples = 0 (its trained model stays the tracker's);
    a hand-written one without the table takes the default, like any other key."""
    import re

    save_config(tmp_path, CaseConfig())
    path = tmp_path / "case.toml"
    text = path.read_text()
    assert load_config(tmp_path).refine.samples == CaseConfig().refine.samples == 1000
    path.write_text(re.sub(r"\[refine\]\n(?:[^\[]*\n)", "", text))
    assert "[refine]" not in path.read_text()
    assert load_config(tmp_path).refine.samples == 0
    assert load_config(tmp_path).network == CaseConfig().network  # the rest as written
    path.write_text("[case]\nname = \"by hand\"\n")
    assert load_config(tmp_path).refine.samples == 1000


def test_a_case_toml_from_before_the_refine_law_reads_as_one_law(tmp_path):
    """A case.toml biopsynav wrote before [refine] material_model existed was made with one
    law: it reads its [material] model for the refine teacher too, so its data sets and
    models stay what they were. Files by hand and overrides take the default."""
    cfg = CaseConfig()
    assert (cfg.material.model, cfg.refine.material_model) == (
        "neo-hookean", "neo-hookean-split-sri-inner")
    path = tmp_path / "case.toml"
    for law in ("neo-hookean-split-sri-inner", "neo-hookean", "svk"):
        cfg.material.model = law
        save_config(tmp_path, cfg)
        text = path.read_text()
        assert "material_model = " in text
        path.write_text("\n".join(line for line in text.splitlines()
                                  if not line.startswith("material_model")) + "\n")
        assert load_config(tmp_path).refine.material_model == law
    path.write_text('[material]\nmodel = "svk"\n[refine]\nsamples = 5\nheld_out = 1\n')
    assert load_config(tmp_path).refine.material_model == "neo-hookean-split-sri-inner"
    assert config_from_dict({"refine": {"samples": 5, "held_out": 1}}).refine.material_model == (
        "neo-hookean-split-sri-inner")


def _drop_refine_key(path, key: str) -> None:
    """Remove ``key`` from the [refine] table of the case.toml at ``path`` (as written before
    the key existed)."""
    lines = path.read_text().splitlines()
    refine_at = lines.index("[refine]")
    path.write_text("\n".join(line for i, line in enumerate(lines)
                              if i < refine_at or not line.startswith(key)) + "\n")


def test_a_case_toml_from_before_the_fictitious_stiffness_keeps_its_teacher(tmp_path):
    """A case.toml biopsynav wrote before [refine] fictitious_stiffness existed reads its
    [material] value for the refine teacher (one law, as it was made); files by hand and
    overrides take the default."""
    cfg = CaseConfig()
    assert (cfg.material.fictitious_stiffness, cfg.refine.fictitious_stiffness) == (0.0, 0.0)
    cfg.material.fictitious_stiffness, cfg.refine.fictitious_stiffness = 0.1, 0.2
    path = tmp_path / "case.toml"
    save_config(tmp_path, cfg)
    assert load_config(tmp_path).refine.fictitious_stiffness == 0.2
    _drop_refine_key(path, "fictitious_stiffness")
    assert load_config(tmp_path).material.fictitious_stiffness == 0.1
    assert load_config(tmp_path).refine.fictitious_stiffness == 0.1
    path.write_text("[material]\nfictitious_stiffness = 0.1\n[refine]\nsamples = 5\n"
                    "held_out = 1\n")
    assert load_config(tmp_path).refine.fictitious_stiffness == 0.0
    with pytest.raises(InputError, match="fictitious_stiffness"):
        config_from_dict({"refine": {"fictitious_stiffness": 1.5}})
    with pytest.raises(InputError, match="fictitious_stiffness"):
        config_from_dict({"material": {"fictitious_stiffness": -0.1}})


def test_a_case_toml_from_before_the_refine_batch_refines_at_the_network_batch(tmp_path):
    """A case.toml biopsynav wrote before [refine] batch_size existed refined at its
    [network] batch_size: it reads that value, so its refine model stays up to date; files
    by hand take the default, and the refine case trains at [refine] batch_size."""
    from biopsynav.refine import refined_config

    cfg = CaseConfig()
    assert (cfg.network.batch_size, cfg.refine.batch_size) == (16, 4)
    assert refined_config(cfg).network.batch_size == 4
    cfg.network.batch_size = 8
    path = tmp_path / "case.toml"
    save_config(tmp_path, cfg)
    assert load_config(tmp_path).refine.batch_size == 4
    _drop_refine_key(path, "batch_size")
    assert load_config(tmp_path).refine.batch_size == 8
    path.write_text("[network]\nbatch_size = 8\n[refine]\nsamples = 5\nheld_out = 1\n")
    assert load_config(tmp_path).refine.batch_size == 4


def test_the_refine_law_is_checked_against_the_tissues():
    with pytest.raises(InputError, match="material_model"):
        config_from_dict({"refine": {"material_model": "hookean"}})
    data = {"material": {"model": "neo-hookean"}, "refine": {"material_model": "svk"}}
    assert config_from_dict(data).refine.material_model == "svk"
