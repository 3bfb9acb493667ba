"""A Slicer segmentation and a markups file made from the UC Davis breast, to walk README
"Your own patient" on a patient-derived anatomy rather than on synthetic shapes.

Writes, into OUT (default ``ucd-slicer``):

* ``Segmentation.seg.nrrd``: a bilateral label image as 3D Slicer saves it (one layer, LPS
  geometry, ``Segment<i>_Name`` / ``_LabelValue`` / ``_Layer`` / ``_ID`` / ``_Color``
  fields), 1 mm voxels by default: segments ``fat``, ``gland`` and ``skin`` voxelised from the
  breast CT mesh's tissue labels (the tetrahedron holding each voxel centre), ``tumour`` (a
  5 mm sphere at example lesion 1) and ``pectoralis`` (a 6 mm slab behind each breast's
  chest-wall face). The patient's other breast is the mirror image across a sagittal plane
  beside this one, so ``--side`` matters.
* ``lesions.mrk.json``: the five example lesions of ``lesions.csv`` as a markups point list in
  LPS (Slicer's file frame), for ``--lesions``.

The mesh's own frame (mm) is taken as RAS. Units: mm.

    python examples/ucdavis_breast3/make_segmentation.py [MESH] [--out DIR] [--voxel-mm 1]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import meshio
import numpy as np
import SimpleITK as sitk
from scipy import ndimage
from scipy.spatial import cKDTree

HERE = Path(__file__).resolve().parent
MESH = HERE.parents[2] / "shared" / "data" / "ucdavis_breast3" / "volmesh3.vtk"
SEGMENTS = (("fat", 1, "0.90 0.75 0.55"), ("gland", 2, "0.85 0.45 0.45"),
            ("skin", 3, "0.95 0.80 0.70"), ("tumour", 4, "0.40 0.60 0.90"),
            ("pectoralis", 5, "0.70 0.20 0.20"))
VOXEL_MM = 1.0  # default voxel size
MUSCLE_MM = 6.0
GAP_MM = 12.0  # sagittal distance from the mesh's lowest x to the mirror plane
MARGIN_MM = 6.0


def breast_labels(points: np.ndarray, tets: np.ndarray, materials: np.ndarray,
                  axes: tuple[np.ndarray, np.ndarray, np.ndarray]) -> np.ndarray:
    """Segment values (nx, ny, nz) int16 of the voxel centres ``axes`` (mm): the material of
    the tetrahedron that holds each centre, 0 outside the mesh."""
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)
    inside_tet = _containing_tetrahedron(points, tets, grid)
    values = np.zeros(len(grid), np.int16)
    hit = inside_tet >= 0
    values[hit] = materials[inside_tet[hit]]  # the mesh's 1/2/3 are the segments' values
    return values.reshape(tuple(len(a) for a in axes))


def _containing_tetrahedron(points: np.ndarray, tets: np.ndarray, query: np.ndarray,
                            k: int = 24) -> np.ndarray:
    """Index (n,) of a tetrahedron holding each query point (mm), -1 where none of the ``k``
    tetrahedra with the nearest centroids does."""
    tree = cKDTree(points[tets].mean(axis=1))
    _, near = tree.query(query, k=k, workers=-1)
    found = np.full(len(query), -1, np.int64)
    for j in range(k):
        open_ = found < 0
        cand = near[open_, j]
        inside = _barycentric_inside(points[tets[cand]], query[open_])
        found[np.flatnonzero(open_)[inside]] = cand[inside]
    return found


def _barycentric_inside(corners: np.ndarray, p: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Whether each point (n, 3) lies in its tetrahedron (n, 4, 3)."""
    t = np.transpose(corners[:, 1:] - corners[:, :1], (0, 2, 1))  # (n, 3, 3)
    lam = np.linalg.solve(t, (p - corners[:, 0])[..., None])[..., 0]
    return (lam >= -tol).all(axis=1) & (lam.sum(axis=1) <= 1 + tol)


def add_tumour(labels: np.ndarray, axes: tuple, centre: np.ndarray, radius: float) -> None:
    """Set the voxels of the sphere (mm) that lie in the breast to ``tumour``."""
    x, y, z = np.meshgrid(*axes, indexing="ij")
    ball = (x - centre[0]) ** 2 + (y - centre[1]) ** 2 + (z - centre[2]) ** 2 <= radius ** 2
    labels[ball & (labels > 0)] = 4


def add_muscle(labels: np.ndarray, axes: tuple, base_z: float, voxel: float) -> None:
    """A pectoralis slab MUSCLE_MM thick under the breast's footprint, up to its chest face."""
    k0 = int(np.flatnonzero((labels > 0).any(axis=(0, 1)))[0])  # the breast's lowest slice
    footprint = (labels[:, :, k0:k0 + 2] > 0).any(axis=2)
    footprint = ndimage.binary_dilation(footprint, iterations=max(1, int(MARGIN_MM / voxel)))
    slab = (axes[2] < base_z + voxel) & (axes[2] >= base_z - MUSCLE_MM)
    labels[footprint[:, :, None] & slab[None, None, :] & (labels == 0)] = 5


