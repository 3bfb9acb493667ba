"""One probe push on a case: patch selection, force spreading, solve, VTU/STL/PNG output."""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from .errors import InputError
from .fem import FEModel, Loads, SolveReport, SolverSettings, solve
from .fileio import save_figure_atomic, write_bytes_atomic, write_json_atomic
from .footprint import Footprint
from .probe import nodal_forces, probe_patch

if TYPE_CHECKING:
    from .case import Case

#: Largest distance (mm) between the --at point and the skin surface.
MAX_AT_DISTANCE_MM = 10.0
#: The push's summary, beside its files in the output folder.
SUMMARY_NAME = "simulate.json"


@dataclass
class ProbePatch:
    """Skin vertices under the probe face.

    ``center`` (3,) the surface vertex nearest the requested point, ``normal`` (3,) its outward
    normal, ``long_axis`` / ``short_axis`` (3,) unit vectors spanning the tangent plane,
    ``vertices`` (n,) ids of the surface vertices in the patch, ``points`` (n, 3) mm.
    """

    center: np.ndarray
    normal: np.ndarray
    long_axis: np.ndarray
    short_axis: np.ndarray
    vertices: np.ndarray
    points: np.ndarray


def world_long_axis(normal: np.ndarray) -> np.ndarray:
    """The probe's long axis for ``simulate``: the world x axis (y when the normal is within 30
    degrees of x), to be projected on the tangent plane by :func:`biopsynav.probe.probe_patch`."""
    return np.array([1.0, 0.0, 0.0]) if abs(normal[0]) < np.cos(np.radians(30)) else \
        np.array([0.0, 1.0, 0.0])


def patch_at(anatomy, at_mm: np.ndarray, footprint: Footprint | tuple[float, float],
             depth_tolerance_mm: float) -> ProbePatch:
    """The probe patch (:func:`biopsynav.probe.probe_patch`) centred at the skin vertex nearest
    ``at_mm`` (3,) mm; InputError if that point is not within 10 mm of the skin."""
    at_mm = np.asarray(at_mm, dtype=np.float64)
    if at_mm.shape != (3,) or not np.all(np.isfinite(at_mm)):
        raise InputError(f"--at must be three finite numbers, got {at_mm.tolist()}", "--at")
    candidates = np.flatnonzero(anatomy.pushable)
    dist = np.linalg.norm(anatomy.vertices[candidates] - at_mm, axis=1)
    nearest = candidates[int(np.argmin(dist))]
    if dist.min() > MAX_AT_DISTANCE_MM:
        raise InputError(f"the point {np.round(at_mm, 2).tolist()} mm is {dist.min():.1f} mm "
                         f"from the skin (at most {MAX_AT_DISTANCE_MM:g} mm)", "--at")
    normal = anatomy.normals[nearest] / np.linalg.norm(anatomy.normals[nearest])
    ids = probe_patch(anatomy, nearest, world_long_axis(normal), footprint,
                      depth_tolerance_mm)
    long_axis = world_long_axis(normal) - (world_long_axis(normal) @ normal) * normal
    long_axis /= np.linalg.norm(long_axis)
    return ProbePatch(anatomy.vertices[nearest], normal, long_axis,
                      np.cross(normal, long_axis), ids, anatomy.vertices[ids])


def simulate(case: Case | str | Path, force_n: np.ndarray, at_mm: np.ndarray,
             out_dir: str | Path) -> dict:
    """One probe push on ``case`` (loaded, or its folder): total force ``force_n`` (3,) N on
    the probe patch at ``at_mm`` (3,) mm.

    Writes ``displaced_surface.vtu``, ``displaced_surface.stl``, ``simulate.png`` and
    ``simulate.json`` into ``out_dir`` (atomically) and returns the summary dict (paths,
    patch size, max displacement, Newton iterations, time).

    Raises:
        InputError: bad force or point (NaN, wrong length, point far from the skin).
        SolverError: the solve did not converge.
    """
    from .case import as_case
    from .grid.embedding import Embedding, surface_embedding

    force_n = np.asarray(force_n, dtype=np.float64).ravel()
    if force_n.shape != (3,) or not np.all(np.isfinite(force_n)):
        raise InputError(f"--force must be three finite numbers, got {force_n.tolist()}",
                         "--force")
    case = as_case(case)
    anatomy, cfg = case.anatomy, case.cfg
    patch = patch_at(anatomy, at_mm, cfg.probe.footprint, cfg.probe.depth_tolerance_mm)
    if len(patch.vertices) == 0:
        raise InputError("no skin vertex under the probe footprint", "--at")
    model = FEModel.from_case(case)
    contact = Embedding.build(case.grid, patch.points, where="probe patch")
    forces = nodal_forces(contact.matrix, force_n)
    u, report = solve(model, Loads(forces=forces), SolverSettings.from_config(cfg.solver))
    skin = surface_embedding(case.grid, anatomy)
    surface_u = skin.interpolate(u)
    out_dir = Path(out_dir)
    paths = _write_outputs(out_dir, anatomy.vertices, anatomy.faces, surface_u, patch)
    summary = {
        "force_n": force_n, "at_mm": np.asarray(at_mm, dtype=np.float64),
        "patch_center_mm": patch.center, "patch_normal": patch.normal,
        "patch_long_axis": patch.long_axis, "patch_points": int(len(patch.vertices)),
        "max_surface_displacement_mm": float(np.linalg.norm(surface_u, axis=1).max()),
        "max_node_displacement_mm": report.max_displacement_mm,
        **_report_summary(report), "files": {k: str(v) for k, v in paths.items()},
    }
    write_json_atomic(out_dir / SUMMARY_NAME, summary)
    return summary


