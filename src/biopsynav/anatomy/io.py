"""Readers for anatomy inputs: surfaces, tetrahedral volumes, label maps, lesion files.

All readers return plain arrays in mm. Formats: STL/OBJ/PLY/OFF (trimesh), VTK/VTU (meshio;
triangles = surface, tetrahedra = volume with optional per-cell tissue labels), NRRD/NIfTI/MHA
label maps (SimpleITK + marching cubes), lesion CSVs ``id,x,y,z,radius_mm``.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import InputError
from .model import Lesion

SURFACE_SUFFIXES = (".stl", ".obj", ".ply", ".off")
MESHIO_SUFFIXES = (".vtk", ".vtu")
LABELMAP_SUFFIXES = (".nrrd", ".nhdr", ".nii", ".nii.gz", ".mha", ".mhd")


@dataclass
class RawAnatomy:
    """What a reader found: a surface, optional label samples, optional lesions."""

    vertices: np.ndarray
    faces: np.ndarray
    label_points: np.ndarray
    label_values: np.ndarray
    lesions: list[Lesion]
    crop_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    chest_points: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    facts: dict = field(default_factory=dict)
    segments: dict = field(default_factory=dict)


def _suffix(path: Path) -> str:
    name = path.name.lower()
    return ".nii.gz" if name.endswith(".nii.gz") else path.suffix.lower()


def _require_file(path: Path) -> None:
    if not path.exists():
        raise InputError("file not found", str(path))
    if not path.is_file():
        raise InputError("not a file", str(path))


def read_anatomy(path: str | Path, breast_labels: list | None = None,
                 lesion_labels: list | None = None, label_field: str = "",
                 **labelmap_options) -> RawAnatomy:
    """Read any supported anatomy file (surface, volume mesh or label map), in mm;
    ``labelmap_options`` go to :func:`read_labelmap`."""
    path = Path(path)
    _require_file(path)
    suffix = _suffix(path)
    if suffix in SURFACE_SUFFIXES:
        v, f = read_surface_trimesh(path)
        return RawAnatomy(v, f, np.zeros((0, 3)), np.zeros(0, np.int32), [])
    if suffix in MESHIO_SUFFIXES:
        return read_meshio(path, label_field)
    if suffix in LABELMAP_SUFFIXES:
        return read_labelmap(path, breast_labels or [], lesion_labels or [],
                             **labelmap_options)
    raise InputError(f"unsupported anatomy format {suffix!r}; use STL, OBJ, PLY, VTK, VTU, "
                     "NRRD, NIfTI or MHA", str(path))


def _reader_failure(exc: Exception) -> str:
    """Why the mesh reader gave up, in words: an import error inside the reader means it took
    the bytes for text in an unknown encoding (a damaged binary file or not a mesh at all)."""
    if isinstance(exc, ImportError):
        return "the bytes are neither a binary mesh of consistent size nor text"
    return f"{type(exc).__name__}: {exc}"


def check_stl(path: Path) -> None:
    """Refuse a file that is neither an ASCII STL nor a binary STL of consistent size, saying
    which: too short, truncated at triangle N, or a triangle count that cannot be."""
    size = path.stat().st_size
    with path.open("rb") as fh:
        head = fh.read(84)
    if head[:5].lower() == b"solid" and b"\0" not in head[:80]:
        return  # ASCII STL: trimesh reads it or says what is wrong
    if size < 84:
        raise InputError(f"not an STL file: {size} bytes, less than a binary STL's 84-byte "
                         "header", str(path))
    count = int(np.frombuffer(head[80:84], "<u4")[0])
    expected = 84 + 50 * count
    if count == 0:
        raise InputError("binary STL holds no triangles", str(path))
    if size < expected and expected <= 100 * size:
        raise InputError(f"binary STL truncated at triangle {(size - 84) // 50 + 1} of {count} "
                         f"({size} of {expected} bytes)", str(path))
    if size < expected:
        raise InputError(f"not an STL file: its header announces {count} triangles "
                         f"({expected} bytes) but the file has {size} bytes", str(path))


def read_surface_trimesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """Triangles of a surface file via trimesh (vertices merged); STL files are checked
    first (:func:`check_stl`)."""
    import trimesh

    if _suffix(path) == ".stl":
        check_stl(path)
    try:
        mesh = trimesh.load(path, force="mesh", process=True)
    except Exception as exc:  # trimesh raises many kinds on broken files
        raise InputError(f"not a readable {_suffix(path).lstrip('.').upper()} surface mesh "
                         f"({_reader_failure(exc)})", str(path)) from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise InputError("file holds no triangles", str(path))
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)


def read_meshio(path: Path, label_field: str = "") -> RawAnatomy:
    """A VTK/VTU file: tetrahedra (volume, boundary taken) or triangles (surface)."""
    import meshio

    try:
        mesh = meshio.read(path)
    except Exception as exc:
        raise InputError(f"cannot read mesh: {exc}", str(path)) from None
    points = np.asarray(mesh.points, np.float64)[:, :3]
    tets = [(i, b.data) for i, b in enumerate(mesh.cells) if b.type == "tetra"]
    if tets:
        block, conn = tets[0]
        labels = _cell_labels(mesh, block, label_field, path)
        faces = tet_boundary_faces(conn)
        used, inv = np.unique(faces, return_inverse=True)
        centroids = points[conn].mean(axis=1)
        return RawAnatomy(points[used], inv.reshape(-1, 3), centroids if labels is not None
                          else np.zeros((0, 3)),
                          labels if labels is not None else np.zeros(0, np.int32), [])
    tris = [b.data for b in mesh.cells if b.type == "triangle"]
    if not tris:
        raise InputError("mesh has neither tetrahedra nor triangles", str(path))
    faces = np.vstack(tris).astype(np.int64)
    used, inv = np.unique(faces, return_inverse=True)
    return RawAnatomy(points[used], inv.reshape(-1, 3), np.zeros((0, 3)),
                      np.zeros(0, np.int32), [])


def _cell_labels(mesh, block: int, label_field: str, path: Path) -> np.ndarray | None:
    data = mesh.cell_data
    if label_field:
        if label_field not in data:
            raise InputError(f"cell data {label_field!r} not found; present: "
                             f"{', '.join(data) or 'none'}", str(path))
        return np.asarray(data[label_field][block]).astype(np.int32).ravel()
    for values in data.values():
        arr = np.asarray(values[block])
        arr = arr.reshape(len(arr), -1)[:, 0] if arr.ndim == 2 and arr.shape[1] == 1 else arr
        if arr.ndim == 1 and np.all(np.equal(np.mod(arr, 1), 0)):
            return arr.astype(np.int32)
    return None


def tet_boundary_faces(tets: np.ndarray) -> np.ndarray:
    """Boundary triangles (outward) of a tetrahedral mesh: faces used by exactly one tet."""
    tets = np.asarray(tets, np.int64)
    local = np.array([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]])
    faces = tets[:, local].reshape(-1, 3)
    key = np.sort(faces, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    return faces[counts[inv.ravel()] == 1]


def read_labelmap(path: Path, breast_labels: list, lesion_labels: list,
                  chest_labels: list | None = None, side: str = "", spacing_mm: float = 0.0,
                  smoothing_mm: float = 1.0, lesion_centres: np.ndarray | None = None,
                  finding=None) -> RawAnatomy:
    """A segmented label map (:mod:`biopsynav.anatomy.labelmap`): one breast's smoothed
    surface, tissue-label samples, lesions (one per connected component of a lesion label),
    crop-face and chest-wall points, all in mm, RAS. ``lesion_centres`` (n, 3) mm RAS, from a
    lesion file, pick the breast that holds them as lesion labels do; ``finding``
    (:class:`.labelmap.BreastFinding`) says how the breast of a torso is found."""
    from .labelmap import read_label_anatomy

    got = read_label_anatomy(path, breast_labels, lesion_labels, chest_labels or [], side,
                             spacing_mm, smoothing_mm, lesion_centres, finding)
    lesions = [_mask_lesion(i + 1, m, got.image) for i, m in enumerate(got.lesion_masks)]
    return RawAnatomy(got.vertices, got.faces, got.label_points, got.label_values, lesions,
                      got.crop_points, got.chest_points, got.facts, got.image.segments)


def _mask_lesion(lesion_id: int, mask: np.ndarray, image) -> Lesion:
    """A lesion from its voxel mask: centre = voxel centroid, points = its surface (RAS)."""
    from .labelmap import smooth_surface

    v, _ = smooth_surface(mask, image, 0.0, 0.0)
    center = image.to_ras(np.argwhere(mask).mean(axis=0)[None])[0]
    return Lesion(lesion_id, center, float(np.linalg.norm(v - center, axis=1).mean()), v)


def read_lesion_csv(path: str | Path, n_points: int) -> list[Lesion]:
    """Spherical lesions from a CSV with columns ``id,x,y,z,radius_mm`` (mm)."""
    path = Path(path)
    _require_file(path)
    with path.open(newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        need = {"id", "x", "y", "z", "radius_mm"}
        if reader.fieldnames is None or not need <= {c.strip() for c in reader.fieldnames}:
            raise InputError(f"lesion CSV needs the columns id,x,y,z,radius_mm; found "
                             f"{reader.fieldnames}", str(path))
        lesions = []
        for line, row in enumerate(reader, start=2):
            row = {k.strip(): (v or "").strip() for k, v in row.items() if k}
            lid, center, radius = _lesion_row(row, line, path)
            if not np.isfinite(center).all() or not np.isfinite(radius) or radius <= 0:
                raise InputError(f"line {line}: lesion {lid} needs finite coordinates and a "
                                 "positive radius", str(path))
            lesions.append(Lesion(lid, center, radius, sphere_points(center, radius, n_points)))
    if not lesions:
        raise InputError("lesion CSV has no rows", str(path))
    ids = [les.id for les in lesions]
    if len(set(ids)) != len(ids):
        raise InputError("lesion ids are not unique", str(path))
    return lesions


def _lesion_row(row: dict[str, str], line: int, path: Path) -> tuple[int, np.ndarray, float]:
    """A lesion CSV row's id, centre (3,) mm and radius mm; InputError naming the line and
    the column that is empty or not a number."""
    values = []
    for column in ("id", "x", "y", "z", "radius_mm"):
        text = row.get(column, "")
        try:
            values.append(int(text) if column == "id" else float(text))
        except ValueError:
            kind = "a whole number" if column == "id" else "a number"
            what = "empty" if not text else f"not {kind}: {text!r}"
            raise InputError(f"line {line}: column {column} is {what}", str(path)) from None
    return values[0], np.array(values[1:4], dtype=np.float64), values[4]


def read_markups(path: Path, radius_mm: float, n_points: int) -> list[Lesion]:
    """Lesions from the control points of a 3D Slicer markups file (``.mrk.json``): one
    spherical lesion of ``radius_mm`` per point, id = its position in the file (from 1),
    converted to RAS from the file's ``coordinateSystem``."""
    import json

    _require_file(path)
    try:
        doc = json.loads(path.read_text(encoding="utf-8"))
        markups = doc["markups"]
        points = [(m.get("coordinateSystem", "LPS"), p["position"])
                  for m in markups for p in m.get("controlPoints", [])]
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise InputError(f"not a Slicer markups file ({type(exc).__name__}: {exc})",
                         str(path)) from None
    if not points:
        raise InputError("markups file has no control points", str(path))
    lesions = []
    for i, (frame, position) in enumerate(points, start=1):
        center = _markup_position(frame, position, i, path)
        lesions.append(Lesion(i, center, radius_mm, sphere_points(center, radius_mm, n_points)))
    return lesions


