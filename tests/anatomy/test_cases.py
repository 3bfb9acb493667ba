"""init / info / show as a user runs them, the phantom, the UC Davis breast, every bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from biopsynav.anatomy.chestwall import chest_wall_plane
from biopsynav.anatomy.model import winding_number
from biopsynav.anatomy.phantom import PHANTOM_LESIONS, SEMI_AXES_MM
from biopsynav.case import Case
from biopsynav.cli import main

from ..conftest import dome_surface


def run(capsys, *argv):
    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_phantom_geometry(phantom_case):
    a = phantom_case.anatomy
    exact = 2 / 3 * np.pi * np.prod(SEMI_AXES_MM) / 1000
    assert a.volume_ml() == pytest.approx(exact, rel=0.01)
    ext = np.ptp(a.vertices, axis=0)
    np.testing.assert_allclose(ext, [150, 120, 75], atol=0.5)
    assert len(a.lesions) == 10
    diam = np.array([2 * les.radius_mm for les in a.lesions])
    assert diam.min() >= 5 and diam.max() <= 10
    np.testing.assert_allclose([les.center for les in a.lesions], PHANTOM_LESIONS[:, 1:4])
    assert np.all(winding_number(np.vstack([les.points for les in a.lesions]),
                                 a.vertices, a.faces) > 0.5)
    # chest wall: the flat base z = 0, outward normal -z
    np.testing.assert_allclose(a.chest_normal, [0, 0, -1], atol=1e-6)
    assert np.all(np.abs(a.vertices[a.fixed_vertices, 2]) < 1.0)
    assert np.all(a.vertices[~a.fixed_vertices, 2] > 0)


def test_chest_wall_specs():
    v, f = dome_surface()
    p, n = chest_wall_plane(v, f, "auto", 1.0)
    np.testing.assert_allclose(n, [0, 0, -1], atol=1e-6)
    assert abs(p[2]) < 1e-6
    p, n = chest_wall_plane(v, f, "z-min", 1.0)
    assert n[2] == -1 and p[2] == pytest.approx(v[:, 2].min())
    p, n = chest_wall_plane(v, f, "plane:0,0,5,0,0,-2", 1.0)
    np.testing.assert_allclose(n, [0, 0, -1])
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=40.0)
    from biopsynav.errors import InputError

    with pytest.raises(InputError, match="no flat posterior face"):
        chest_wall_plane(np.asarray(sphere.vertices), np.asarray(sphere.faces), "auto", 1.0)


def test_init_info_show_phantom(tmp_path, capsys):
    case = tmp_path / "my-case"
    code, out, err = run(capsys, "init", case, "--phantom")
    assert code == 0, err
    assert (case / "case.toml").is_file() and (case / "inputs" / "phantom_lesions.csv").is_file()
    code, out, _ = run(capsys, "info", case, "--json")
    info = json.loads(out)
    for key in ("volume_ml", "grid_shape", "cell_size_mm", "active_cells", "n_lesions",
                "n_fixed_nodes"):
        assert key in info
    assert info["grid_shape"] == [24, 20, 13] and info["n_lesions"] == 10
    code, out, _ = run(capsys, "info", case)
    assert "2225 active cells" in out and "stages" in out
    code, out, _ = run(capsys, "show", case)
    png = case / "anatomy.png"
    assert code == 0 and png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    code, _, err = run(capsys, "init", case, "--phantom")
    assert code == 2 and "already exists" in err
    (case / "model").mkdir()  # a rebuilt case names what it keeps from before
    code, out, err = run(capsys, "init", case, "--phantom", "--overwrite")
    assert code == 0 and "kept from before: model;" in out and (case / "model").is_dir()


def test_init_from_stl_and_csv(tmp_path, capsys, dome_stl, dome_lesions_csv):
    case = tmp_path / "c"
    code, out, err = run(capsys, "init", case, "--surface", dome_stl, "--lesions",
                         dome_lesions_csv, "--cell-size", "5")
    assert code == 0, err
    assert (case / "inputs" / "dome.stl").is_file()
    info = json.loads(run(capsys, "info", case, "--json")[1])
    assert info["n_lesions"] == 2 and info["cell_size_mm"] == 5.0
    assert info["volume_ml"] == pytest.approx(0.5 * 4 / 3 * np.pi * 40 * 40 * 30 / 1000,
                                              rel=0.02)


def test_ucdavis_init_and_show(tmp_path, capsys, ucdavis_dir):
    from pathlib import Path

    lesions = Path(__file__).resolve().parents[2] / "examples" / "ucdavis_breast3" / "lesions.csv"
    case = tmp_path / "ucd"
    code, _, err = run(capsys, "init", case, "--surface", ucdavis_dir / "volmesh3.vtk",
                       "--tissue-labels", "1=fat,2=gland,3=skin", "--lesions", lesions)
    assert code == 0, err
    info = json.loads(run(capsys, "info", case, "--json")[1])
    assert info["pinch_vertices_split"] == 1
    assert info["volume_ml"] == pytest.approx(599, rel=0.01)
    rows = {t["label"]: t for t in info["tissues"]}
    assert {k: r["tissue"] for k, r in rows.items()} == {"1": "fat", "2": "gland", "3": "skin"}
    assert rows["2"]["E_kpa"] == pytest.approx(15.1)
    # the 2 mm skin does not turn whole 7.3 mm cells into skin: its volume, not its cells
    assert rows["3"]["volume_ml"] < 0.1 * info["volume_ml"] < rows["3"]["cells"] * 0.389
    assert abs(info["chest_wall"]["n_surface_vertices"] - 1171) < 30
    assert info["chest_wall"]["normal"][2] == pytest.approx(-1.0, abs=1e-3)
    assert run(capsys, "show", case)[0] == 0


def _bad(tmp_path, name, text=None, data=None):
    path = tmp_path / name
    if text is not None:
        path.write_text(text)
    if data is not None:
        path.write_bytes(data)
    return path


def test_bad_inputs_exit_2_with_one_line_and_write_nothing(tmp_path, capsys, dome_stl,
                                                            dome_lesions_csv):
    v, f = dome_surface()
    open_stl = tmp_path / "open.stl"
    keep = v[f].mean(axis=1)[:, 2] < 20
    trimesh.Trimesh(v, f[keep]).export(open_stl)
    metres = tmp_path / "metres.stl"
    trimesh.Trimesh(v / 1000.0, f).export(metres)
    outside = _bad(tmp_path, "outside.csv", "id,x,y,z,radius_mm\n1,0,0,200,3\n")
    junk = _bad(tmp_path, "junk.stl", data=b"\x00garbage")
    random_stl = _bad(tmp_path, "random.stl", data=np.random.default_rng(0).bytes(3000))
    cut_stl = _bad(tmp_path, "cut.stl", data=dome_stl.read_bytes()[:84 + 50 * 100 + 17])
    random_obj = _bad(tmp_path, "random.obj", data=np.random.default_rng(0).bytes(3000))
    cases = [
        (["--surface", tmp_path / "missing.stl"], "missing.stl: file not found"),
        (["--surface", junk], f"{junk}: not an STL file: 8 bytes"),
        (["--surface", random_stl], f"{random_stl}: not an STL file: its header announces"),
        (["--surface", cut_stl], f"{cut_stl}: binary STL truncated at triangle 101 of "),
        (["--surface", random_obj], f"{random_obj}: not a readable OBJ surface mesh"),
        (["--surface", open_stl], "surface is not closed: 1 hole"),
        (["--surface", metres], "units look wrong"),
        (["--surface", dome_stl, "--lesions", outside],
         f"{outside}: lesion 1 at [0.0, 0.0, 200.0] mm"),
        (["--surface", dome_stl, "--chest-wall", "plane:0,0,-50,0,0,-1"], "chest wall is empty"),
        (["--surface", dome_stl, "--chest-wall", "plane:0,0,0,0,0,1"],
         "more than [anatomy] max_fixed_share = 40 %"),
        (["--surface", dome_stl, "--lesions", dome_lesions_csv, "--chest-wall",
          "plane:0,0,0,0,0,1"], f"{dome_lesions_csv}: lesion 1 at [0.0, 0.0, 10.0] mm lies on "
                                "or behind the chest wall"),
        (["--surface", dome_stl, "--lesions", tmp_path / "nope.csv"], "nope.csv: file not found"),
        (["--surface", _bad(tmp_path, "x.xyz", "1 2 3")], "unsupported anatomy format"),
        (["--surface", dome_stl, "--config", _bad(tmp_path, "c.toml", "[grid]\nsize = 3\n")],
         "unknown key 'size' in [grid]"),
        (["--surface", dome_stl, "--cell-size", "-3"], "below its minimum"),
    ]
    for i, (args, message) in enumerate(cases):
        case = tmp_path / f"case{i}"
        code, out, err = run(capsys, "init", case, *args)
        assert code == 2, (args, err)
        assert message in err, (message, err)
        assert err.count("\n") == 1 and "Traceback" not in err
        assert "inputs/" not in err, "the error names the case's copy, not the user's file"
        assert not case.exists(), "a half-built case was left behind"


def test_label_absent_from_labelmap(tmp_path, capsys):
    import SimpleITK as sitk

    labels = np.zeros((20, 20, 20), np.uint8)
    labels[5:15, 5:15, 0:10] = 1
    path = tmp_path / "seg.nrrd"
    sitk.WriteImage(sitk.GetImageFromArray(labels), str(path))
    code, _, err = run(capsys, "init", tmp_path / "c", "--labelmap", path, "--breast-labels",
                       "1", "--lesion-labels", "4")
    assert code == 2 and "--lesion-labels: none of 4 is in the label map" in err
    code, _, err = run(capsys, "init", tmp_path / "c", "--labelmap", path, "--breast-labels",
                       "1,4")
    assert code == 2 and "label 4 is absent" in err, "a breast label must be there"


def test_ucdavis_coarse_grid_embeds_the_whole_skin(tmp_path, capsys, ucdavis_dir):
    """Chest-wall vertices lie up to ~1 mm behind the fitted wall plane, where the grid's first
    node plane sits: they are clamped onto that plane (fixed or unused nodes: they never move);
    the rest must be in active cells.
    (Data generation failed on the 12 mm grid before: every worker crashed on them.)"""
    from pathlib import Path

    import numpy as np

    from biopsynav.case import Case
    from biopsynav.dataset.generate import preflight
    from biopsynav.grid.embedding import surface_embedding

    lesions = Path(__file__).resolve().parents[2] / "examples" / "ucdavis_breast3" / "lesions.csv"
    case_dir = tmp_path / "ucd"
    code, _, err = run(capsys, "init", case_dir, "--surface", ucdavis_dir / "volmesh3.vtk",
                       "--tissue-labels", "1=fat,2=gland,3=skin", "--lesions", lesions,
                       "--cell-size", "12")
    assert code == 0, err
    case = Case.load(case_dir)
    behind = case.anatomy.vertices[:, 2] < case.grid.origin[2]
    assert behind.any() and np.all(case.anatomy.fixed_vertices[behind])
    emb = surface_embedding(case.grid, case.anatomy)
    assert emb.matrix.shape == (len(case.anatomy.vertices), case.grid.n_nodes)
    assert np.allclose(np.asarray(emb.matrix.sum(axis=1)).ravel(), 1.0)
    still = case.grid.fixed_nodes.ravel() | ~case.grid.active_nodes.ravel()  # never move
    assert np.all(still[emb.nodes[behind]] | (emb.weights[behind] < 1e-9))
    preflight(case)


def test_readme_walkthrough_on_the_ucdavis_segmentation(tmp_path, capsys, ucdavis_dir):
    """README "Your own patient" on a Slicer segmentation made from the UC Davis breast
    (examples/ucdavis_breast3/make_segmentation.py, 2 mm voxels here): init by segment names
    with --side and the pectoralis, the tumour segment as the lesion; and with the markups
    file instead, which alone picks the breast."""
    import importlib.util
    from pathlib import Path

    script = (Path(__file__).resolve().parents[2] / "examples" / "ucdavis_breast3"
              / "make_segmentation.py")
    spec = importlib.util.spec_from_file_location("make_segmentation", script)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    volumes = module.make_segmentation(ucdavis_dir / "volmesh3.vtk", tmp_path / "seg", 2.0)
    breast_ml = sum(volumes[k] for k in ("fat", "gland", "skin", "tumour")) / 2
    assert breast_ml == pytest.approx(599, rel=0.03)
    seg, markups = tmp_path / "seg" / "Segmentation.seg.nrrd", tmp_path / "seg" / "lesions.mrk.json"
    code, _, err = run(capsys, "init", tmp_path / "a", "--labelmap", seg, "--side", "right",
                       "--breast-labels", "fat,gland,skin", "--lesion-labels", "tumour",
                       "--chest-labels", "pectoralis")
    assert code == 0, err
    info = json.loads(run(capsys, "info", tmp_path / "a", "--json")[1])
    assert info["n_lesions"] == 1
    assert info["chest_wall"]["kind"].startswith("interface with the chest labels")
    assert "the patient's right one of 2 breasts (--side right)" in info["label_map"]["breast"]
    assert info["volume_ml"] == pytest.approx(599, rel=0.03)
    tissues = {t["segment"]: t["tissue"] for t in info["tissues"]}
    assert tissues == {"fat": "fat", "gland": "gland", "skin": "skin", "tumour": "lesion"}
    a = Case.load(tmp_path / "a").anatomy
    np.testing.assert_allclose(a.lesions[0].center, [90.0, 105.0, 30.0], atol=1.0)
    code, _, err = run(capsys, "init", tmp_path / "b", "--labelmap", seg, "--breast-labels",
                       "fat,gland,skin,tumour", "--chest-labels", "pectoralis", "--lesions",
                       markups)
    assert code == 0, err
    b = Case.load(tmp_path / "b").anatomy
    assert len(b.lesions) == 5 and b.vertices[:, 0].min() > 25.0  # the breast of the lesions
