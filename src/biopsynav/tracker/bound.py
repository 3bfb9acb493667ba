"""Each lesion's 95 % error bound: how far from the answer the true position may lie.

``bound = c + |d| (a + b p + k r + k_t g)`` mm, with ``d`` the lesion's predicted displacement
from rest (mm), ``p`` the probe's depth (mm: the mean displacement of the rest contact's
points), ``r`` the lesion's *relative miss* at that depth: the share of its motion the network
missed against its own FE teacher in the lesion's self-check (``biopsynav evaluate``;
:mod:`biopsynav.evaluate.lesion_check`, interpolated between the check's depths and held
beyond them), and ``g`` the lesion's *teacher gap*: the share of its motion by which the
teacher moves it otherwise on a grid finer by
:data:`~biopsynav.evaluate.lesion_check.TEACHER_CHECK_REFINEMENT` (one push of the check). A
lesion that moves further errs further, the share of its motion that is missed grows with the
push (the teacher's contact error, docs/fem.md "Limits"), a lesion the network learnt badly
from its teacher errs further still, and so does one whose teacher is far from converged
there. ``k`` is :data:`CHECK_WEIGHT`, ``k_t`` :data:`TEACHER_WEIGHT`.

Both coefficient sets are the 95 % quantile of tracking networks' lesion errors against the
independent P2 truth, fitted on the UC Davis breast and checked on the phantom, which took no
part in the fit (``benchmarks/error_bound.py``, ``benchmarks/results/error-bound.json``;
docs/tracker.md, "Error bound"). A model without a current self-check (trained again since,
or never evaluated) is bounded by :data:`UNCHECKED_COEFFICIENTS`, fitted on the same errors
without either term (also for a lesion whose check lacks one). The bound is of the
deformation model only: not of the image, the segmentation, the probe's calibration or its
tracking; out of the training envelope the tracker answers no position at all.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..layout import LESION_CHECK

#: (c mm, a, b per mm) with the self-check's terms, as benchmarks/error_bound.py fitted them
COEFFICIENTS = (0.03065, 0.0200, 0.00200)
#: (c mm, a, b per mm) of a model without a current self-check (the same fit, k = k_t = 0)
UNCHECKED_COEFFICIENTS = (0.1038, 0.0025, 0.00400)
#: k: the weight of the self-check's relative miss (benchmarks/error_bound.py --weight)
CHECK_WEIGHT = 0.5
#: k_t: the weight of the teacher gap (benchmarks/error_bound.py --teacher-weight)
TEACHER_WEIGHT = 0.5
#: the layout of lesion_check.json this module reads (2: with each lesion's teacher gap)
CHECK_FORMAT = 2


def error_bound_mm(displacement: np.ndarray, probe_depth_mm: float,
                   relative_miss: np.ndarray | None = None,
                   teacher_gap: np.ndarray | None = None) -> np.ndarray:
    """The 95 % bound (n,) mm of lesions moved by ``displacement`` (n, 3) mm at a push of
    ``probe_depth_mm``, each with its self-check's ``relative_miss`` (n,) at that depth and
    ``teacher_gap`` (n,) (NaN or None in either: no check, :data:`UNCHECKED_COEFFICIENTS`);
    0 for a lesion that has not moved (the rest pose)."""
    size = np.linalg.norm(np.asarray(displacement, dtype=np.float64).reshape(-1, 3), axis=1)
    p = max(float(probe_depth_mm), 0.0)
    miss, gap = (np.full(len(size), np.nan) if x is None
                 else np.asarray(x, dtype=np.float64).reshape(-1)
                 for x in (relative_miss, teacher_gap))
    checked = np.isfinite(miss) & np.isfinite(gap)
    c, a, b = np.where(checked[:, None], COEFFICIENTS, UNCHECKED_COEFFICIENTS).T
    terms = np.where(checked, CHECK_WEIGHT * miss + TEACHER_WEIGHT * gap, 0.0)
    bound = c + size * (a + b * p + terms)
    return np.where(size > 0.0, bound, 0.0)


@dataclass(frozen=True)
class LesionCheck:
    """A model's lesion self-check, read from its folder: ``depths_mm`` (m,), each lesion's
    relative miss ``relative`` (n_lesions, m) at them and its ``teacher_gap`` (n_lesions,), in
    the tracker's lesion order; a depth neither engine answered is filled from the lesion's
    others, a lesion with none, or without a teacher gap, is NaN there."""

    depths_mm: np.ndarray
    relative: np.ndarray
    teacher_gap: np.ndarray

    @staticmethod
    def checksum_of(meta: dict) -> str:
        """The model identity a check is bound to: its ``meta.json`` checksum."""
        from ..inference.model_files import meta_checksum

        return meta_checksum(meta)

    @classmethod
    def load(cls, model_dir: Path, meta: dict, lesion_ids: list[int]) -> LesionCheck | None:
        """The check of the model in ``model_dir`` (``meta``: its meta.json) for the lesions
        ``lesion_ids``; None when there is none, it is of another model (trained again since),
        of another layout or unreadable (the tracker then says its bounds lack it)."""
        try:
            data = json.loads((Path(model_dir) / LESION_CHECK).read_text())
            if data.get("format") != CHECK_FORMAT \
                    or data.get("model_checksum") != cls.checksum_of(meta):
                return None
            depths = np.asarray(data["depths_mm"], dtype=np.float64).reshape(-1)
            lesions = [data["lesions"].get(str(i), {}) for i in lesion_ids]
            rows = [filled(depths, lesion.get("relative")) for lesion in lesions]
            gaps = np.array([gap_or_nan(lesion.get("teacher_gap")) for lesion in lesions],
                            dtype=np.float64)
        except (OSError, ValueError, TypeError, KeyError, AttributeError):
            return None
        if len(depths) == 0 or np.any(np.diff(depths) <= 0):
            return None
        return cls(depths, np.array(rows, dtype=np.float64).reshape(len(lesion_ids),
                                                                    len(depths)), gaps)

    def relative_at(self, probe_depth_mm: float) -> np.ndarray:
        """Each lesion's relative miss (n_lesions,) at ``probe_depth_mm``: linear between the
        check's depths, held beyond them."""
        if len(self.depths_mm) == 1:
            return self.relative[:, 0]
        p = float(np.clip(probe_depth_mm, self.depths_mm[0], self.depths_mm[-1]))
        hi = int(np.clip(np.searchsorted(self.depths_mm, p), 1, len(self.depths_mm) - 1))
        lo = hi - 1
        span = self.depths_mm[hi] - self.depths_mm[lo]
        w = 0.0 if span <= 0.0 else (p - self.depths_mm[lo]) / span
        return (1.0 - w) * self.relative[:, lo] + w * self.relative[:, hi]


def gap_or_nan(value: float | None) -> float:
    """A stored teacher gap as a float: NaN for None (the finer grid gave no answer) or a
    negative value."""
    gap = np.nan if value is None else float(value)
    return gap if gap >= 0.0 else np.nan


def basis_words(check: LesionCheck | None) -> str:
    """What a network's 95 % bounds rest on, in words: with or without its lesion check."""
    if check is None:
        return ("without the lesion self-check (none current or readable for this model: "
                "`biopsynav evaluate CASE` makes it), so a lesion the network learnt badly is "
                "not told apart")
    return ("widened by each lesion's self-check against the network's teacher and by the "
            "teacher's own gap to a finer grid")


def filled(depths: np.ndarray, relative: list | None) -> np.ndarray:
    """``relative`` (m,) at ``depths`` with unanswered depths (None) interpolated from the
    answered ones (held beyond them); all NaN when none was answered."""
    given = list(relative or [])[:len(depths)]
    values = np.array([np.nan if r is None else float(r) for r in given]
                      + [np.nan] * (len(depths) - len(given)), dtype=np.float64)
    ok = np.isfinite(values) & (values >= 0.0)
    if not ok.any():
        return np.full(len(depths), np.nan)
    return np.interp(depths, depths[ok], values[ok])
