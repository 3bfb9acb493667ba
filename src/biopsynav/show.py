"""Offscreen pictures of a case (matplotlib, Agg: no display needed)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from .case import Case  # noqa: E402
from .fileio import save_figure_atomic  # noqa: E402
from .layout import ANATOMY_PICTURE


def render_case(case: Case, out: str | Path | None = None) -> Path:
    """PNG with a 3D view and three mid-slices: surface, lesions, chest wall, grid fractions."""
    out = Path(out) if out else case.dir / ANATOMY_PICTURE
    fig = plt.figure(figsize=(14, 10))
    ax = fig.add_subplot(2, 2, 1, projection="3d")
    draw_anatomy_3d(ax, case)
    for i, axis in enumerate((1, 0, 2)):
        draw_slice(fig.add_subplot(2, 2, i + 2), case, axis)
    fig.suptitle(f"{case.cfg.case.name}: {case.anatomy.volume_ml():.0f} mL, "
                 f"{int(case.grid.active_cells.sum())} active cells of "
                 f"{case.grid.spacing:g} mm, {len(case.anatomy.lesions)} lesions")
    save_figure_atomic(fig, out)
    plt.close(fig)
    return out


def draw_anatomy_3d(ax, case: Case) -> None:
    """Surface (grey), chest wall (red; curved on a muscle interface), crop faces (purple,
    never pushed), lesions (coloured), active cell centres (blue). Axes in RAS mm."""
    a, g = case.anatomy, case.grid
    v = a.vertices
    ax.plot_trisurf(v[:, 0], v[:, 1], v[:, 2], triangles=a.faces, color="0.8", alpha=0.25,
                    linewidth=0)
    fv = v[a.fixed_vertices]
    ax.scatter(fv[:, 0], fv[:, 1], fv[:, 2], s=1, c="red",
               label="chest wall (muscle)" if a.chest_curved else "chest wall")
    cv = v[np.asarray(a.crop_vertices, bool)]
    if len(cv):
        ax.scatter(cv[:, 0], cv[:, 1], cv[:, 2], s=1, c="tab:purple", label="crop faces")
    centres = g.origin + (g.active_cell_ijk() + 0.5) * g.spacing
    ax.scatter(centres[:, 0], centres[:, 1], centres[:, 2], s=2, c="tab:blue", alpha=0.15,
               label="active cells")
    for les in a.lesions:
        p = les.points
        ax.scatter(p[:, 0], p[:, 1], p[:, 2], s=4, c="tab:orange")
        ax.text(*les.center, str(les.id), color="k", fontsize=8)
    ax.set_xlabel("R (mm)")
    ax.set_ylabel("A (mm)")
    ax.set_zlabel("S (mm)")
    ax.set_box_aspect(np.ptp(v, axis=0))
    ax.legend(loc="upper left", fontsize=7)


def draw_slice(ax, case: Case, axis: int) -> None:
    """Tissue fraction of the cells in the middle slice across ``axis``, with lesions, fixed
    nodes (red) and the crop faces where the image or the torso cut ends the breast
    (purple)."""
    g, a = case.grid, case.anatomy
    mid = g.cell_shape[axis] // 2
    if axis == 2:
        mid = g.cell_shape[2] // 3
    frac = np.take(g.fraction, mid, axis=axis)
    fixed = np.take(g.fixed_nodes, mid, axis=axis)
    dims = [d for d in range(3) if d != axis]
    lo = g.origin[dims]
    hi = lo + np.array(g.cell_shape)[dims] * g.spacing
    ax.imshow(frac.T, origin="lower", extent=(lo[0], hi[0], lo[1], hi[1]), cmap="Blues",
              vmin=0, vmax=1)
    nodes = np.argwhere(fixed) * g.spacing + lo
    ax.scatter(nodes[:, 0], nodes[:, 1], s=6, c="red", label="fixed nodes")
    plane = g.origin[axis] + (mid + 0.5) * g.spacing
    crop = a.vertices[np.asarray(a.crop_vertices, bool)]
    crop = crop[np.abs(crop[:, axis] - plane) <= 0.5 * g.spacing][:, dims]
    if len(crop):
        ax.scatter(crop[:, 0], crop[:, 1], s=2, c="tab:purple", label="crop faces (cut)")
    for les in a.lesions:
        cut = abs(les.center[axis] - plane) <= les.radius_mm
        ax.add_patch(plt.Circle(les.center[dims], les.radius_mm, color="tab:orange", fill=cut,
                                alpha=0.9 if cut else 0.5, linestyle="-" if cut else ":"))
    ax.set_xticks(lo[0] + np.arange(0, frac.shape[0] + 1, 4) * g.spacing)
    ax.set_yticks(lo[1] + np.arange(0, frac.shape[1] + 1, 4) * g.spacing)
    ax.grid(color="0.6", linewidth=0.3)
    names = "xyz"
    ax.set_xlabel(f"{names[dims[0]]} (mm)")
    ax.set_ylabel(f"{names[dims[1]]} (mm)")
    ax.set_title(f"cell fraction, slice {names[axis]} = "
                 f"{g.origin[axis] + (mid + 0.5) * g.spacing:.1f} mm")
