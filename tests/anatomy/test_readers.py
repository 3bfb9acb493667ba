"""Every anatomy input format, written by the test itself, reads back to the same breast."""

from __future__ import annotations

import meshio
import numpy as np
import pytest
import SimpleITK as sitk
import trimesh

from biopsynav.anatomy.io import read_anatomy, read_lesion_csv, tet_boundary_faces
from biopsynav.anatomy.model import surface_volume, winding_number
from biopsynav.anatomy.surface import close_surface, split_pinch_vertices
from biopsynav.errors import InputError

from ..conftest import dome_surface


@pytest.fixture(scope="module")
def dome():
    return dome_surface()


@pytest.mark.parametrize("suffix", [".stl", ".obj", ".ply", ".vtk", ".vtu"])
def test_surface_formats(tmp_path, dome, suffix):
    v, f = dome
    path = tmp_path / f"dome{suffix}"
    if suffix in (".vtk", ".vtu"):
        meshio.write(path, meshio.Mesh(v, [("triangle", f)]))
    else:
        trimesh.Trimesh(v, f).export(path)
    raw = read_anatomy(path)
    rv, rf = close_surface(raw.vertices, raw.faces, str(path))
    assert abs(surface_volume(rv, rf) - abs(surface_volume(v, f))) < 1e-3 * abs(
        surface_volume(v, f))


def _box_tets(n: int = 6, size: float = 40.0):
    from scipy.spatial import Delaunay

    g = np.linspace(0, size, n)
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    pts = pts + 1e-6 * np.random.default_rng(0).standard_normal(pts.shape)
    tets = Delaunay(pts).simplices
    vol = np.einsum("ij,ij->i", pts[tets[:, 1]] - pts[tets[:, 0]],
                    np.cross(pts[tets[:, 2]] - pts[tets[:, 0]], pts[tets[:, 3]] - pts[tets[:, 0]]))
    tets[vol < 0] = tets[vol < 0][:, [0, 2, 1, 3]]
    return pts, tets


def test_tetrahedral_volume_with_labels(tmp_path):
    pts, tets = _box_tets()
    labels = np.where(pts[tets].mean(axis=1)[:, 0] < 20, 1, 2)
    path = tmp_path / "box.vtu"
    meshio.write(path, meshio.Mesh(pts, [("tetra", tets)], cell_data={"materials": [labels]}))
    raw = read_anatomy(path)
    assert set(np.unique(raw.label_values)) == {1, 2}
    assert len(raw.label_points) == len(tets)
    v, f = close_surface(raw.vertices, raw.faces, str(path))
    assert surface_volume(v, f) == pytest.approx(40.0 ** 3, rel=1e-6)
    with pytest.raises(InputError, match="cell data 'tissue' not found"):
        read_anatomy(path, label_field="tissue")


def test_tet_boundary_is_outward():
    pts, tets = _box_tets(4)
    faces = tet_boundary_faces(tets)
    assert surface_volume(pts, faces) == pytest.approx(40.0 ** 3, rel=1e-6)


@pytest.mark.parametrize("suffix", [".nrrd", ".nii.gz", ".mha"])
def test_label_maps(tmp_path, suffix):
    spacing = 1.5
    n = 60
    idx = np.indices((n, n, n)).transpose(1, 2, 3, 0) * spacing  # x, y, z
    centre = np.array([45.0, 45.0, 0.0])
    r = np.linalg.norm(idx - centre, axis=-1)
    labels = np.zeros((n, n, n), np.uint8)
    labels[r < 40] = 1
    labels[np.linalg.norm(idx - np.array([45.0, 45.0, 20.0]), axis=-1) < 5] = 7
    image = sitk.GetImageFromArray(np.transpose(labels, (2, 1, 0)))  # to (z, y, x)
    image.SetSpacing((spacing,) * 3)
    image.SetOrigin((10.0, 20.0, 30.0))
    path = tmp_path / f"labels{suffix}"
    sitk.WriteImage(image, str(path))
    raw = read_anatomy(path, breast_labels=[1], lesion_labels=[7])
    v, f = close_surface(raw.vertices, raw.faces, str(path))
    half_ball = 0.5 * 4 / 3 * np.pi * 40 ** 3
    assert surface_volume(v, f) == pytest.approx(half_ball, rel=0.05)
    assert len(raw.lesions) == 1
    lps = np.array([10 + 45, 20 + 45, 30 + 20])
    np.testing.assert_allclose(raw.lesions[0].center, lps * [-1, -1, 1], atol=0.2)  # RAS
    assert winding_number(raw.lesions[0].center[None], v, f)[0] > 0.5
    with pytest.raises(InputError, match="--lesion-labels: none of 5 is in the label map"):
        read_anatomy(path, breast_labels=[1], lesion_labels=[5])
    with pytest.raises(InputError, match="label 5 is absent"):
        read_anatomy(path, breast_labels=[1, 5], lesion_labels=[7])
    # a protocol's lesion classes (benign, malignant) need not all be in one patient's map
    both = read_anatomy(path, breast_labels=[1], lesion_labels=[5, 7])
    assert len(both.lesions) == 1 and both.facts["lesion_labels_absent"] == ["5"]
    assert "lesion_labels_absent" not in raw.facts
    with pytest.raises(InputError, match="needs --breast-labels"):
        read_anatomy(path)


