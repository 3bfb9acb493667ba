"""The breast of a torso segmentation (a clinical prone breast MRI's label map holds both
breasts, the muscle and the subcutaneous tissue from the upper chest to the abdomen): found by
the label flags alone, with what was modelled said and warned about."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import SimpleITK as sitk
import trimesh
from scipy import ndimage

from biopsynav.anatomy.torso import back_voxels, cut_torso
from biopsynav.case import Case
from biopsynav.cli import main
from biopsynav.config import AnatomySection

SPACING = 2.0  # mm
SHAPE = (150, 70, 130)  # LPS x (right to left), y (anterior to posterior), z (inferior up)
LAYER = (85.0, 110.0)  # LPS y of the torso layer in front of the muscle, mm
MUSCLE = (110.0, 120.0)
RADIUS = 55.0  # hemispherical breasts on the layer
CENTRES = ((80.0, 140.0), (220.0, 140.0))  # LPS (x, z), mm: the patient's right, then left
PROTRUSION = AnatomySection().breast_protrusion_mm  # the default, mm
FOLD_RADIUS = np.sqrt(RADIUS ** 2 - PROTRUSION ** 2)  # where the breast stands that far off


def torso_labels(lesions=((80.0, 50.0, 150.0),), graded: bool = False) -> np.ndarray:
    """(x, y, z) labels: muscle -1 behind a 25 mm fat layer over the whole image (chest above,
    abdomen below the breasts), two hemispherical breasts, skin -2 over all the tissue that
    faces air, tumours -3 (6 mm radius) at ``lesions`` (LPS mm). ``graded``: fat as labels
    5, 6, 7 and gland as 1, 2, 3 in bands, as detailed MRI models grade them."""
    idx = np.indices(SHAPE).transpose(1, 2, 3, 0) * SPACING
    x, y, z = idx[..., 0], idx[..., 1], idx[..., 2]
    lab = np.zeros(SHAPE, np.int16)
    tissue = (y >= LAYER[0]) & (y < LAYER[1])
    for cx, cz in CENTRES:
        tissue |= (np.sqrt((x - cx) ** 2 + (y - LAYER[0]) ** 2 + (z - cz) ** 2) < RADIUS) \
            & (y < LAYER[0])
    lab[tissue] = 1
    if graded:
        band = (np.floor(y / 10.0).astype(int) % 6)
        lab[tissue] = np.array([1, 2, 3, 5, 6, 7], np.int16)[band[tissue]]
    skin = tissue & ~ndimage.binary_erosion(tissue, border_value=1)
    lab[skin] = -2
    lab[(y >= MUSCLE[0]) & (y < MUSCLE[1])] = -1
    for centre in lesions:
        lab[np.linalg.norm(idx - np.array(centre), axis=-1) < 6.0] = -3
    return lab


def expected_breast_ml() -> float:
    """The tissue of the footprint columns (analytic): the layer under the footprint disc and
    the hemisphere inside it."""
    layer = np.pi * FOLD_RADIUS ** 2 * (LAYER[1] - LAYER[0])
    ring = 2.0 * np.pi / 3.0 * (RADIUS ** 2 - FOLD_RADIUS ** 2) ** 1.5
    return (layer + 2.0 / 3.0 * np.pi * RADIUS ** 3 - ring) / 1000.0


def write(path, lab: np.ndarray) -> None:
    image = sitk.GetImageFromArray(np.transpose(lab, (2, 1, 0)))
    image.SetSpacing((SPACING,) * 3)
    sitk.WriteImage(image, str(path))


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


LABEL_FLAGS = ("--breast-labels", "1,-2", "--lesion-labels", "-3", "--chest-labels", "-1",
               "--tissue-labels", "1=fat,-2=skin")


@pytest.fixture(scope="module")
def torso_case(tmp_path_factory):
    """The right breast of the torso, by the label flags and --side alone."""
    root = tmp_path_factory.mktemp("torso")
    write(root / "torso.nrrd", torso_labels())
    code = main([str(a) for a in ("init", root / "c", "--labelmap", root / "torso.nrrd",
                                  "--side", "right", *LABEL_FLAGS)])
    assert code == 0
    return root / "c"


def test_one_breast_of_the_expected_volume_with_the_abdomen_cut(torso_case, capsys):
    case = Case.load(torso_case)
    a = case.anatomy
    assert a.volume_ml() == pytest.approx(expected_breast_ml(), rel=0.05)
    z = a.vertices[:, 2]  # RAS z = LPS z here (origin 0)
    assert z.min() > CENTRES[0][1] - FOLD_RADIUS - 2 * SPACING, "the abdomen is cut away"
    assert z.max() < CENTRES[0][1] + FOLD_RADIUS + 2 * SPACING, "the upper chest is cut away"
    assert (-a.vertices[:, 0]).max() < 150.0, "the patient's right breast only"
    # the cut faces are crop faces, the back is the chest wall
    assert a.crop_vertices.sum() > 100 and a.fixed_vertices.sum() > 100
    cut_y = -a.vertices[a.crop_vertices][:, 1]  # LPS y
    # through the layer and the breast's rim that stands under PROTRUSION off it
    assert cut_y.min() > LAYER[0] - PROTRUSION - 2 * SPACING
    assert cut_y.max() > LAYER[0] + 15.0, "down to the chest wall, which holds its foot"
    code, out, _ = run(capsys, "info", torso_case, "--json")
    info = json.loads(out)
    assert info["warnings"] == []
    m = info["modelled"]
    assert m["back_held_share"] > 0.95
    assert m["breast_volume_ml"] == pytest.approx(expected_breast_ml(), rel=0.05)
    torso_ml = np.prod(SHAPE) * SPACING ** 3 / 1000.0 * (LAYER[1] - LAYER[0]) / (
        SHAPE[1] * SPACING)
    assert m["torso_cut_ml"] == pytest.approx(torso_ml - 2 * np.pi * FOLD_RADIUS ** 2 * 25e-3,
                                              rel=0.05)
    assert sum(m["torso_cut_where"].values()) == pytest.approx(1.0, abs=1e-3)
    _, text, _ = run(capsys, "info", torso_case)
    assert "of the map's torso tissue cut away" in text and "holds 100 % of its back" in text


def test_chest_labels_need_no_tissue(torso_case):
    case = Case.load(torso_case)
    assert -1 not in case.grid.label_values.tolist()
    assert set(case.grid.label_values.tolist()) == {-3, -2, 1}


def test_without_side_the_breast_that_holds_the_lesion(tmp_path, capsys):
    write(tmp_path / "t.nrrd", torso_labels(lesions=((220.0, 50.0, 130.0),)))
    code, out, err = run(capsys, "init", tmp_path / "c", "--labelmap", tmp_path / "t.nrrd",
                         *LABEL_FLAGS)
    assert code == 0, err
    a = Case.load(tmp_path / "c").anatomy
    assert (-a.vertices[:, 0]).min() > 150.0, "the patient's left breast, holding the tumour"
    assert "the patient's left one of 2 breasts, the one holding the lesions" in json.dumps(
        json.loads(run(capsys, "info", tmp_path / "c", "--json")[1])["label_map"])
    assert "breast    the patient's left one of 2 breasts" in out  # init says which it took


def test_a_lesion_near_the_cut_is_warned_about(tmp_path, capsys):
    near = (80.0 + FOLD_RADIUS - 9.0, 97.0, 140.0)  # in the layer, 3 mm inside the cut
    write(tmp_path / "t.nrrd", torso_labels(lesions=((80.0, 50.0, 150.0), near)))
    code, out, err = run(capsys, "init", tmp_path / "c", "--labelmap", tmp_path / "t.nrrd",
                         "--side", "right", *LABEL_FLAGS)
    assert code == 0, err
    warned = [line for line in out.splitlines() if line.startswith("  warning")]
    assert len(warned) == 1 and "lesion 2 lies" in warned[0] and "crop face" in warned[0]
    assert "a lower [anatomy] breast_protrusion_mm cuts the torso further out" in warned[0]


def test_graded_labels_map_by_a_table(tmp_path, capsys):
    write(tmp_path / "t.nrrd", torso_labels(graded=True))
    table = tmp_path / "grades.csv"
    table.write_text("# label, tissue\n1,gland\n2,gland\n3,gland\n5,fat\n6,fat\n7,fat\n"
                     "-2,skin\n", encoding="utf-8")
    code, out, err = run(capsys, "init", tmp_path / "c", "--labelmap", tmp_path / "t.nrrd",
                         "--side", "right", "--lesion-labels", "-3", "--chest-labels", "-1",
                         "--tissue-labels", table)
    assert code == 0, err
    info = json.loads(run(capsys, "info", tmp_path / "c", "--json")[1])
    tissues = {int(t["label"]): t["tissue"] for t in info["tissues"]}
    assert tissues == {-3: "lesion", -2: "skin", 1: "gland", 2: "gland", 3: "gland",
                       5: "fat", 6: "fat", 7: "fat"}
    # a graded label the table leaves out is refused, named
    table.write_text("1,gland\n2,gland\n3,gland\n5,fat\n6,fat\n-2,skin\n", encoding="utf-8")
    code, _, err = run(capsys, "init", tmp_path / "d", "--labelmap", tmp_path / "t.nrrd",
                       "--side", "right", "--lesion-labels", "-3", "--chest-labels", "-1",
                       "--breast-labels", "1,2,3,5,6,7,-2", "--tissue-labels", table)
    assert code == 2 and "tissue labels 7 with no tissue" in err


def test_a_breast_alone_is_not_cut():
    """A map of one breast (no torso layer around it) keeps every voxel."""
    idx = np.indices((60, 40, 60)).transpose(1, 2, 3, 0) * SPACING
    mask = np.linalg.norm(idx - np.array([60.0, 80.0, 60.0]), axis=-1) < 55.0
    got = cut_torso(mask, np.full(3, SPACING), np.eye(3), 20.0, 200.0)
    assert (got.keep == mask).all() and not got.cut_face.any() and got.facts == {}


def test_a_thin_patients_torso_is_cut():
    """A torso layer of 4 mm (exam 44 of the MRI collection: at most 4 mm, the others 7-9 mm)
    is a torso: the breasts are kept and the layer beside them cut away."""
    idx = np.indices(SHAPE).transpose(1, 2, 3, 0) * SPACING
    x, y, z = idx[..., 0], idx[..., 1], idx[..., 2]
    front = LAYER[0] + 4.0
    mask = (y >= LAYER[0]) & (y < front)
    for cx, cz in CENTRES:
        mask |= (np.sqrt((x - cx) ** 2 + (y - LAYER[0]) ** 2 + (z - cz) ** 2) < RADIUS) \
            & (y < LAYER[0])
    got = cut_torso(mask, np.full(3, SPACING), np.diag([1.0, -1.0, 1.0]), PROTRUSION, 200.0)
    assert got.facts.get("torso_cut_ml", 0.0) > 100.0, "the thin layer beside the breasts"
    for cx, cz in CENTRES:  # each breast's apex column is kept
        i, k = int(cx / SPACING), int(cz / SPACING)
        assert got.keep[i, :, k].sum() == mask[i, :, k].sum() > 0
    assert not got.keep[int(150 / SPACING), :, int(20 / SPACING)].any(), "between, below"


def test_back_voxels_are_the_most_posterior_of_each_column():
    mask = np.zeros((3, 6, 2), bool)
    mask[0, 1:4, 0] = True
    mask[1, 2:6, 1] = True
    back = back_voxels(mask, axis=1, sign=-1.0)  # a larger index is more posterior
    assert np.argwhere(back).tolist() == [[0, 3, 0], [1, 5, 1]]
    back = back_voxels(mask, axis=1, sign=1.0)
    assert np.argwhere(back).tolist() == [[0, 1, 0], [1, 2, 1]]


def dome(path, rx: float, ry: float, h: float) -> None:
    """A closed half-ellipsoid surface (base on z = 0), mm."""
    sphere = trimesh.creation.icosphere(subdivisions=4)
    v = sphere.vertices * np.array([rx, ry, h])
    v[:, 2] = np.maximum(v[:, 2], 0.0)
    trimesh.Trimesh(v, sphere.faces).export(path)


@pytest.mark.parametrize("size, flags, message", [
    ((25.0, 25.0, 20.0), (), "outside 100-3000 mL"),
    ((140.0, 50.0, 40.0), (), "long along R, over 250 mm"),
    ((60.0, 50.0, 40.0), ("--chest-wall", "plane:0,0,0,0.35,0,-0.94"), "chest wall holds"),
])
def test_each_warning_fires_on_a_breast_made_for_it(tmp_path, capsys, size, flags, message):
    dome(tmp_path / "b.stl", *size)
    code, out, err = run(capsys, "init", tmp_path / "c", "--surface", tmp_path / "b.stl",
                         *flags)
    assert code == 0, err
    warned = [line for line in out.splitlines() if line.startswith("  warning")]
    assert len(warned) == 1 and message in warned[0], out
    assert json.loads(run(capsys, "info", tmp_path / "c", "--json")[1])["warnings"]


def test_a_normal_breast_is_not_warned_about(tmp_path, capsys):
    dome(tmp_path / "b.stl", 60.0, 50.0, 40.0)
    code, out, err = run(capsys, "init", tmp_path / "c", "--surface", tmp_path / "b.stl")
    assert code == 0, err
    assert "  warning" not in out and "holds 100 % of its back" in out


def test_an_open_surface_is_closed_and_said(tmp_path, capsys):
    box = trimesh.creation.box(extents=(80.0, 60.0, 40.0))
    top = np.flatnonzero(box.face_normals[:, 2] > 0.9)
    open_box = trimesh.Trimesh(box.vertices, np.delete(box.faces, top, axis=0), process=False)
    open_box.export(tmp_path / "open.stl")
    code, out, err = run(capsys, "init", tmp_path / "c", "--surface", tmp_path / "open.stl",
                         "--chest-wall", "z-min")
    assert code == 0, err
    said = [line for line in out.splitlines() if "was open" in line]
    assert len(said) == 1 and "1 hole(s)" in said[0]


def test_a_closed_pipe_ends_quietly(torso_case):
    """`biopsynav info CASE | head -1`: the reader closes the pipe; no error is printed."""
    shell = (f"{sys.executable} -m biopsynav.cli info {torso_case} --json | head -c 10 "
             "> /dev/null; echo ${PIPESTATUS[0]}")
    got = subprocess.run(["bash", "-c", shell], capture_output=True, text=True, timeout=120)
    assert got.stderr == "" and got.stdout.strip() in ("0", "141")


@pytest.mark.parametrize("content, message", [
    (b"1,gland,extra\n", "line 1: expected LABEL,TISSUE"),
    (b"# nothing but a comment\n", "no LABEL,TISSUE rows"),
    (b"\xff\xfe\x00binary", "not a readable LABEL,TISSUE table"),
])
def test_a_bad_tissue_table_is_one_line_naming_it(tmp_path, capsys, content, message):
    write(tmp_path / "t.nrrd", torso_labels())
    table = tmp_path / "grades.csv"
    table.write_bytes(content)
    with pytest.raises(SystemExit) as exit_:
        main(["init", str(tmp_path / "c"), "--labelmap", str(tmp_path / "t.nrrd"),
              "--tissue-labels", str(table)])
    err = capsys.readouterr().err
    assert exit_.value.code == 2 and message in err and str(table) in err
    assert "Traceback" not in err and not (tmp_path / "c").exists()
