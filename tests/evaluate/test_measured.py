"""Table 2 from user data (poses + measured positions) and the evaluate entry point."""

from __future__ import annotations

import numpy as np
import pytest

from biopsynav.errors import InputError
from biopsynav.evaluate import evaluate_case, evaluate_measured, read_measured
from biopsynav.evaluate.placement import place_probe
from biopsynav.evaluate.simulation import evaluation_solver_settings
from biopsynav.tracker.core import fem_engine
from biopsynav.tracker.csvtrack import MATRIX_COLUMNS

LESION = 2  # index of the lesion under the probe (id 3)


def _pose_row(frame: int, seq: str, pose: np.ndarray) -> str:
    return ",".join([str(frame), seq, *(f"{v:.10g}" for v in pose[:3].ravel())])


def _write(path, header: str, rows: list[str]):
    path.write_text("\n".join([header, *rows]) + "\n")
    return path


@pytest.fixture(scope="module")
def experiment(coarse_phantom, tmp_path_factory):
    """A synthetic phantom experiment: rest + pushes of 10 and 15 mm above lesion 3; the
    'measured' positions are the FE model's plus known offsets."""
    tmp = tmp_path_factory.mktemp("measured")
    a = coarse_phantom.anatomy
    pl = place_probe(a, LESION)
    depths = [0.0, 10.0, 15.0]
    poses = [pl.pushed(d) for d in depths]
    fem = fem_engine(coarse_phantom, evaluation_solver_settings(coarse_phantom))
    fem.set_rest_pose(poses[0])
    disp = [np.zeros(3)] + [fem.update(p).lesions[LESION].displacement for p in poses[1:]]
    centre = a.lesions[LESION].center
    lid = a.lesions[LESION].id
    anchor_offset = np.array([0.2, 0.0, 0.0])  # the rest-frame measurement
    offsets = [anchor_offset, np.array([0.2, 0.3, 0.0]), np.zeros(3)]
    measured = [centre + d + o for d, o in zip(disp, offsets, strict=True)]
    poses_csv = _write(tmp / "poses.csv", "frame,sequence," + ",".join(MATRIX_COLUMNS),
                       [_pose_row(f, "s1", p) for f, p in enumerate(poses)])
    measured_csv = _write(tmp / "measured.csv", "frame,lesion_id,x,y,z",
                          [f"{f},{lid},{m[0]:.10g},{m[1]:.10g},{m[2]:.10g}"
                           for f, m in enumerate(measured)])
    return {"poses": poses_csv, "measured": measured_csv, "disp": disp, "offsets": offsets,
            "lid": lid, "tmp": tmp}


def test_measured_table_against_a_fem_tracker(coarse_phantom, experiment):
    r = evaluate_measured(coarse_phantom.dir, experiment["poses"], experiment["measured"],
                          methods=("fem", "rigid"), log=lambda s: None)
    assert r["source"] == "measured" and not r["failures"]
    recs = {(x["method"], x["frame"]): x for x in r["records"]}
    assert set(recs) == {("fem", 1), ("fem", 2), ("rigid", 1), ("rigid", 2)}  # rest unscored
    # fem predicts anchor + its displacement: TRE = |anchor offset - frame offset|
    assert recs["fem", 1]["tre_mm"] == pytest.approx(0.3, abs=1e-4)
    assert recs["fem", 2]["tre_mm"] == pytest.approx(0.2, abs=1e-4)
    d, o = experiment["disp"], experiment["offsets"]
    assert recs["rigid", 2]["tre_mm"] == pytest.approx(np.linalg.norm(o[0] - d[2] - o[2]))
    assert recs["fem", 1]["bin"] == "D10" and recs["fem", 2]["bin"] == "D15"
    assert recs["fem", 2]["displacement_mm"] == pytest.approx(15.0)
    row = r["tables"]["fem"]["rows"][0]
    assert row["lesion"] == experiment["lid"]
    assert row["cells"][:2] == pytest.approx([0.3, 0.2], abs=1e-4) and row["cells"][2] is None


@pytest.mark.parametrize(("text", "message"), [
    ("frame,lesion_id,x,y\n1,3,0,0\n", "line 1: measured positions CSV lacks the columns z"),
    ("frame,lesion_id,x,y,z\n1,3,0,0,0\n2,3,0,zero,0\n", "line 3:"),
    ("frame,lesion_id,x,y,z\n1,3,0,0,0\n1,3,1,1,1\n", "line 3: lesion 3 of frame 1 is given"),
    ("frame,lesion_id,x,y,z\n1,3,0,nan,0\n", "line 2: x, y, z must be finite"),
    ("frame,lesion_id,x,y,z\n", "no rows"),
    ("frame,lesion_id,x,y,z\n1,3,0,0,0\n7,3,0,0,0\n", "line 3: frame 7 is not in the poses"),
    ("frame,lesion_id,x,y,z\n1,99,0,0,0\n", "line 2: lesion 99 is not a lesion"),
])
def test_malformed_measured_csv_names_file_and_line(coarse_phantom, experiment, tmp_path, text,
                                                     message):
    bad = tmp_path / "bad.csv"
    bad.write_text(text)
    with pytest.raises(InputError) as err:
        evaluate_measured(coarse_phantom.dir, experiment["poses"], bad, methods=("rigid",),
                          log=lambda s: None)
    assert message in str(err.value) and "bad.csv" in str(err.value)


def test_malformed_poses_csv_names_file_and_line(coarse_phantom, experiment, tmp_path):
    lines = experiment["poses"].read_text().splitlines()
    bad = tmp_path / "poses_bad.csv"
    bad.write_text("\n".join([lines[0], lines[1], lines[2].replace(",", ",x", 3)]) + "\n")
    with pytest.raises(InputError, match=r"poses_bad.csv.*line 3"):
        evaluate_measured(coarse_phantom.dir, bad, experiment["measured"], methods=("rigid",))
    dup = tmp_path / "poses_dup.csv"
    dup.write_text("\n".join([lines[0], lines[1], lines[1]]) + "\n")
    with pytest.raises(InputError, match=r"poses_dup.csv.*line 3: frame 0 appears twice"):
        evaluate_measured(coarse_phantom.dir, dup, experiment["measured"], methods=("rigid",))
    with pytest.raises(InputError, match="file not found"):
        read_measured(tmp_path / "absent.csv")


def test_evaluate_case_asks_to_train_first(coarse_phantom, experiment):
    with pytest.raises(InputError, match="biopsynav train"):
        evaluate_case(coarse_phantom.dir)
    with pytest.raises(InputError, match="go together"):
        evaluate_case(coarse_phantom.dir, poses=experiment["poses"])