def _markup_position(frame: str, position, index: int, path: Path) -> np.ndarray:
    """One control point (3,) in RAS from the markups' ``coordinateSystem`` (RAS or LPS)."""
    try:
        p = np.asarray(position, dtype=np.float64).reshape(3)
    except (ValueError, TypeError):
        raise InputError(f"control point {index}: position {position!r} is not three "
                         "numbers", str(path)) from None
    if frame not in ("RAS", "LPS") or not np.isfinite(p).all():
        raise InputError(f"control point {index}: needs a finite position in RAS or LPS, got "
                         f"{position!r} in {frame!r}", str(path))
    return p * np.array([-1.0, -1.0, 1.0]) if frame == "LPS" else p


def read_lesion_meshes(paths: list[Path]) -> list[Lesion]:
    """One lesion per closed surface file: centre = volume centroid, points = vertices."""
    from .model import surface_volume

    lesions = []
    for i, path in enumerate(sorted(paths), start=1):
        raw = read_anatomy(path)
        v, f = raw.vertices, raw.faces
        tri = v[f]
        vol6 = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2]))
        vol = surface_volume(v, f)
        if abs(vol) < 1e-9:
            raise InputError("lesion surface encloses no volume", str(path))
        center = (vol6[:, None] * tri.sum(axis=1)).sum(axis=0) / (24.0 * vol)
        radius = float(np.linalg.norm(v - center, axis=1).mean())
        lesions.append(Lesion(i, center, radius, v))
    return lesions


def sphere_points(center: np.ndarray, radius: float, n: int) -> np.ndarray:
    """``n`` nearly uniform points (n, 3) on a sphere (Fibonacci lattice), mm."""
    k = np.arange(n) + 0.5
    z = 1.0 - 2.0 * k / n
    r = np.sqrt(1.0 - z * z)
    phi = np.pi * (3.0 - np.sqrt(5.0)) * k
    return center + radius * np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)