def test_lesion_csv(tmp_path):
    path = tmp_path / "l.csv"
    path.write_text("id,x,y,z,radius_mm\n3,1,2,3,4\n")
    (les,) = read_lesion_csv(path, 30)
    assert les.id == 3 and les.points.shape == (30, 3)
    np.testing.assert_allclose(np.linalg.norm(les.points - les.center, axis=1), 4.0)
    for text, msg in [("id,x,y\n1,2,3\n", "needs the columns"),
                      ("id,x,y,z,radius_mm\n1,a,2,3,4\n", "line 2: column x is not a number: 'a'"),
                      ("id,x,y,z,radius_mm\n1,1,2,3\n", "line 2: column radius_mm is empty"),
                      ("id,x,y,z,radius_mm\n1,1,2,3,4\n2.5,1,2,3,4\n",
                       "line 3: column id is not a whole number"),
                      ("id,x,y,z,radius_mm\n1,1,2,3,-4\n", "positive radius"),
                      ("id,x,y,z,radius_mm\n1,1,2,3,4\n1,1,2,3,4\n", "not unique"),
                      ("id,x,y,z,radius_mm\n", "no rows")]:
        path.write_text(text)
        with pytest.raises(InputError, match=msg):
            read_lesion_csv(path, 10)


def test_open_surface_is_repaired_or_reported(dome):
    v, f = dome
    # one missing triangle: a small hole that trimesh fills
    rv, rf = close_surface(v, f[1:], "dome.stl")
    assert surface_volume(rv, rf) > 0
    # a large cut: not repairable, the error counts the holes
    keep = v[f].mean(axis=1)[:, 2] < 20
    with pytest.raises(InputError, match=r"dome.stl: surface is not closed: 1 hole"):
        close_surface(v, f[keep], "dome.stl")


def test_pinch_vertex_is_split():
    # two tetrahedra surfaces touching at one vertex
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0],
                  [0, 0, -1]], float)
    f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3],
                  [0, 4, 5], [0, 6, 4], [0, 5, 6], [4, 6, 5]])
    nv, nf, n_split = split_pinch_vertices(v, f)
    assert n_split == 1 and len(nv) == 8
    assert surface_volume(nv, nf) == pytest.approx(surface_volume(v, f))


def test_lesion_surface_meshes(tmp_path, capsys, dome_stl):
    from biopsynav.cli import main

    folder = tmp_path / "lesions"
    folder.mkdir()
    centres = [np.array([0.0, 0.0, 12.0]), np.array([8.0, -6.0, 15.0])]
    for i, c in enumerate(centres):
        ball = trimesh.creation.icosphere(subdivisions=2, radius=3.0 + i)
        ball.apply_translation(c)
        ball.export(folder / f"lesion{i + 1}.stl")
    case = tmp_path / "case"
    assert main(["init", str(case), "--surface", str(dome_stl), "--lesions", str(folder)]) == 0
    from biopsynav.case import Case

    lesions = Case.load(case).anatomy.lesions
    assert [les.id for les in lesions] == [1, 2]
    for les, c, r in zip(lesions, centres, (3.0, 4.0), strict=True):
        np.testing.assert_allclose(les.center, c, atol=1e-6)
        assert les.radius_mm == pytest.approx(r, rel=0.02)