def format_simulation(s: dict) -> str:
    """The summary of :func:`simulate` as a few lines for people (mm, N, s)."""
    force = ", ".join(f"{v:.3g}" for v in np.asarray(s["force_n"]).ravel())
    centre = ", ".join(f"{v:.1f}" for v in np.asarray(s["patch_center_mm"]).ravel())
    files = [Path(p) for p in s["files"].values()]
    return "\n".join([
        f"push of ({force}) N on {s['patch_points']} skin points around ({centre}) mm",
        f"  largest displacement: {s['max_surface_displacement_mm']:.2f} mm on the skin, "
        f"{s['max_node_displacement_mm']:.2f} mm at a grid node",
        f"  solve: {s['newton_iterations']} Newton iterations in {s['load_increments']} load "
        f"increment{'' if s['load_increments'] == 1 else 's'}, {s['solve_time_s']:.2f} s, "
        f"smallest det F {s['min_det_F']:.3f}",
        f"  written to {files[0].parent}: {', '.join(p.name for p in files)} and its summary "
        f"{SUMMARY_NAME}"])


def _report_summary(report: SolveReport) -> dict:
    return {"newton_iterations": report.iterations, "load_increments": report.increments,
            "residual_rel": report.residual_rel, "min_det_F": report.min_det_F,
            "solve_time_s": report.time_s, "backend": report.backend}


def _write_outputs(out_dir: Path, vertices: np.ndarray, faces: np.ndarray,
                   surface_u: np.ndarray, patch: ProbePatch) -> dict[str, Path]:
    import meshio

    out_dir.mkdir(parents=True, exist_ok=True)
    mesh = meshio.Mesh(vertices + surface_u, [("triangle", faces)],
                       point_data={"displacement": surface_u,
                                   "displacement_magnitude": np.linalg.norm(surface_u, axis=1),
                                   "in_patch": np.isin(np.arange(len(vertices)),
                                                       patch.vertices).astype(np.int8)})
    paths = {"vtu": out_dir / "displaced_surface.vtu", "stl": out_dir / "displaced_surface.stl",
             "png": out_dir / "simulate.png"}
    for key in ("vtu", "stl"):
        write_bytes_atomic(paths[key], _mesh_bytes(mesh, key))
    save_figure_atomic(_push_figure(vertices, faces, surface_u, patch), paths["png"])
    return paths


def _mesh_bytes(mesh, file_format: str) -> bytes:
    """meshio writes to paths only: write into a private temporary folder and read back."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"mesh.{file_format}"
        if file_format == "stl":
            mesh = type(mesh)(mesh.points, mesh.cells)  # STL holds geometry only
        mesh.write(path, file_format=file_format, **({"binary": True}
                                                      if file_format == "stl" else {}))
        return path.read_bytes()


def _push_figure(vertices: np.ndarray, faces: np.ndarray, surface_u: np.ndarray, patch: ProbePatch):
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    fig = Figure(figsize=(8, 6))
    ax = fig.add_subplot(projection="3d")
    rest, moved = vertices, vertices + surface_u
    ax.plot_trisurf(rest[:, 0], rest[:, 1], rest[:, 2], triangles=faces, color="0.8",
                    alpha=0.15, linewidth=0)
    mag = np.linalg.norm(surface_u, axis=1)
    art = ax.plot_trisurf(moved[:, 0], moved[:, 1], moved[:, 2], triangles=faces,
                          cmap="viridis", alpha=0.8, linewidth=0)
    art.set_array(mag[faces].mean(axis=1))
    fig.colorbar(art, ax=ax, shrink=0.6, label="displacement (mm)")
    pts = moved[patch.vertices]
    ax.scatter(pts[:, 0], pts[:, 1], pts[:, 2], color="red", s=6, label="probe patch")
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")
    ax.set_box_aspect(np.ptp(np.vstack([rest, moved]), axis=0))
    ax.legend(loc="upper left")
    ax.set_title(f"probe push: max skin displacement {mag.max():.1f} mm")
    return fig


__all__ = ["ProbePatch", "patch_at", "simulate"]
