"""The built-in phantom, shaped like the CIRS Model 073 breast biopsy phantom of the paper.

Geometry (mm, chest wall at z = 0, nipple towards +z): a half-ellipsoid dome with semi-axes
75 x 60 x 75 (a 150 x 120 mm base, 75 mm high, 707 mL) on a flat chest-wall base, meshed by
marching cubes at 2.5 mm, and 10 spherical lesions of 5-10 mm diameter at depths from 13 to
40 mm below the skin (:data:`PHANTOM_LESIONS`).
"""

from __future__ import annotations

import numpy as np

SEMI_AXES_MM = (75.0, 60.0, 75.0)
PHANTOM_DESCRIPTION = "Built-in CIRS 073-like phantom: 150 x 120 x 75 mm dome, 10 lesions"
MESH_STEP_MM = 2.5

#: id, x, y, z, diameter (mm)
PHANTOM_LESIONS = np.array([
    [1, -30.0, -20.0, 20.0, 8.0],
    [2, 25.0, -25.0, 15.0, 6.0],
    [3, 0.0, 0.0, 45.0, 10.0],
    [4, -20.0, 25.0, 35.0, 7.0],
    [5, 35.0, 15.0, 25.0, 9.0],
    [6, 10.0, -35.0, 30.0, 5.0],
    [7, -45.0, 0.0, 15.0, 6.0],
    [8, 45.0, -5.0, 40.0, 8.0],
    [9, -10.0, 30.0, 55.0, 7.0],
    [10, 15.0, 10.0, 60.0, 5.0],
])


def phantom_surface() -> tuple[np.ndarray, np.ndarray]:
    """Closed outward surface (vertices (nv, 3), faces (nf, 3)) of the phantom dome, mm."""
    from skimage.measure import marching_cubes

    a, b, c = SEMI_AXES_MM
    h = MESH_STEP_MM
    xs = np.arange(-a - 2 * h, a + 2 * h + 1e-9, h)
    ys = np.arange(-b - 2 * h, b + 2 * h + 1e-9, h)
    zs = np.arange(-2 * h, c + 2 * h + 1e-9, h)
    x, y, z = np.meshgrid(xs, ys, zs, indexing="ij")
    # signed-distance-like field: positive inside the dome and above the base
    dome = 1.0 - np.sqrt((x / a) ** 2 + (y / b) ** 2 + (z / c) ** 2)
    field = np.minimum(dome * min(a, b, c), z)
    verts, faces, _, _ = marching_cubes(field, level=0.0, spacing=(h, h, h))
    verts += np.array([xs[0], ys[0], zs[0]])
    verts[np.abs(verts[:, 2]) < 1e-9, 2] = 0.0
    return verts, faces[:, ::-1].astype(np.int64)


def phantom_lesions_csv() -> str:
    """The phantom lesions as CSV text (id,x,y,z,radius_mm)."""
    rows = ["id,x,y,z,radius_mm"]
    rows += [f"{int(r[0])},{r[1]:g},{r[2]:g},{r[3]:g},{r[4] / 2:g}" for r in PHANTOM_LESIONS]
    return "\n".join(rows) + "\n"
