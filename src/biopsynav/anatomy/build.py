"""Turn the inputs named in case.toml into a checked :class:`Anatomy`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..config import CaseConfig
from ..errors import InputError
from .chestwall import chest_wall_plane, chest_wall_vertices
from .io import read_anatomy, read_lesion_csv, read_lesion_meshes
from .model import Anatomy, Lesion, vertex_normals, winding_number
from .phantom import phantom_surface
from .surface import check_units, close_surface, split_pinch_vertices


def build_anatomy(cfg: CaseConfig, case_dir: Path) -> tuple[Anatomy, dict]:
    """Read, repair and check the anatomy of a case; also return a few facts for ``info``."""
    a = cfg.anatomy
    if a.source == "phantom":
        vertices, faces = phantom_surface()
        label_points, label_values, lesions = np.zeros((0, 3)), np.zeros(0, np.int32), []
        where = "built-in phantom"
    else:
        path = case_dir / a.path
        where = str(path)
        raw = read_anatomy(path, a.breast_labels, a.lesion_labels, a.label_field)
        vertices, faces = raw.vertices, raw.faces
        label_points, label_values, lesions = raw.label_points, raw.label_values, raw.lesions
    check_units(vertices, where)
    vertices, faces = close_surface(vertices, faces, where)
    vertices, faces, n_pinch = split_pinch_vertices(vertices, faces)
    if a.lesions:
        lesions = read_lesions(case_dir / a.lesions, a.lesion_points)
    point, normal = chest_wall_plane(vertices, faces, a.chest_wall, a.chest_wall_tolerance_mm)
    fixed = chest_wall_vertices(vertices, point, normal, a.chest_wall_tolerance_mm, where)
    lesion_source = str(case_dir / a.lesions) if a.lesions else where
    check_lesions_inside(lesions, vertices, faces, lesion_source)
    check_lesions_free(lesions, point, normal, a.chest_wall_tolerance_mm, lesion_source)
    anatomy = Anatomy(vertices, faces, vertex_normals(vertices, faces), fixed, point, normal,
                      lesions, np.asarray(label_points, np.float64),
                      np.asarray(label_values, np.int32))
    return anatomy, {"pinch_vertices_split": n_pinch}


def read_lesions(path: Path, n_points: int) -> list[Lesion]:
    """Lesions from a CSV file or a folder of lesion surface meshes."""
    if path.is_dir():
        files = [p for p in path.iterdir() if p.is_file()]
        if not files:
            raise InputError("lesion folder holds no mesh files", str(path))
        return read_lesion_meshes(files)
    return read_lesion_csv(path, n_points)


def check_lesions_free(lesions: list[Lesion], point: np.ndarray, normal: np.ndarray,
                       tol: float, where: str) -> None:
    """No lesion centre may lie on or behind the chest-wall plane (``point``, outward
    ``normal``, mm), where the grid is fixed: a lesion there could never move."""
    for les in lesions:
        height = float((np.asarray(les.center) - point) @ normal)
        if height >= -tol:
            raise InputError(f"lesion {les.id} at {np.round(les.center, 2).tolist()} mm lies on "
                             f"or behind the chest wall ({height:+.1f} mm along its outward "
                             f"normal {np.round(normal, 3).tolist()}), where the tissue is fixed;"
                             " is the chest-wall normal reversed? ([anatomy] chest_wall)", where)


def check_lesions_inside(lesions: list[Lesion], vertices: np.ndarray, faces: np.ndarray,
                         where: str = "lesions") -> None:
    """Every lesion centre must lie inside the breast surface; ``where`` names the lesions'
    source in the error."""
    if not lesions:
        return
    centres = np.array([les.center for les in lesions])
    inside = winding_number(centres, vertices, faces) > 0.5
    if not inside.all():
        bad = [les for les, ok in zip(lesions, inside, strict=True) if not ok][0]
        raise InputError(f"lesion {bad.id} at {np.round(bad.center, 2).tolist()} mm lies "
                         "outside the breast surface", where)
