"""benchmarks/pushes_only.py: a case's rigid pushes trained alone, in a copy of the case."""

from __future__ import annotations

from pathlib import Path

from tests.runs import BENCHMARKS


def test_the_copy_links_the_push_data_and_leaves_the_case_alone(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import pushes_only

    case = tmp_path / "case"
    (case / "refine" / "dataset.zarr").mkdir(parents=True)
    (case / "inputs").mkdir()
    for name in ("anatomy.npz", "grid.npz", "case.toml", "inputs/lesions.csv"):
        (case / name).write_text(name)
    for name in pushes_only.REFINE_FILES:
        (case / "refine" / name).write_text("refine " + name)
    refine = pushes_only.copy_case(case, tmp_path / "work")
    assert (refine / "dataset.zarr").is_symlink()
    assert (refine / "dataset.zarr").resolve() == (case / "refine" / "dataset.zarr").resolve()
    assert (refine / "case.toml").read_text() == "refine case.toml"
    assert (refine.parent / "inputs" / "lesions.csv").read_text() == "inputs/lesions.csv"
    assert not (refine / "model").exists() and not (case / "refine" / "model").exists()


def test_the_defaults_are_the_measured_recipe(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import pushes_only

    args = pushes_only.parser().parse_args(["c", "--reference", "t.json"])
    assert (args.prior, args.iterations, args.batch, args.lr) == ("none", 4000, 16, 2e-3)


def test_a_truth_truth_py_would_solve_again_is_refused_before_any_work(tmp_path, monkeypatch):
    """The truth's whole key is checked as truth.py reads it: another anatomy, or the
    phantom's own truth with another depth list, stops the run naming what differs; a file
    that is no truth file (broken JSON, no key, a key that is no object, none at all) stops
    it saying so; nothing is written."""
    import json

    import pytest

    from biopsynav.case import make_phantom_case

    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import pushes_only

    make_phantom_case(tmp_path / "ph")
    stored = Path(__file__).resolve().parents[2] / "src/biopsynav/data/truths/phantom.json"
    truth = json.loads(stored.read_text())
    for key, value in (("anatomy", "0"), ("depths_mm", [10.0, 20.0])):
        other = tmp_path / f"other-{key}.json"
        other.write_text(json.dumps({"key": {**truth["key"], key: value}, "lesions": {}}))
        with pytest.raises(SystemExit, match=f"{key} differs"):
            pushes_only.main([str(tmp_path / "ph"), "--reference", str(other),
                              "--workdir", str(tmp_path / "work")])
    for name, text in (("broken.json", "{not json"), ("keyless.json", '{"lesions": {}}'),
                       ("odd-key.json", '{"key": [1], "lesions": {}}')):
        (tmp_path / name).write_text(text)
        with pytest.raises(SystemExit, match="not a .*truth file"):
            pushes_only.main([str(tmp_path / "ph"), "--reference", str(tmp_path / name),
                              "--workdir", str(tmp_path / "work")])
    with pytest.raises(SystemExit, match="not a readable truth file"):
        pushes_only.main([str(tmp_path / "ph"), "--reference", str(tmp_path / "missing.json"),
                          "--workdir", str(tmp_path / "work")])
    assert not (tmp_path / "work").exists()
    pushes_only.check_reference(tmp_path / "ph", stored)  # the phantom's own: accepted
