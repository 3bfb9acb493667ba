"""Label maps as clinicians have them: a bilateral prone segmentation with negative labels, a
pectoral-muscle label and named segments (a Slicer .seg.nrrd, LPS in the file), taken to a
case in RAS with --side, --chest-labels and names; markups; reading errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
import SimpleITK as sitk

from biopsynav.case import Case
from biopsynav.cli import main
from biopsynav.probe import eligible_centers

SPACING = np.array([2.0, 2.0, 2.5])  # mm, anisotropic: the surface is made on resampled voxels
ORIGIN = np.array([10.0, -20.0, 5.0])  # LPS mm
SEGMENTS = [("muscle", -1), ("skin", -2), ("fat", 1), ("tumour", -3), ("benign", -4)]
LPS_TO_RAS = np.array([-1.0, -1.0, 1.0])


def chest_wall_y(x):
    """Index-frame LPS y (mm from the image corner) of the curved pectoral surface at x."""
    return 60.0 - 8.0 * ((x - 85.0) / 50.0) ** 2


def bilateral_labels(bridge: bool = False) -> np.ndarray:
    """(x, y, z) labels: two half-ellipsoid breasts (skin -2, fat 1) in front of (LPS -y) a
    curved muscle (-1), a tumour (-3) in the patient's left breast (LPS +x), a benign lesion
    (-4) in the right; both breasts run out of the image along z (crop faces). ``bridge``
    joins the breasts with skin across the sternum."""
    shape = (np.array([170.0, 80.0, 70.0]) / SPACING).astype(int)
    idx = np.indices(shape).transpose(1, 2, 3, 0) * SPACING
    wall = chest_wall_y(idx[..., 0])
    lab = np.zeros(shape, np.int16)
    lab[(idx[..., 1] >= wall) & (idx[..., 1] < wall + 14)] = -1
    front = idx[..., 1] < wall
    for cx, lesion, value in ((45.0, (45.0, 40.0, 35.0), -4), (125.0, (125.0, 38.0, 30.0), -3)):
        r = (((idx[..., 0] - cx) / 32) ** 2 + ((idx[..., 1] - 60) / 40) ** 2
             + ((idx[..., 2] - 35) / 40) ** 2)
        lab[front & (r < 1.0)] = -2
        lab[front & (r < 0.86)] = 1
        lab[np.linalg.norm(idx - np.array(lesion), axis=-1) < 6.0] = value
    if bridge:
        band = ((np.abs(idx[..., 0] - 85) < 25) & front & (idx[..., 1] > wall - 6)
                & (np.abs(idx[..., 2] - 35) < 15))
        lab[band & (lab == 0)] = -2
    return lab


def write_segmentation(path, lab: np.ndarray, names: bool = True) -> None:
    image = sitk.GetImageFromArray(np.transpose(lab, (2, 1, 0)))  # (z, y, x)
    image.SetSpacing(tuple(SPACING.tolist()))
    image.SetOrigin(tuple(ORIGIN.tolist()))
    for i, (name, value) in enumerate(SEGMENTS if names else []):
        image.SetMetaData(f"Segment{i}_Name", name)
        image.SetMetaData(f"Segment{i}_LabelValue", str(value))
        image.SetMetaData(f"Segment{i}_Layer", "0")
    sitk.WriteImage(image, str(path))


def to_ras(ijk: np.ndarray) -> np.ndarray:
    return (ORIGIN + np.asarray(ijk, float) * SPACING) * LPS_TO_RAS


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.fixture(scope="module")
def segmentation(tmp_path_factory):
    lab = bilateral_labels()
    path = tmp_path_factory.mktemp("seg") / "breasts.seg.nrrd"
    write_segmentation(path, lab)
    return path, lab


def test_bilateral_segmentation_by_name_side_and_muscle(segmentation, tmp_path, capsys):
    path, lab = segmentation
    code, out, err = run(capsys, "init", tmp_path / "c", "--labelmap", path, "--side", "left",
                         "--chest-labels", "muscle", "--breast-labels", "fat,skin",
                         "--lesion-labels", "tumour")
    assert code == 0, err
    case = Case.load(tmp_path / "c")
    a, g = case.anatomy, case.grid
    # the patient's left breast: LPS +x, RAS -x
    assert a.vertices[:, 0].max() < -90.0
    # the lesion centre is the tumour label's centroid in RAS, within half a voxel
    (lesion,) = a.lesions
    centroid = to_ras(np.argwhere(lab == -3).mean(axis=0))
    assert np.linalg.norm(lesion.center - centroid) < 0.5 * SPACING.min()
    # the surface volume matches the labelled volume of that breast
    ijk = np.argwhere(np.isin(lab, [1, -2, -3]))
    left = ijk[ijk[:, 0] * SPACING[0] > 85.0]
    labelled_ml = len(left) * np.prod(SPACING) / 1000.0
    assert a.volume_ml() == pytest.approx(labelled_ml, rel=0.03)
    # the chest wall is the curved muscle interface, not a plane
    assert a.chest_curved
    wall_vertices = a.vertices[a.fixed_vertices] * LPS_TO_RAS - ORIGIN  # index-frame LPS mm
    gap = wall_vertices[:, 1] - chest_wall_y(wall_vertices[:, 0])
    assert np.abs(gap).max() < 2.5 * SPACING.max()
    assert np.ptp(wall_vertices[:, 1]) > 3.0, "the wall follows the curved muscle"
    nodes = g.node_coords()[g.fixed_nodes.ravel()] * LPS_TO_RAS - ORIGIN
    node_gap = nodes[:, 1] - chest_wall_y(nodes[:, 0])
    diagonal = np.sqrt(3.0) * g.spacing
    assert node_gap.min() > -case.cfg.anatomy.chest_wall_tolerance_mm - 2 * SPACING.max()
    assert node_gap.max() < diagonal, "every fixed node lies on the muscle interface"
    assert len(nodes) > 50
    # crop faces (the image ends the breast along z) are never a push centre
    assert a.crop_vertices.sum() > 50
    assert not a.crop_vertices[eligible_centers(a, case.cfg.probe.min_chest_distance_mm)].any()
    # every label got a tissue by its segment name, mixed by volume in cells
    code, out, _ = run(capsys, "info", tmp_path / "c", "--json")
    info = json.loads(out)
    tissues = {t["segment"]: t["tissue"] for t in info["tissues"]}
    assert tissues == {"tumour": "lesion", "skin": "skin", "fat": "fat"}
    assert info["label_map"]["label_volume_ml"] == pytest.approx(labelled_ml, rel=1e-3)
    assert "the patient's left one of 2 breasts (--side left)" in info["label_map"]["breast"]
    share = g.active_label_share()
    assert ((share > 0).sum(axis=1) > 1).sum() > 50, "cells across the skin mix tissues"


def test_negative_values_in_every_spelling(segmentation, tmp_path, capsys):
    path, _ = segmentation
    by_value = ["--breast-labels", "-2,1", "--chest-labels", "-1", "--lesion-labels", "-3",
                "--tissue-labels", "-2=skin,1=fat"]
    code, _, err = run(capsys, "init", tmp_path / "a", "--labelmap", path, "--side", "left",
                       *by_value)
    assert code == 0, err
    code, _, err = run(capsys, "init", tmp_path / "b", "--labelmap", path, "--side=left",
                       "--breast-labels=-2,1", "--chest-labels=-1", "--lesion-labels=-3")
    assert code == 0, err
    a, b = Case.load(tmp_path / "a"), Case.load(tmp_path / "b")
    np.testing.assert_array_equal(a.grid.label_values, [-3, -2, 1])
    np.testing.assert_allclose(a.grid.label_share, b.grid.label_share)
    assert a.anatomy.fingerprint() == b.anatomy.fingerprint()


def test_two_breasts_need_a_side(segmentation, tmp_path, capsys):
    path, _ = segmentation
    code, _, err = run(capsys, "init", tmp_path / "c", "--labelmap", path, "--breast-labels",
                       "fat,skin")
    assert code == 2 and "2 separate breasts" in err and "--side left" in err
    assert "no lesion given to choose by" in err and err.count("\n") == 1
    # the lesions decide when they lie in one breast only
    code, _, err = run(capsys, "init", tmp_path / "c", "--labelmap", path, "--breast-labels",
                       "fat,skin", "--lesion-labels", "benign", "--chest-labels", "muscle")
    assert code == 0, err
    assert Case.load(tmp_path / "c").anatomy.vertices[:, 0].min() > -90.0  # the right one


def test_lesion_specks_do_not_choose_the_breast(tmp_path, capsys):
    """Clinical maps hold specks of a lesion label far from the tumour (exam 10 of the MRI
    collection: 44 of them, 0.001-0.03 mL, in both breasts): they neither make the map's
    breasts both hold lesions nor become lesions. A lesion-sized blob does."""
    lab = bilateral_labels()
    speck = (int(120 / SPACING[0]), int(50 / SPACING[1]), int(40 / SPACING[2]))
    assert lab[speck] == 1, "the speck lies in the patient's left breast's fat"
    lab[speck] = -4
    path = tmp_path / "specks.nrrd"
    write_segmentation(path, lab, names=False)
    flags = ["--breast-labels", "-2,1", "--chest-labels", "-1", "--lesion-labels", "-4",
             "--tissue-labels", "-2=skin,1=fat,-4=lesion"]
    code, _, err = run(capsys, "init", tmp_path / "c", "--labelmap", path, *flags)
    assert code == 0, err
    case = Case.load(tmp_path / "c")
    assert case.anatomy.vertices[:, 0].max() < -20.0, "the right breast, which holds the lesion"
    assert len(case.anatomy.lesions) == 1
    lab[speck[0] - 2:speck[0] + 3, speck[1] - 2:speck[1] + 3, speck[2] - 2:speck[2] + 2] = -4
    write_segmentation(path, lab, names=False)
    code, _, err = run(capsys, "init", tmp_path / "d", "--labelmap", path, *flags)
    assert code == 2 and "lesions in 2 of them" in err


def test_small_compact_lesions_are_lesions_and_slivers_specks():
    """On 1 mm voxels (the MRI collection's): a 0.048 mL lesion beside a large one is a
    lesion (its one-voxel erosion keeps a core: exam 37's second lesion), a 0.030 mL sliver
    one voxel thick is a speck (exam 02's largest speck is 0.040 mL, its core 1 voxel)."""
    from scipy import ndimage

    from biopsynav.anatomy.labelmap import kept_lesions

    labels = np.zeros((60, 40, 40), np.int16)
    idx = np.indices(labels.shape).transpose(1, 2, 3, 0)
    labels[np.linalg.norm(idx - [15, 20, 20], axis=-1) < 6] = -3
    labels[40:44, 10:14, 10:13] = -3  # 48 voxels, 4 x 4 x 3
    labels[30:70, 30, 30] = -3  # a line of 30 voxels
    (voxels, kept), = kept_lesions(labels, [-3], 1.0)
    assert ndimage.label(kept)[1] == 2
    assert kept[41, 11, 11] and not kept[35, 30, 30]


def test_a_maps_only_lesion_is_kept_however_small(tmp_path, capsys):
    """A map's one lesion under the speck size (exam 31 of the MRI collection: a 0.041 mL
    benign lesion) is the lesion, not a speck: it chooses the breast and is modelled."""
    lab = bilateral_labels()
    lab[lab == -4] = 1
    spot = (int(45 / SPACING[0]), int(42 / SPACING[1]), int(35 / SPACING[2]))
    lab[spot[0]:spot[0] + 3, spot[1], spot[2]] = -4  # 3 voxels of 10 mm3: 0.03 mL
    path = tmp_path / "small.nrrd"
    write_segmentation(path, lab, names=False)
    code, out, err = run(capsys, "init", tmp_path / "c", "--labelmap", path, "--breast-labels",
                         "-2,1", "--chest-labels", "-1", "--lesion-labels", "-4",
                         "--tissue-labels", "-2=skin,1=fat,-4=lesion")
    assert code == 0, err
    case = Case.load(tmp_path / "c")
    assert case.anatomy.vertices[:, 0].max() < -20.0, "the right breast, which holds it"
    assert len(case.anatomy.lesions) == 1


def test_breasts_joined_across_the_sternum_are_cut(tmp_path, capsys):
    path = tmp_path / "joined.nrrd"
    write_segmentation(path, bilateral_labels(bridge=True), names=False)
    code, _, err = run(capsys, "init", tmp_path / "c", "--labelmap", path, "--side", "right",
                       "--breast-labels", "-2,1", "--chest-labels", "-1", "--lesion-labels",
                       "-4", "--tissue-labels", "-2=skin,1=fat")
    assert code == 0, err
    a = Case.load(tmp_path / "c").anatomy
    assert a.vertices[:, 0].min() > -90.0 and a.vertices[:, 0].max() < -20.0
    cut_x = a.vertices[a.crop_vertices][:, 0]
    assert (cut_x < -80.0).any(), "the midline cut is a crop face"
    # without --side the lesions choose the half, as they choose between separate breasts
    flags = ["--breast-labels", "-2,1", "--chest-labels", "-1", "--tissue-labels",
             "-2=skin,1=fat,-3=lesion,-4=lesion"]
    code, out, err = run(capsys, "init", tmp_path / "d", "--labelmap", path, *flags,
                         "--lesion-labels", "-4")
    assert code == 0, err
    assert "the patient's right breast, cut from the other at the midline (the one holding" in out
    np.testing.assert_allclose(Case.load(tmp_path / "d").anatomy.vertices, a.vertices)
    code, _, err = run(capsys, "init", tmp_path / "e", "--labelmap", path, *flags,
                       "--lesion-labels", "-3,-4")
    assert code == 2 and "joined across the sternum, lesions in both; give --side" in err


def test_unmapped_and_unknown_labels_are_refused_at_init(tmp_path, capsys):
    path = tmp_path / "plain.nrrd"
    write_segmentation(path, bilateral_labels(), names=False)
    code, _, err = run(capsys, "init", tmp_path / "c", "--labelmap", path, "--side", "left",
                       "--breast-labels", "-2,1")
    assert code == 2 and "tissue labels -3, -2, 1 with no tissue" in err
    assert str(path) in err and "case.toml" not in err, "names the user's label map"
    code, _, err = run(capsys, "init", tmp_path / "c", "--labelmap", path, "--breast-labels",
                       "fat")
    assert code == 2 and "'fat' is neither a label value nor a segment name" in err
    code, _, err = run(capsys, "init", tmp_path / "c", "--labelmap", path, "--breast-labels",
                       "+-3")
    assert code == 2 and "'+-3' is neither a label value nor a segment name" in err
    assert not (tmp_path / "c").exists()


@pytest.mark.parametrize("kind, message", [
    ("rgb", "not a label map: 3 channels"),
    ("float", "voxel values are not integers"),
    ("overlap", "segments overlap in"),
])
def test_images_that_are_not_label_maps(tmp_path, capsys, kind, message):
    arr = np.zeros((20, 20, 20), np.uint8)
    arr[5:15, 5:15, 5:15] = 1
    path = tmp_path / "x.nrrd"
    if kind == "float":
        image = sitk.GetImageFromArray(arr.astype(np.float32) * 0.37)
    else:
        layers = [sitk.GetImageFromArray(arr) for _ in range(3 if kind == "rgb" else 2)]
        image = sitk.Compose(layers)
        if kind == "overlap":
            for i in range(2):
                image.SetMetaData(f"Segment{i}_Name", f"s{i}")
                image.SetMetaData(f"Segment{i}_LabelValue", "1")
                image.SetMetaData(f"Segment{i}_Layer", str(i))
    sitk.WriteImage(image, str(path))
    code, _, err = run(capsys, "init", tmp_path / "c", "--labelmap", path, "--breast-labels",
                       "1")
    assert code == 2 and message in err and str(path) in err, err


def test_markups_and_csv_frames(segmentation, tmp_path, capsys):
    """Lesions from Slicer markups (LPS and RAS) and from a CSV given in LPS land on the label
    map's tumour in RAS."""
    path, lab = segmentation
    centre = to_ras(np.argwhere(lab == -3).mean(axis=0))
    markups = tmp_path / "lesions.mrk.json"
    lps = (centre * LPS_TO_RAS).tolist()
    markups.write_text(json.dumps({"markups": [{"type": "Fiducial", "coordinateSystem": "LPS",
                                                "controlPoints": [{"position": lps}]}]}))
    csv = tmp_path / "lesions.csv"
    csv.write_text("id,x,y,z,radius_mm\n4,{},{},{},6\n".format(*lps))
    common = ["--labelmap", path, "--side", "left", "--breast-labels", "fat,skin",
              "--chest-labels", "muscle"]
    for name, extra in [("m", ["--lesions", markups]), ("c", ["--lesions", csv, "--frame",
                                                              "lps"])]:
        code, _, err = run(capsys, "init", tmp_path / name, *common, *extra)
        assert code == 0, err
        (les,) = Case.load(tmp_path / name).anatomy.lesions
        np.testing.assert_allclose(les.center, centre, atol=1e-9)
    # the same CSV read as RAS lies outside this breast: refused, naming the file
    code, _, err = run(capsys, "init", tmp_path / "r", *common, "--lesions", csv)
    assert code == 2 and "outside the breast" in err and str(csv) in err
    markups.write_text('{"markups": [{"controlPoints": [{"position": [1, 2]}]}]}')
    code, _, err = run(capsys, "init", tmp_path / "r", *common, "--lesions", markups)
    assert code == 2 and "control point 1" in err


def test_markup_lesions_pick_the_breast_that_holds_them(segmentation, tmp_path, capsys):
    """Without --side, lesions given as markups choose the breast as lesion labels do."""
    path, lab = segmentation
    markups = tmp_path / "lesions.mrk.json"
    lps = (to_ras(np.argwhere(lab == -4).mean(axis=0)) * LPS_TO_RAS).tolist()
    markups.write_text(json.dumps({"markups": [{"coordinateSystem": "LPS",
                                                "controlPoints": [{"position": lps}]}]}))
    code, _, err = run(capsys, "init", tmp_path / "c", "--labelmap", path, "--breast-labels",
                       "fat,skin,benign", "--chest-labels", "muscle", "--tissue-labels",
                       "-4=lesion", "--lesions", markups)
    assert code == 0, err
    case = Case.load(tmp_path / "c")
    assert case.anatomy.vertices[:, 0].min() > -90.0  # the patient's right breast
    facts = json.loads(case.paths.facts.read_text())
    assert "holding the lesions" in facts["breast"]


def test_unlabelled_gaps_inside_the_breast_take_the_nearest_tissue(tmp_path, capsys):
    """Background voxels enclosed by the breast (gaps a segmentation leaves) are breast, with
    the tissue of their neighbours: never an unmapped label 0; info counts them."""
    lab = bilateral_labels()
    from scipy import ndimage

    fat = np.argwhere(ndimage.binary_erosion(lab == 1, iterations=2, border_value=0))
    gaps = fat[np.random.default_rng(0).choice(len(fat), 40, replace=False)]
    lab[tuple(gaps.T)] = 0
    path = tmp_path / "gaps.seg.nrrd"
    write_segmentation(path, lab)
    code, _, err = run(capsys, "init", tmp_path / "c", "--labelmap", path, "--side", "left",
                       "--breast-labels", "fat,skin", "--chest-labels", "muscle")
    assert code == 0, err
    case = Case.load(tmp_path / "c")
    assert 0 not in set(np.unique(case.anatomy.label_values).tolist())
    left = (gaps[:, 0] * SPACING[0] > 85.0).sum()
    facts = json.loads(case.paths.facts.read_text())
    assert facts["unlabelled_holes_voxels"] == left > 0
    code, out, _ = run(capsys, "info", tmp_path / "c")
    assert f"{left} unlabelled voxels inside the breast" in out


def test_labelled_volume_mesh_without_a_tissue_map_exits_2_at_init(tmp_path, capsys):
    """Tissue labels of a volume mesh with no mapping (UC Davis without --tissue-labels): one
    line at init naming them, with the option that maps them; nothing written."""
    import meshio

    from .test_readers import _box_tets

    pts, tets = _box_tets()
    labels = np.where(pts[tets].mean(axis=1)[:, 0] < 20, -5, 2)
    path = tmp_path / "box.vtu"
    meshio.write(path, meshio.Mesh(pts, [("tetra", tets)], cell_data={"materials": [labels]}))
    code, _, err = run(capsys, "init", tmp_path / "c", "--surface", path, "--chest-wall",
                       "z-min")
    assert code == 2 and err.count("\n") == 1
    assert "tissue labels -5, 2 with no tissue" in err and "--tissue-labels -5=fat" in err
    assert str(path) in err and "case.toml" not in err, "names the user's mesh"
    assert not (tmp_path / "c").exists()
    code, _, err = run(capsys, "init", tmp_path / "c", "--surface", path, "--chest-wall",
                       "z-min", "--tissue-labels", "-5=gland,2=fat")
    assert code == 0, err
    rows = {t["label"]: t["tissue"] for t in json.loads(run(capsys, "info", tmp_path / "c",
                                                               "--json")[1])["tissues"]}
    assert rows == {"-5": "gland", "2": "fat"}
