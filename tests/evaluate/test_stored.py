"""Table 2 against a stored truth (``[evaluate] reference = "stored"``)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from biopsynav.case import make_phantom_case
from biopsynav.errors import InputError
from biopsynav.evaluate.simulation import run_simulation
from biopsynav.evaluate.stored import StoredTruth, find_truth, shipped_truths

STORED = {"evaluate": {"reference": "stored"}}


@pytest.fixture(scope="module")
def phantom(tmp_path_factory):
    return make_phantom_case(tmp_path_factory.mktemp("stored") / "ph", overrides=STORED)


def test_the_phantom_finds_its_shipped_truth(phantom):
    path, data = find_truth(phantom)
    assert path.name == "phantom.json"
    assert path in shipped_truths()
    assert data["key"]["anatomy"] == phantom.anatomy.fingerprint()


def test_rigid_tre_is_the_stored_motion_of_every_lesion_and_depth(phantom):
    """The rigid assumption's TRE is the truth's displacement: every stored push was found
    by its pose, at the stored depths, for every lesion."""
    result = run_simulation(phantom, methods=("rigid",), log=lambda _: None)
    stored = json.loads(find_truth(phantom)[0].read_text())["lesions"]
    records = [r for r in result["records"] if r["method"] == "rigid"]
    assert len(records) == 3 * len(phantom.anatomy.lesions)
    for r in records:
        li = next(i for i, les in enumerate(phantom.anatomy.lesions) if les.id == r["lesion"])
        depth = round(r["displacement_mm"])
        want = stored[str(li)]["displacement"][[10, 20, 30].index(depth)]
        assert r["tre_mm"] == pytest.approx(float(np.linalg.norm(want)), abs=1e-9)
    assert result["reference"]["kind"] == "stored"
    assert result["timing"]["total_s"] < 60.0  # nothing is solved


def test_another_material_is_refused_naming_it(tmp_path):
    case = make_phantom_case(tmp_path / "soft", overrides={
        **STORED, "material": {"tissues": {"phantom": {"E_mpa": 0.004, "nu": 0.45}}}})
    with pytest.raises(InputError, match="E_mpa differ"):
        StoredTruth.check(case)


@pytest.mark.parametrize("content, message", [
    ("{not json", "truth.json is not JSON"),
    ('{"lesions": {}}', "truth.json has no 'key' and 'lesions'"),
    (None, "cannot read the stored truth .*truth.json"),
])
def test_a_broken_truth_file_is_refused_naming_it(tmp_path, content, message):
    (tmp_path / "ph").mkdir()
    if content is not None:
        (tmp_path / "ph" / "truth.json").write_text(content)
    case = make_phantom_case(tmp_path / "ph", overwrite=True, overrides={
        "evaluate": {"reference": "stored", "truth_file": "truth.json"}})
    with pytest.raises(InputError, match=message):
        StoredTruth.check(case)
    if content is not None:  # nothing written over the user's file
        assert (tmp_path / "ph" / "truth.json").read_text() == content


def test_a_pose_it_does_not_hold_is_not_answered(phantom):
    ref = StoredTruth(phantom, None, None)
    ref.set_rest_pose(np.eye(4))
    assert not ref.update(np.eye(4)).reliable


def test_the_ucdavis_example_of_one_material_finds_its_shipped_truth(tmp_path, ucdavis_dir):
    """`init` of the UC Davis breast with examples/ucdavis_breast3/homogeneous.toml (as its
    comment says) gives a case whose Table 2 is the shipped truth of that breast, every
    lesion: a change to the anatomy, the material or the probe that the truth's key holds
    fails here, not at the end of a user's run."""
    from pathlib import Path

    from biopsynav.case import Case
    from biopsynav.cli import main

    example = Path(__file__).resolve().parents[2] / "examples" / "ucdavis_breast3"
    case_dir = tmp_path / "ucd-h"
    assert main(["init", str(case_dir), "--surface", str(ucdavis_dir / "volmesh3.vtk"),
                 "--tissue-labels", "1=fat,2=fat,3=fat", "--lesions",
                 str(example / "lesions.csv"), "--config",
                 str(example / "homogeneous.toml")]) == 0
    case = Case.load(case_dir)
    assert (case.cfg.evaluate.reference, case.cfg.evaluate.max_lesions) == ("stored", 0)
    path, data = find_truth(case)
    assert path.name == "ucdavis-homogeneous.json"
    assert sorted(map(int, data["lesions"])) == list(range(len(case.anatomy.lesions)))


def test_the_default_reference_is_the_stored_truth_where_one_serves_the_case(tmp_path):
    """``[evaluate] reference = "auto"`` (the default): the built-in phantom is judged against
    its stored independent truth; the same phantom of another material, which no stored truth
    serves, against the fine grid, and Table 2 says which it chose and why."""
    from biopsynav.reference_registry import chosen_reference

    case = make_phantom_case(tmp_path / "ph")
    assert case.cfg.evaluate.reference == "auto"
    name, why = chosen_reference(case)
    assert name == "stored" and "stored independent truth serves" in why
    said: list[str] = []
    result = run_simulation(case, methods=("rigid",), log=said.append)
    assert result["reference"]["kind"] == "stored" and result["reference"]["chosen"] == why
    assert any("independent P2" in line and why in line for line in said), said
    soft = make_phantom_case(tmp_path / "soft", overrides={
        "material": {"tissues": {"phantom": {"E_mpa": 0.004, "nu": 0.45}}}})
    name, why = chosen_reference(soft)
    assert name == "fine_grid"
    assert "no stored independent truth serves this case" in why and "material" in why
    stated = make_phantom_case(tmp_path / "stated", overrides={
        "evaluate": {"reference": "fine_grid"}})
    assert chosen_reference(stated) == ("fine_grid", "")
