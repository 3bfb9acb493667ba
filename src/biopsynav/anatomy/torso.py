"""The breast of a torso segmentation, found from how far the tissue stands off the chest.

A clinical breast MRI segmentation holds the subcutaneous tissue of the whole anterior torso:
both breasts, the tissue between them, above them up to the clavicles and below them down to
the abdomen. The breast is the tissue that protrudes from that layer:

* The tissue thickness ``T`` (mm) is counted along the image axis nearest the anterior
  direction, for every column of the coronal plane.
* The torso layer's own thickness ``B`` under each column is the grey-level opening of ``T`` by
  a disc of ``torso_disc_mm`` diameter (a rolling ball): anything narrower than the disc (a
  breast) is removed, the broad layer and its slow changes stay.
* The breast's footprint is where ``T - B`` exceeds ``protrusion_mm``: the inframammary fold
  below, the sternum medially, and where the upper pole and the axillary tail fade into the
  chest wall; strips of it narrower than :data:`RIDGE_MM` (folds of the torso running from
  the breast to the axilla or the shoulder) are opened away. Every breast voxel in a
  footprint column is kept, down to the chest.
* The tissue outside the footprints is cut away; the breast's faces where it was cut are crop
  faces (never pushed). A map of one breast alone has no layer: the disc always meets empty
  columns, ``B`` is at least :data:`MIN_LAYER_MM` over less than :data:`MIN_LAYER_AREA_MM2`
  (about nothing), and nothing is cut. A thin patient's layer is thin but broad: exam 44 of
  the collection, 4 mm at most, at least 2 mm over 547 cm2 (the others 7-9 mm at most).

The defaults were chosen on exams of a public 3 T prone breast MRI collection
(docs/anatomy.md): from 20 mm the footprint's lower edge falls on the fold crease of each
exam's sagittal slices, and at 25 mm its lateral edge on the crease where the skin leaves the
chest (at 20 mm it ran down the lateral slope).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

COARSE_MM = 4.0  # in-plane pixel of the opening (the disc is 50 of them across at 200 mm)
MAX_HOLE_MM2 = 2500.0  # holes in a footprint up to 50 x 50 mm are the breast's own
MIN_LAYER_MM = 2.0  # the torso layer is where B is at least this (mm; about the skin alone)
MIN_LAYER_AREA_MM2 = 10_000.0  # ... over at least this (a 100 x 100 mm patch): else no torso
RIDGE_MM = 40.0  # strips of the footprint narrower than this are folds of the torso


@dataclass
class TorsoCut:
    """What the torso cut kept (xyz bool, the image's shape), the faces it cut, and facts."""

    keep: np.ndarray
    cut_face: np.ndarray
    facts: dict


def anterior_axis(direction: np.ndarray) -> tuple[int, float]:
    """The index axis nearest RAS anterior (+y) of an ITK image (LPS ``direction`` (3, 3)),
    and +1.0 when a larger index is more anterior, else -1.0."""
    ras_y = -np.asarray(direction, np.float64)[1]  # LPS y is posterior
    axis = int(np.argmax(np.abs(ras_y)))
    return axis, float(np.sign(ras_y[axis]))


def protrusion(mask: np.ndarray, spacing: np.ndarray, axis: int,
               disc_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Tissue thickness ``T`` and the torso layer's thickness ``B`` under it (both mm, the
    coronal plane's shape) of ``mask`` (xyz bool) counted along index ``axis``."""
    plane = [a for a in range(3) if a != axis]
    thickness = mask.sum(axis=axis) * float(spacing[axis])
    step = [max(1, int(round(COARSE_MM / spacing[a]))) for a in plane]
    coarse = thickness[::step[0], ::step[1]]
    radii = [0.5 * disc_mm / (spacing[a] * s) for a, s in zip(plane, step, strict=True)]
    layer = ndimage.grey_opening(coarse, footprint=_disc_footprint(radii), mode="nearest")
    fine = np.meshgrid(*(np.arange(n) / s for n, s in zip(thickness.shape, step, strict=True)),
                       indexing="ij")
    return thickness, ndimage.map_coordinates(layer, fine, order=1, mode="nearest")


def _disc_footprint(radii: list[float]) -> np.ndarray:
    """Boolean footprint of an ellipse with semi-axes ``radii`` (pixels)."""
    r = [max(1, int(np.ceil(x))) for x in radii]
    a, b = np.mgrid[-r[0]:r[0] + 1, -r[1]:r[1] + 1]
    return (a / radii[0]) ** 2 + (b / radii[1]) ** 2 <= 1.0


def cut_torso(mask: np.ndarray, spacing: np.ndarray, direction: np.ndarray,
              protrusion_mm: float, disc_mm: float) -> TorsoCut:
    """The breasts of ``mask`` (xyz bool): the columns whose tissue stands more than
    ``protrusion_mm`` off the torso layer, when there is a torso layer (at least
    :data:`MIN_LAYER_MM` thick over :data:`MIN_LAYER_AREA_MM2`); a map of one breast alone has
    none and is kept whole."""
    axis, _ = anterior_axis(direction)
    thickness, layer = protrusion(mask, spacing, axis, disc_mm)
    pixel_mm = spacing[[a for a in range(3) if a != axis]]
    if (layer >= MIN_LAYER_MM).sum() * float(np.prod(pixel_mm)) < MIN_LAYER_AREA_MM2:
        return TorsoCut(mask, np.zeros_like(mask), {})
    torso = thickness - layer <= protrusion_mm
    footprint = without_ridges(fill_small_holes(~torso, pixel_mm), pixel_mm)
    columns = np.expand_dims(footprint, axis)
    keep = mask & columns
    away = mask & ~columns
    if not away.any():
        return TorsoCut(mask, np.zeros_like(mask), {})
    cut_face = keep & ndimage.binary_dilation(away)
    voxel_ml = float(np.prod(spacing)) / 1000.0
    return TorsoCut(keep, cut_face, {"torso_cut_ml": round(float(away.sum()) * voxel_ml, 1)})


def fill_small_holes(footprint: np.ndarray, pixel_mm: np.ndarray) -> np.ndarray:
    """``footprint`` (2D bool) with its holes under :data:`MAX_HOLE_MM2` filled (spots inside
    a breast that stand less off the layer); larger enclosed regions stay (a torso layer that
    the thin edges of a body in air enclose)."""
    holes, n = ndimage.label(ndimage.binary_fill_holes(footprint) & ~footprint)
    if n == 0:
        return footprint
    area = np.bincount(holes.ravel())[1:] * float(np.prod(pixel_mm))
    small = np.flatnonzero(area < MAX_HOLE_MM2) + 1
    return footprint | np.isin(holes, small)


def without_ridges(footprint: np.ndarray, pixel_mm: np.ndarray) -> np.ndarray:
    """``footprint`` (2D bool) opened by a disc of :data:`RIDGE_MM` diameter: strips narrower
    than that (the axillary and pectoral folds, ridges of the torso) leave it."""
    radii = [0.5 * RIDGE_MM / p for p in pixel_mm]
    return ndimage.binary_opening(footprint, structure=_disc_footprint(radii))


def back_voxels(mask: np.ndarray, axis: int, sign: float) -> np.ndarray:
    """(xyz bool) The most posterior voxel of ``mask`` in each column along ``axis`` (``sign``
    +1: a larger index is anterior): the breast's back, against the chest."""
    posterior_first = mask if sign > 0 else np.flip(mask, axis)
    first = np.argmax(posterior_first, axis=axis)
    back = np.zeros_like(mask)
    has = posterior_first.any(axis=axis)
    np.put_along_axis(back, np.expand_dims(first, axis), np.expand_dims(has, axis), axis=axis)
    return back if sign > 0 else np.flip(back, axis)
