"""Label maps as clinicians have them: NRRD/NIfTI/MHA label images and 3D Slicer segmentations.

* Frames: ITK files store physical points in LPS; a case lives in RAS (3D Slicer's frame), so
  every point read here is converted (x and y negated) by :meth:`LabelImage.to_ras`.
* Labels: any integer value, negative included, or a segment name of a Slicer ``.seg.nrrd``
  (``Segment<i>_Name`` / ``Segment<i>_LabelValue``; several layers are merged when the
  segments do not overlap).
* The breast of a torso: a segmentation of the whole anterior torso (both breasts, the tissue
  between, above and below them) is cut to the tissue that stands off the chest
  (:mod:`.torso`); a map of one breast alone is kept whole.
* One breast: several separate breasts (a bilateral image) are told apart by ``side`` (the
  patient's left is RAS -x) or by the lesions they hold; one breast joined to the other across
  the sternum is cut at the narrowest sagittal slab between them.
* Chest labels (the pectoral muscle) are never breast tissue: the chest wall is their
  interface with the breast and the breast's back where the segmentation leaves the chest
  unlabelled.
* Surface: the breast mask (with what it encloses: a lesion not listed as breast tissue) is
  resampled to isotropic voxels, lightly smoothed, and triangulated by marching cubes; its
  volume is compared with the labelled volume.
* Crop faces (where the image cuts the breast) and the chest-wall interface with a muscle label
  are returned as point sets (mm, RAS) for the anatomy to mark surface vertices with.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy import ndimage

from ..config import AnatomySection, label_item
from ..errors import InputError
from ..grid.index import image_array_to_xyz
from .torso import anterior_axis, back_voxels, cut_torso

LPS_TO_RAS = np.array([-1.0, -1.0, 1.0])
MIN_COMPONENT_SHARE = 0.05  # components under this share of the largest are specks
MAX_VOLUME_MISMATCH = 0.10  # surface volume against labelled volume
MAX_SAMPLES = 400_000
#: a lesion label's component of at least this (mL; a 4.6 mm sphere) is a lesion, as is one
#: whose one-voxel erosion keeps MIN_LESION_CORE_VOXELS (:func:`kept_lesions`)
MIN_LESION_ML = 0.05
MIN_LESION_CORE_VOXELS = 3


@dataclass
class LabelImage:
    """An integer label image in (x, y, z) index order with its geometry (ITK's LPS)."""

    labels: np.ndarray
    origin: np.ndarray
    spacing: np.ndarray
    direction: np.ndarray
    segments: dict[str, int] = field(default_factory=dict)

    def to_ras(self, ijk: np.ndarray) -> np.ndarray:
        """RAS points (n, 3), mm, of continuous voxel indices ``ijk`` (n, 3)."""
        lps = self.origin + (np.asarray(ijk, np.float64) * self.spacing) @ self.direction.T
        return lps * LPS_TO_RAS

    def voxels_at(self, ras: np.ndarray | None) -> np.ndarray:
        """Mask (labels' shape) of the voxels that hold the points ``ras`` (n, 3) mm; points
        outside the image mark nothing."""
        mask = np.zeros(self.labels.shape, bool)
        if ras is None or len(ras) == 0:
            return mask
        lps = np.asarray(ras, np.float64).reshape(-1, 3) * LPS_TO_RAS
        ijk = np.rint(np.linalg.solve(self.direction, (lps - self.origin).T).T
                      / self.spacing).astype(np.int64)
        ok = ((ijk >= 0) & (ijk < np.array(self.labels.shape))).all(axis=1)
        mask[tuple(ijk[ok].T)] = True
        return mask

    @property
    def voxel_mm3(self) -> float:
        """Volume of one voxel, mm^3."""
        return float(np.prod(self.spacing))

    def ras_axis_signs(self) -> np.ndarray:
        """Change of RAS x (3,) per unit step of each index axis, mm."""
        return (self.direction * self.spacing[None, :])[0] * LPS_TO_RAS[0]


@dataclass
class LabelAnatomy:
    """What a label map gives the anatomy (mm, RAS)."""

    vertices: np.ndarray
    faces: np.ndarray
    label_points: np.ndarray
    label_values: np.ndarray
    lesion_masks: list[np.ndarray]
    crop_points: np.ndarray
    chest_points: np.ndarray
    image: LabelImage
    facts: dict


def read_label_image(path: Path) -> LabelImage:
    """Read a label image; InputError when it is not one (channels, fractions, unreadable)."""
    import SimpleITK as sitk

    try:
        image = sitk.ReadImage(str(path))
    except RuntimeError as exc:
        raise InputError(f"cannot read label map: {str(exc).strip().splitlines()[0]}",
                         str(path)) from None
    if image.GetDimension() != 3:
        raise InputError(f"not a label map: {image.GetDimension()} dimensions, expected 3",
                         str(path))
    segments, layers = slicer_segments(image)
    array = sitk.GetArrayFromImage(image)
    if image.GetNumberOfComponentsPerPixel() > 1:
        array = _merge_layers(array, layers, segments, path)
    labels = image_array_to_xyz(_integer_labels(array, path))
    return LabelImage(labels, np.array(image.GetOrigin(), np.float64),
                      np.array(image.GetSpacing(), np.float64),
                      np.array(image.GetDirection(), np.float64).reshape(3, 3), segments)


def slicer_segments(image) -> tuple[dict[str, int], dict[str, int]]:
    """Segment name -> label value and name -> layer of a Slicer ``.seg.nrrd`` (empty dicts
    for a plain label map)."""
    keys = set(image.GetMetaDataKeys())
    names, layers = {}, {}
    i = 0
    while f"Segment{i}_Name" in keys:
        name = image.GetMetaData(f"Segment{i}_Name").strip()
        names[name] = int(image.GetMetaData(f"Segment{i}_LabelValue")) \
            if f"Segment{i}_LabelValue" in keys else i + 1
        layers[name] = int(image.GetMetaData(f"Segment{i}_Layer")) \
            if f"Segment{i}_Layer" in keys else 0
        i += 1
    return names, layers


def _merge_layers(array: np.ndarray, layers: dict[str, int], segments: dict[str, int],
                  path: Path) -> np.ndarray:
    """One label array (z, y, x) from a multi-layer array (z, y, x, layers) of a Slicer
    segmentation whose segments do not overlap."""
    n = array.shape[-1]
    if not segments:
        raise InputError(f"not a label map: {n} channels per voxel (an RGB or vector image?)",
                         str(path))
    occupied = (array != 0).sum(axis=-1)
    if (occupied > 1).any():
        raise InputError(f"segments overlap in {int((occupied > 1).sum())} voxels ({n} "
                         "layers); in Slicer, make the segments exclusive (Segment Editor, "
                         "masking: overwrite all) and save again", str(path))
    merged = np.zeros(array.shape[:-1], np.int64)
    for name, value in segments.items():
        merged[array[..., layers[name]] == value] = value
    return merged


def _integer_labels(array: np.ndarray, path: Path) -> np.ndarray:
    if np.issubdtype(array.dtype, np.integer):
        return array.astype(np.int64)
    if not np.all(np.isfinite(array)) or np.any(np.mod(array, 1) != 0):
        raise InputError("not a label map: voxel values are not integers (an intensity "
                         "image?)", str(path))
    return array.astype(np.int64)


def resolve_labels(spec: list, image: LabelImage, option: str, path: Path) -> list[int]:
    """Label values of ``spec`` (integers or segment names), each present in the image."""
    values, present = _values_and_present(spec, image, option, path)
    for item, value in zip(spec, values, strict=True):
        if value not in present:
            raise InputError(f"label {item} is absent from the label map (present: "
                             f"{sorted(present)})", str(path))
    return values


def resolve_lesion_labels(spec: list, image: LabelImage, path: Path
                          ) -> tuple[list[int], list[str]]:
    """Label values of the lesion labels ``spec`` present in the image, and the items absent
    from it: a segmentation protocol names every lesion class (benign, malignant), and one
    patient need not have each. InputError when some are given and none is present."""
    values, present = _values_and_present(spec, image, "--lesion-labels", path)
    absent = [str(label_item(item)) for item, v in zip(spec, values, strict=True)
              if v not in present]
    if spec and len(absent) == len(spec):
        raise InputError(f"--lesion-labels: none of {', '.join(absent)} is in the label map "
                         f"(present: {sorted(present)})", str(path))
    return [v for v in values if v in present], absent


def _values_and_present(spec: list, image: LabelImage, option: str, path: Path
                        ) -> tuple[list[int], set[int]]:
    """The label value of each item of ``spec`` (InputError for a name that is no segment)
    and the set of values the image holds."""
    values = [_label_value(item, image.segments, option, path) for item in spec]
    return values, set(np.unique(image.labels).tolist())


def label_value(item: int | str, segments: dict[str, int]) -> int | None:
    """The label value of ``item``: an integer as it is, a segment name (any case) looked up
    in ``segments``; None for a name that is not a segment."""
    item = label_item(item)
    if isinstance(item, int):
        return item
    return {name.lower(): value for name, value in segments.items()}.get(item.lower())


def _label_value(item, segments: dict[str, int], option: str, path: Path) -> int:
    value = label_value(item, segments)
    if value is not None:
        return value
    text = str(item).strip()
    known = ", ".join(f"{n}={v}" for n, v in segments.items()) or "none: a plain label map"
    raise InputError(f"{option}: {text!r} is neither a label value nor a segment name "
                     f"(segments: {known})", str(path))


@dataclass
class BreastFinding:
    """How the breast of a torso segmentation is found (:mod:`.torso`; ``protrusion_mm`` 0
    turns the cut off), mm."""

    protrusion_mm: float = AnatomySection().breast_protrusion_mm
    torso_disc_mm: float = AnatomySection().torso_disc_mm


def read_label_anatomy(path: Path, breast: list, lesion: list, chest: list, side: str,
                       spacing_mm: float, smoothing_mm: float,
                       lesion_centres: np.ndarray | None = None,
                       finding: BreastFinding | None = None) -> LabelAnatomy:
    """The breast of a label map: surface, label samples, lesion masks, crop and chest-wall
    points (mm, RAS), and facts for ``info``. The lesion labels' voxels and the voxels at
    ``lesion_centres`` (n, 3) mm RAS tell which breast holds the lesions. Voxels of the chest
    labels are never breast, even where the breast's tissue encloses them."""
    finding = finding or BreastFinding()
    image = read_label_image(path)
    if not breast:
        raise InputError("a label map needs --breast-labels (label values or segment names of "
                         "breast tissue)", str(path))
    breast_v = resolve_labels(breast, image, "--breast-labels", path)
    lesion_v, lesion_absent = resolve_lesion_labels(lesion, image, path)
    chest_v = resolve_labels(chest, image, "--chest-labels", path)
    chest_mask = np.isin(image.labels, chest_v)
    mask = np.isin(image.labels, breast_v + lesion_v) & ~chest_mask
    found = kept_lesions(image.labels, lesion_v, image.voxel_mm3)
    held = lesion_voxels(found, image.labels.shape) | image.voxels_at(lesion_centres)
    kept, torso_cut, facts = cut_torso_tissue(mask, image, finding)
    away = mask & ~kept
    mask, cut, picked = select_breast(kept, held, side, image, path)
    facts.update(picked)
    if lesion_absent:
        facts["lesion_labels_absent"] = lesion_absent
    if away.any():
        facts["torso_cut_where"] = cut_directions(away, mask, image)
    cut = cut | (torso_cut & mask)
    labelled = mask
    mask = ndimage.binary_fill_holes(mask) & ~chest_mask  # other labels the breast encloses
    vertices, faces = smooth_surface(mask, image, spacing_mm, smoothing_mm)
    facts.update(volume_facts(mask, vertices, faces, image, path))
    sampled = mask & ~unlabelled_holes(labelled, mask, image.labels, breast_v + lesion_v)
    facts["unlabelled_holes_voxels"] = int(mask.sum() - sampled.sum())
    ijk = np.argwhere(sampled)[:: max(1, int(sampled.sum()) // MAX_SAMPLES)]
    lesions, facts["lesion_specks_left_out"] = lesion_masks(found, mask)
    return LabelAnatomy(vertices, faces, image.to_ras(ijk),
                        image.labels[tuple(ijk.T)].astype(np.int32), lesions,
                        image.to_ras(crop_voxels(mask, cut)), chest_interface(
                            mask, image, chest_v, path, cut), image, facts)


def cut_torso_tissue(mask: np.ndarray, image: LabelImage, finding: BreastFinding
                     ) -> tuple[np.ndarray, np.ndarray, dict]:
    """The breasts of a torso segmentation's tissue ``mask`` (xyz bool), the faces where the
    torso was cut from them, and the volume cut away (:func:`.torso.cut_torso`)."""
    if finding.protrusion_mm <= 0:
        return mask, np.zeros_like(mask), {}
    got = cut_torso(mask, image.spacing, image.direction, finding.protrusion_mm,
                    finding.torso_disc_mm)
    return got.keep, got.cut_face, got.facts


def cut_directions(away: np.ndarray, kept: np.ndarray, image: LabelImage) -> dict[str, float]:
    """Shares (summing to 1) of the tissue ``away`` (xyz bool) that lay above, below, to the
    patient's left or right of the breast ``kept`` (RAS bounding box), or around it."""
    ras_away = image.to_ras(np.argwhere(away)[::20])
    ras_kept = image.to_ras(np.argwhere(kept)[::20])
    lo, hi = ras_kept.min(axis=0), ras_kept.max(axis=0)
    x, z = ras_away[:, 0], ras_away[:, 2]
    above, below = z > hi[2], z < lo[2]
    level = ~above & ~below
    left, right = level & (x < lo[0]), level & (x > hi[0])  # the patient's left is RAS -x
    shares = {"superior": above, "inferior": below, "patient's left": left,
              "patient's right": right, "around": level & ~left & ~right}
    return {k: round(float(np.mean(v)), 3) for k, v in shares.items() if len(v)}


def unlabelled_holes(labelled: np.ndarray, filled: np.ndarray, labels: np.ndarray,
                     listed: list[int]) -> np.ndarray:
    """Background voxels (label 0, when 0 is not a listed label) that the breast encloses:
    gaps in a segmentation. They are inside the breast but carry no tissue; the grid gives
    them the tissue of the nearest labelled voxel."""
    if 0 in listed:
        return np.zeros_like(filled)
    return filled & ~labelled & (labels == 0)


def select_breast(mask: np.ndarray, lesion_mask: np.ndarray, side: str, image: LabelImage,
                  path: Path) -> tuple[np.ndarray, np.ndarray, dict]:
    """The one breast of ``mask`` (xyz bool), the voxels of a midline cut made to free it, and
    what was chosen."""
    comps, n = ndimage.label(mask)
    sizes = np.bincount(comps.ravel(), minlength=n + 1)[1:]
    keep = [c + 1 for c in np.flatnonzero(sizes >= MIN_COMPONENT_SHARE * sizes.max())]
    centres = [image.to_ras(np.argwhere(comps == c).mean(axis=0)[None])[0] for c in keep]
    no_cut = np.zeros_like(mask)
    if len(keep) == 1:
        if side:
            return _cut_at_midline(comps == keep[0], side, image)
        return _joined_breast(comps == keep[0], lesion_mask, image, path)
    if side:
        x = [c[0] for c in centres]
        pick = keep[int(np.argmin(x) if side == "left" else np.argmax(x))]
        return comps == pick, no_cut, {"breast": f"the patient's {side} one of {len(keep)} "
                                                f"breasts (--side {side})"}
    holding = [c for c in keep if (lesion_mask & (comps == c)).any()]
    if len(holding) == 1:
        side_of = _side_among([c[0] for c in centres], keep.index(holding[0]))
        return comps == holding[0], no_cut, {"breast": f"the {side_of}one of {len(keep)} "
                                                       "breasts, the one holding the lesions"}
    where = "; ".join(f"{int(sizes[c - 1] * image.voxel_mm3 / 1000)} mL at RAS "
                      f"{np.round(p, 1).tolist()}" for c, p in zip(keep, centres, strict=True))
    lesions = (f"lesions in {len(holding)} of them" if holding else
               "no lesion in any" if lesion_mask.any() else "no lesion given to choose by")
    raise InputError(f"the label map holds {len(keep)} separate breasts ({where}), {lesions}; "
                     "give --side left or --side right", str(path))


def _side_among(ras_x: list[float], index: int) -> str:
    """``"patient's left "`` or ``"patient's right "`` for the breast ``index`` of those whose
    centres lie at RAS ``ras_x`` (mm) when it is the furthest to that side, else ``""``."""
    if ras_x[index] == max(ras_x):
        return "patient's right "
    if ras_x[index] == min(ras_x):
        return "patient's left "
    return ""


def _cut_at_midline(mask: np.ndarray, side: str, image: LabelImage
                    ) -> tuple[np.ndarray, np.ndarray, dict]:
    """The ``--side`` breast of a mask that joins both across the sternum
    (:func:`_midline_halves`), or the mask as it is when it has one lobe."""
    halves = _midline_halves(mask, image)
    if halves is None:
        return mask, np.zeros_like(mask), {"breast": "the only breast"}
    return _take_half(mask, halves[side], side, f"--side {side}")


def _take_half(mask: np.ndarray, half: np.ndarray, side: str, why: str
               ) -> tuple[np.ndarray, np.ndarray, dict]:
    """The largest piece of ``mask`` in the patient's ``side`` ``half`` (xyz bool), the face
    where it was cut from the rest, and what was chosen (``why``)."""
    keep = _largest_component(mask & half)
    cut_face = keep & ndimage.binary_dilation(mask & ~keep)
    return keep, cut_face, {"breast": f"the patient's {side} breast, cut from the other at the "
                                      f"midline ({why})"}


def _midline_halves(mask: np.ndarray, image: LabelImage) -> dict[str, np.ndarray] | None:
    """The patient's left and right of a mask (xyz bool) whose tissue has two lobes along
    the index axis nearest RAS x, split at the thinnest sagittal slab between them; None for
    one lobe."""
    signs = image.ras_axis_signs()
    axis = int(np.argmax(np.abs(signs)))
    profile = mask.sum(axis=tuple(a for a in range(3) if a != axis)).astype(np.float64)
    cut = _valley(profile)
    if cut is None:
        return None
    index = np.arange(mask.shape[axis]).reshape([-1 if a == axis else 1 for a in range(3)])
    lower, upper = index < cut, index > cut
    if signs[axis] < 0:  # a larger index is further to the patient's left (RAS -x)
        lower, upper = upper, lower
    return {"left": lower, "right": upper}


def _joined_breast(mask: np.ndarray, lesion_mask: np.ndarray, image: LabelImage, path: Path
                   ) -> tuple[np.ndarray, np.ndarray, dict]:
    """The map's one component without ``--side``: the half of two lobes joined across the
    sternum that holds the lesions (cut at the midline), or the component when it has one
    lobe; InputError when the lesions do not choose a half."""
    halves = _midline_halves(mask, image)
    if halves is None:
        return mask, np.zeros_like(mask), {"breast": "the only breast"}
    holding = [side for side, half in halves.items() if (lesion_mask & mask & half).any()]
    if len(holding) != 1:
        lesions = "lesions in both" if holding else "no lesion in either"
        raise InputError(f"the label map's two breasts are joined across the sternum, "
                         f"{lesions}; give --side left or --side right", str(path))
    side = holding[0]
    return _take_half(mask, halves[side], side, "the one holding the lesions")


def _valley(profile: np.ndarray) -> int | None:
    """Index of a clear valley in a two-lobed profile (under half of both lobes), or None."""
    nz = np.flatnonzero(profile)
    if len(nz) < 6:
        return None
    lo, hi = nz[0], nz[-1]
    inner = np.arange(lo + (hi - lo) // 4, hi - (hi - lo) // 4 + 1)
    v = int(inner[np.argmin(profile[inner])])
    if profile[v] < 0.5 * min(profile[lo:v].max(), profile[v + 1:hi + 1].max()):
        return v
    return None


def _largest_component(mask: np.ndarray) -> np.ndarray:
    comps, n = ndimage.label(mask)
    if n <= 1:
        return mask
    return comps == 1 + int(np.argmax(np.bincount(comps.ravel())[1:]))


def crop_voxels(mask: np.ndarray, cut: np.ndarray) -> np.ndarray:
    """Indices (n, 3) of breast voxels where the image or a midline cut ends the breast."""
    border = np.zeros_like(mask)
    for axis in range(3):
        for end in (0, -1):
            index = [slice(None)] * 3
            index[axis] = end
            border[tuple(index)] = True
    return np.argwhere((mask & border) | cut)


def chest_interface(mask: np.ndarray, image: LabelImage, chest: list[int],
                    path: Path, cut: np.ndarray | None = None) -> np.ndarray:
    """RAS points (n, 3) of the fixed wall: breast voxels touching a chest label (muscle), and
    the breast's back (the most posterior voxel of each column, :func:`.torso.back_voxels`)
    off the cut faces ``cut`` (xyz bool), where a segmentation leaves the chest behind the
    breast unlabelled; none without chest labels."""
    if not chest:
        return np.zeros((0, 3))
    touching = mask & ndimage.binary_dilation(np.isin(image.labels, chest))
    if not touching.any():
        raise InputError(f"the chest labels {chest} do not touch the breast tissue; check "
                         "--chest-labels", str(path))
    axis, sign = anterior_axis(image.direction)
    back = back_voxels(mask, axis, sign) & ~(cut if cut is not None else False)
    return image.to_ras(np.argwhere(touching | back))


def smooth_surface(mask: np.ndarray, image: LabelImage, spacing_mm: float,
                   smoothing_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Marching-cubes surface (RAS vertices, faces) of ``mask`` resampled to isotropic voxels
    of ``spacing_mm`` (0: the finest spacing of the image) and smoothed by a Gaussian of
    ``smoothing_mm`` (standard deviation)."""
    from skimage.measure import marching_cubes

    occupied = np.argwhere(mask)
    lo = np.maximum(occupied.min(axis=0) - 2, 0)
    hi = occupied.max(axis=0) + 3
    box = mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].astype(np.float32)
    iso = spacing_mm or float(image.spacing.min())
    step = iso / image.spacing  # index units per new voxel
    axes = [np.arange(-2.0, box.shape[a] + 1.0, step[a]) for a in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"))
    fine = ndimage.map_coordinates(box, grid, order=1, mode="constant", cval=0.0)
    if smoothing_mm > 0:
        fine = ndimage.gaussian_filter(fine, smoothing_mm / iso, mode="constant")
    verts, faces, _, _ = marching_cubes(fine, level=0.5)
    ijk = lo + np.array([-2.0, -2.0, -2.0]) + verts * step
    return image.to_ras(ijk), faces[:, ::-1].astype(np.int64)


def volume_facts(mask: np.ndarray, vertices: np.ndarray, faces: np.ndarray, image: LabelImage,
                 path: Path) -> dict:
    """The labelled and the surface volume (mL); InputError when they differ by more than
    :data:`MAX_VOLUME_MISMATCH`."""
    from .model import surface_volume

    labelled = float(mask.sum()) * image.voxel_mm3 / 1000.0
    surface = abs(surface_volume(vertices, faces)) / 1000.0
    if abs(surface - labelled) > MAX_VOLUME_MISMATCH * labelled:
        raise InputError(f"the breast surface encloses {surface:.1f} mL but its labels hold "
                         f"{labelled:.1f} mL; lower [anatomy] labelmap_smoothing_mm", str(path))
    return {"label_volume_ml": round(labelled, 3), "surface_volume_ml": round(surface, 3),
            "voxel_mm": np.round(image.spacing, 4).tolist()}


def lesion_voxels(found: list[tuple[np.ndarray, np.ndarray]], shape: tuple) -> np.ndarray:
    """The voxels (xyz bool, ``shape``) of the lesions ``found`` (:func:`kept_lesions`, over
    the whole map): the lesions that choose the breast, without the specks."""
    held = np.zeros(shape, bool)
    for _, kept in found:
        held |= kept
    return held


def kept_lesions(labels: np.ndarray, lesion: list[int], voxel_mm3: float
                 ) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per lesion label, (its voxels, the voxels of its lesions) (xyz bool each). A connected
    component is a lesion when it holds at least :data:`MIN_LESION_ML`, or when it is thicker
    than a sliver (a one-voxel erosion leaves :data:`MIN_LESION_CORE_VOXELS`), or when it is
    the map's largest lesion component; else a speck of segmentation noise. Over the 55 exams
    of the MRI collection the 83 lesions its README lists are lesions by this rule (the
    smallest 0.039-0.048 mL, cores of 5-6 voxels) and its 83 other components specks (up to
    0.040 mL, cores of 0-1 voxel; exam 10 has 44 beside its 5.6 mL tumour)."""
    found = []
    for value in lesion:
        voxels = labels == value
        comps, n = ndimage.label(voxels)
        sizes = np.bincount(comps.ravel(), minlength=n + 1) * voxel_mm3 / 1000.0
        sizes[0] = 0.0
        found.append((voxels, comps, sizes, _core_voxels(comps, n)))
    largest = max((float(sizes.max()) for _, _, sizes, _ in found), default=0.0)
    return [(voxels, (((sizes >= MIN_LESION_ML) | (core >= MIN_LESION_CORE_VOXELS)
                       | (sizes == largest)) & (sizes > 0.0))[comps])
            for voxels, comps, sizes, core in found]


def _core_voxels(comps: np.ndarray, n: int) -> np.ndarray:
    """(n + 1,) int: how many voxels of each labelled component of ``comps`` a one-voxel
    erosion keeps (each eroded within its own bounding box; index 0 unused)."""
    core = np.zeros(n + 1, np.int64)
    for i, box in enumerate(ndimage.find_objects(comps), start=1):
        if box is not None:
            core[i] = ndimage.binary_erosion(comps[box] == i).sum()
    return core


def lesion_masks(found: list[tuple[np.ndarray, np.ndarray]], breast: np.ndarray
                 ) -> tuple[list[np.ndarray], int]:
    """One mask per connected component, inside the chosen ``breast`` (xyz bool), of the
    lesions ``found`` (:func:`kept_lesions`), and the number of specks left out inside it."""
    masks, specks = [], 0
    for voxels, kept in found:
        comps, n = ndimage.label(kept & breast)
        masks += [comps == c + 1 for c in range(n)]
        specks += ndimage.label(voxels & ~kept & breast)[1]
    return masks, specks
