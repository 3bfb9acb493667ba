"""Turn the inputs named in case.toml into a checked :class:`Anatomy`."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..config import CaseConfig
from ..errors import InputError
from .chestwall import chest_wall_plane, chest_wall_vertices
from .io import RawAnatomy, read_anatomy, read_lesion_csv, read_lesion_meshes, read_markups
from .labelmap import LPS_TO_RAS, BreastFinding
from .model import Anatomy, Lesion, face_cross, vertex_normals, winding_number
from .modelled import modelled_facts, modelled_warnings
from .phantom import phantom_surface
from .surface import check_units, close_surface, split_pinch_vertices


def build_anatomy(cfg: CaseConfig, case_dir: Path) -> tuple[Anatomy, dict]:
    """Read, repair and check the anatomy of a case (mm, RAS); also return facts for ``info``."""
    a = cfg.anatomy
    lesions = (read_lesions(case_dir / a.lesions, a.lesion_points, a.input_frame,
                            a.lesion_radius_mm) if a.lesions else [])
    raw, where = read_raw(cfg, case_dir, np.array([les.center for les in lesions]))
    check_units(raw.vertices, where)
    repairs: list[str] = []
    vertices, faces = close_surface(raw.vertices, raw.faces, where, repairs)
    vertices, faces, n_pinch = split_pinch_vertices(vertices, faces)
    lesion_source = str(case_dir / a.lesions) if a.lesions else where
    lesions = lesions or raw.lesions
    curved = len(raw.chest_points) > 0
    point, normal, fixed = chest_wall(vertices, faces, raw.chest_points, a, where)
    check_lesions_inside(lesions, vertices, faces, lesion_source)
    check_lesions_free(lesions, vertices[fixed], point, normal, a.chest_wall_tolerance_mm,
                       curved, lesion_source)
    crop = near_points(vertices, raw.crop_points, _voxel_reach(raw)) & ~fixed
    if a.crop_faces == "held" and curved:
        fixed = fixed | crop  # never pushed either way; held, they are fixed like the wall
    anatomy = Anatomy(vertices, faces, vertex_normals(vertices, faces), fixed, point, normal,
                      lesions, np.asarray(raw.label_points, np.float64),
                      np.asarray(raw.label_values, np.int32), crop, curved, dict(raw.segments))
    facts = {"pinch_vertices_split": n_pinch, "crop_vertices": int(crop.sum()),
             "chest_wall_kind": _chest_kind(a, raw), **raw.facts, **modelled_facts(anatomy)}
    facts["warnings"] = repairs + modelled_warnings(facts, [les.id for les in lesions])
    return anatomy, facts


def anatomy_source(cfg: CaseConfig, case_dir: Path) -> str:
    """The name errors give the anatomy input of ``cfg``: its file in ``case_dir`` (which
    ``init`` reports as the user's own file), or the built-in phantom."""
    if cfg.anatomy.source == "phantom":
        return "built-in phantom"
    return str(case_dir / cfg.anatomy.path)


def read_raw(cfg: CaseConfig, case_dir: Path, lesion_centres: np.ndarray | None = None
             ) -> tuple[RawAnatomy, str]:
    """The anatomy input of ``cfg`` in RAS, and the name errors give it; ``lesion_centres``
    (n, 3) mm RAS, from a lesion file, pick the breast of a bilateral label map."""
    a = cfg.anatomy
    source = anatomy_source(cfg, case_dir)
    if a.source == "phantom":
        vertices, faces = phantom_surface()
        return (RawAnatomy(vertices, faces, np.zeros((0, 3)), np.zeros(0, np.int32), []),
                source)
    raw = read_anatomy(Path(source), a.breast_labels, a.lesion_labels, a.label_field,
                       chest_labels=a.chest_labels, side=a.side,
                       spacing_mm=a.labelmap_spacing_mm, smoothing_mm=a.labelmap_smoothing_mm,
                       lesion_centres=lesion_centres,
                       finding=BreastFinding(a.breast_protrusion_mm, a.torso_disc_mm))
    if a.source != "labelmap" and a.input_frame == "lps":
        raw.vertices = raw.vertices * LPS_TO_RAS
        raw.label_points = raw.label_points * LPS_TO_RAS
    return raw, source


def _voxel_reach(raw: RawAnatomy) -> float:
    """How far (mm) from a voxel centre a label-map surface vertex of that voxel may lie."""
    voxel = np.asarray(raw.facts.get("voxel_mm", [1.0, 1.0, 1.0]), np.float64)
    return float(np.linalg.norm(voxel)) + 1.0


def near_points(vertices: np.ndarray, points: np.ndarray, reach: float) -> np.ndarray:
    """(nv,) True for vertices within ``reach`` mm of any of ``points`` (n, 3)."""
    if len(points) == 0:
        return np.zeros(len(vertices), dtype=bool)
    from scipy.spatial import cKDTree

    dist, _ = cKDTree(points).query(vertices, distance_upper_bound=reach)
    return np.isfinite(dist)


def chest_wall(vertices: np.ndarray, faces: np.ndarray, interface: np.ndarray, a,
               where: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Point (3,), outward normal (3,) and fixed-vertex mask (nv,) of the chest wall: the
    vertices on a muscle interface (``interface`` points, mm) when there is one, else the
    plane of ``[anatomy] chest_wall``."""
    if len(interface) == 0:
        point, normal = chest_wall_plane(vertices, faces, a.chest_wall,
                                         a.chest_wall_tolerance_mm)
        fixed = chest_wall_vertices(vertices, point, normal, a.chest_wall_tolerance_mm, where)
        return point, normal, fixed
    fixed = near_points(vertices, interface, a.chest_wall_tolerance_mm
                        + 0.75 * _interface_spacing(interface))
    point, normal = patch_plane(vertices, faces, fixed)
    return point, normal, fixed


def _interface_spacing(points: np.ndarray) -> float:
    """Typical distance (mm) between neighbouring interface voxel centres."""
    from scipy.spatial import cKDTree

    d, _ = cKDTree(points).query(points[:: max(1, len(points) // 500)], k=2)
    return float(np.median(d[:, 1]))


def patch_plane(vertices: np.ndarray, faces: np.ndarray,
                fixed: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Area-weighted centroid (3,) and mean outward unit normal (3,) of the faces whose three
    vertices are fixed."""
    held = faces[fixed[faces].all(axis=1)]
    tri = vertices[held]
    cross = face_cross(vertices, held)
    area = 0.5 * np.linalg.norm(cross, axis=1)
    normal = cross.sum(axis=0)
    normal /= np.linalg.norm(normal)
    return (tri.mean(axis=1) * area[:, None]).sum(axis=0) / area.sum(), normal


def _chest_kind(a, raw: RawAnatomy) -> str:
    if len(raw.chest_points):
        return f"interface with the chest labels {a.chest_labels}"
    if a.chest_wall == "auto":
        return "plane of the largest flat face (auto)"
    return f"plane {a.chest_wall}"


def read_lesions(path: Path, n_points: int, frame: str = "ras",
                 markup_radius_mm: float = 5.0) -> list[Lesion]:
    """Lesions (RAS) from a CSV file in ``frame``, a Slicer markups file (its own frame), or
    a folder of lesion surface meshes in ``frame``."""
    if path.is_dir():
        files = [p for p in path.iterdir() if p.is_file()]
        if not files:
            raise InputError("lesion folder holds no mesh files", str(path))
        lesions = read_lesion_meshes(files)
    elif path.name.lower().endswith(".json"):
        return read_markups(path, markup_radius_mm, n_points)
    else:
        lesions = read_lesion_csv(path, n_points)
    if frame == "lps":
        for les in lesions:
            les.center, les.points = les.center * LPS_TO_RAS, les.points * LPS_TO_RAS
    return lesions


def check_lesions_free(lesions: list[Lesion], wall_vertices: np.ndarray, point: np.ndarray,
                       normal: np.ndarray, tol: float, curved: bool, where: str) -> None:
    """No lesion centre may lie on the chest wall (within ``tol`` mm of its vertices) or, for
    a plane wall (``point``, outward ``normal``, mm), behind it, where the grid is fixed: a
    lesion there could never move."""
    from scipy.spatial import cKDTree

    tree = cKDTree(wall_vertices)
    for les in lesions:
        gap = float(tree.query(les.center)[0])
        height = float((np.asarray(les.center) - point) @ normal)
        if curved and gap <= tol:
            raise InputError(f"lesion {les.id} at {np.round(les.center, 2).tolist()} mm lies on "
                             f"the chest wall ({gap:.1f} mm from the muscle interface), where "
                             "the tissue is fixed; check --chest-labels", where)
        if not curved and height >= -tol:
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
