"""benchmarks/truth.py: which lesions it evaluates."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.runs import BENCHMARKS


@pytest.fixture
def truth(monkeypatch):
    monkeypatch.syspath_prepend(str(BENCHMARKS))
    import truth

    return truth


def test_lesions_are_chosen_by_id_or_spread_over_the_list(phantom_case, truth):
    ids = [int(lesion.id) for lesion in phantom_case.anatomy.lesions]
    assert truth.chosen_lesions(phantom_case, 0) == list(range(len(ids)))
    assert truth.chosen_lesions(phantom_case, 3) == [0, 4, 9]  # as Table 2 spreads them
    picked = truth.chosen_lesions(phantom_case, 3, f"{ids[6]},{ids[1]},{ids[1]}")
    assert picked == [1, 6]


@pytest.mark.parametrize("ids, words", [("2,x", "not a comma list"),
                                        ("2,99", "no lesion with id 99")])
def test_a_bad_lesion_id_is_one_line_naming_it(phantom_case, truth, ids, words):
    with pytest.raises(SystemExit) as exc:
        truth.chosen_lesions(phantom_case, 3, ids)
    assert words in str(exc.value) and "\n" not in str(exc.value)


def _stored_reference(truth, case, path: Path, depth: float, disp: list[float]) -> None:
    """A reference file holding ``disp`` (mm) as lesion index 0's answer at ``depth``, keyed as
    truth.py's defaults key it (so that it is read, not solved again)."""
    import argparse
    import json

    e_mpa, nu, _ = truth.reference_material(case)
    args = argparse.Namespace(depths=[depth], tet_size=10.0, tet_fine=4.0, friction="stick",
                              tet_rim=0.0, edge_radius=0.0, quadrature_degree=5)
    key = truth.reference_key(case, e_mpa, nu, args)
    path.write_text(json.dumps({"key": key, "lesions": {"0": {"displacement": [disp],
                                                              "failure": None}}}))


def _no_reference_solve(*args, **kwargs):
    raise AssertionError("the stored reference was not reused")


def test_the_fe_engine_is_judged_without_a_trained_model(coarse_phantom, truth, tmp_path,
                                                         monkeypatch, capsys):
    import json

    monkeypatch.setattr(truth, "tet_pushes", _no_reference_solve)
    ref, out = tmp_path / "ref.json", tmp_path / "out.json"
    _stored_reference(truth, coarse_phantom, ref, 3.0, [0.0, 0.0, -2.0])
    argv = [str(coarse_phantom.dir), "--lesions", "1", "--depths", "3", "--reference", str(ref),
            "--methods", "fem", "rigid", "--out", str(out)]
    assert truth.main(argv) == 0
    (row,) = json.loads(out.read_text())["rows"]
    assert set(row["tre_mm"]) == {"fem", "rigid"} and row["status"]["fem"] == "ok"
    assert row["tre_mm"]["rigid"] == pytest.approx(2.0)  # the lesion left where it was
    assert 0.0 < row["tre_mm"]["fem"] < 10.0 and row["fem_spring_factor"] == 1.0
    last = capsys.readouterr().out.strip().splitlines()[-1]
    assert last.startswith("RESULT fem_tre_d10_mm=") and "rigid_answered=1/1" in last


def test_a_case_without_its_model_is_one_line_when_the_network_is_judged(
        coarse_phantom, truth, tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(truth, "tet_pushes", _no_reference_solve)
    ref = tmp_path / "ref.json"
    _stored_reference(truth, coarse_phantom, ref, 3.0, [0.0, 0.0, -2.0])
    argv = [str(coarse_phantom.dir), "--lesions", "1", "--depths", "3", "--reference", str(ref)]
    assert truth.main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("truth.py: error: ") and "\n" not in err and "model" in err


def test_an_unknown_method_is_refused_naming_the_choices(coarse_phantom, truth, capsys):
    with pytest.raises(SystemExit) as exc:
        truth.main([str(coarse_phantom.dir), "--methods", "fem", "nett"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    # the choices named, not only the wrong value ("net" alone is inside "nett")
    assert "--methods" in err and "'nett'" in err
    assert all(f"'{m}'" in err for m in ("net", "fem", "rigid"))


def test_a_stored_truth_of_other_depths_is_kept_and_the_run_refused(coarse_phantom, truth,
                                                                   tmp_path, monkeypatch):
    """Asked at other depths than the stored truth holds, truth.py neither solves nor writes
    over it (hours of solves) unless told to, and says what differs."""
    monkeypatch.setattr(truth, "tet_pushes", _no_reference_solve)
    ref = tmp_path / "ref.json"
    _stored_reference(truth, coarse_phantom, ref, 3.0, [0.0, 0.0, -2.0])
    before = ref.read_bytes()
    argv = [str(coarse_phantom.dir), "--lesions", "1", "--depths", "4", "--reference", str(ref),
            "--methods", "rigid"]
    with pytest.raises(SystemExit) as exc:
        truth.main(argv)
    assert "depths_mm" in str(exc.value) and "--replace-reference" in str(exc.value)
    assert ref.read_bytes() == before
    with pytest.raises(AssertionError, match="not reused"):  # told to: it solves over it
        truth.main([*argv, "--replace-reference"])