def bilateral(labels: np.ndarray, gap_voxels: int) -> np.ndarray:
    """This breast and its mirror image across a sagittal plane ``gap_voxels`` beside it
    (lower x), with the tumour left out of the mirror."""
    mirror = labels[::-1].copy()
    mirror[mirror == 4] = 1
    gap = np.zeros((2 * gap_voxels, *labels.shape[1:]), labels.dtype)
    return np.concatenate([mirror, gap, labels], axis=0)


def write_seg_nrrd(labels: np.ndarray, origin_ras: np.ndarray, voxel: float, path: Path) -> None:
    """``labels`` (x, y, z) on cubic voxels of ``voxel`` mm whose first centre is
    ``origin_ras`` (mm), as a Slicer ``.seg.nrrd``: ITK's LPS geometry with index axes along
    RAS x, y, z."""
    image = sitk.GetImageFromArray(np.ascontiguousarray(labels.transpose(2, 1, 0)))
    image.SetSpacing((voxel,) * 3)
    image.SetDirection((-1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0))
    image.SetOrigin(tuple(float(v) for v in origin_ras * np.array([-1.0, -1.0, 1.0])))
    extent = " ".join(f"0 {n - 1}" for n in labels.shape)
    for i, (name, value, colour) in enumerate(SEGMENTS):
        for key, text in (("ID", f"Segment_{value}"), ("Name", name), ("LabelValue", value),
                          ("Layer", 0), ("Color", colour), ("Extent", extent),
                          ("NameAutoGenerated", 0), ("ColorAutoGenerated", 0),
                          ("Tags", "TerminologyEntry:")):
            image.SetMetaData(f"Segment{i}_{key}", str(text))
    image.SetMetaData("Segmentation_MasterRepresentation", "Binary labelmap")
    image.SetMetaData("Segmentation_ContainedRepresentationNames", "Binary labelmap|")
    image.SetMetaData("Segmentation_ReferenceImageExtentOffset", "0 0 0")
    sitk.WriteImage(image, str(path), useCompression=True)


def write_markups(lesions: np.ndarray, path: Path) -> None:
    """Lesion centres (n, 3) mm RAS as a Slicer markups point list saved in LPS."""
    points = [{"id": str(i), "label": f"lesion-{i}", "position": [-p[0], -p[1], p[2]],
               "positionStatus": "defined"} for i, p in enumerate(lesions, start=1)]
    doc = {"@schema": "https://raw.githubusercontent.com/slicer/slicer/master/Modules/Loadable/"
                      "Markups/Resources/Schema/markups-schema-v1.0.3.json#",
           "markups": [{"type": "Fiducial", "coordinateSystem": "LPS",
                        "coordinateUnits": "mm", "controlPoints": points}]}
    path.write_text(json.dumps(doc, indent=2))


def make_segmentation(mesh_path: str | Path, out: str | Path, voxel: float = VOXEL_MM) -> dict:
    """Write ``out/Segmentation.seg.nrrd`` and ``out/lesions.mrk.json`` from the breast CT
    mesh at ``mesh_path``; return each segment's volume, mL."""
    mesh = meshio.read(mesh_path)
    tets = mesh.cells_dict["tetra"]
    materials = np.concatenate(mesh.cell_data["materials"]).ravel().astype(np.int16)
    lo, hi = mesh.points.min(axis=0), mesh.points.max(axis=0)
    lo = lo - np.array([MARGIN_MM, MARGIN_MM, MUSCLE_MM + 2.0])
    axes = tuple(np.arange(lo[a], hi[a] + MARGIN_MM, voxel) for a in range(3))
    labels = breast_labels(mesh.points, tets, materials, axes)
    lesions = np.loadtxt(HERE / "lesions.csv", delimiter=",", skiprows=1)
    add_tumour(labels, axes, lesions[0, 1:4], lesions[0, 4])
    add_muscle(labels, axes, float(mesh.points[:, 2].min()), voxel)
    gap = max(1, int(round((GAP_MM - MARGIN_MM) / voxel)))
    both = bilateral(labels, gap)
    origin = np.array([axes[0][0] - (labels.shape[0] + 2 * gap) * voxel, axes[1][0],
                       axes[2][0]])
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    write_seg_nrrd(both, origin, voxel, out / "Segmentation.seg.nrrd")
    write_markups(lesions[:, 1:4], out / "lesions.mrk.json")
    return {name: float((both == value).sum() * voxel ** 3 / 1000.0)
            for name, value, _ in SEGMENTS}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("mesh", nargs="?", default=str(MESH))
    ap.add_argument("--out", default="ucd-slicer")
    ap.add_argument("--voxel-mm", type=float, default=VOXEL_MM)
    args = ap.parse_args()
    volumes = make_segmentation(args.mesh, args.out, args.voxel_mm)
    print(f"wrote {args.out}/Segmentation.seg.nrrd ({args.voxel_mm:g} mm voxels; mL per "
          "segment: " + ", ".join(f"{k} {v:.1f}" for k, v in volumes.items())
          + f") and {args.out}/lesions.mrk.json (LPS)")


if __name__ == "__main__":
    main()
