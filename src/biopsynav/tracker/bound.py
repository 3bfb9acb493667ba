"""Each lesion's 95 % error bound: how far from the answer the true position may lie.

``bound = c + |d| (a + b p)`` mm, with ``d`` the lesion's predicted displacement from rest
(mm) and ``p`` the probe's depth (mm: the mean displacement of the rest contact's points). A
lesion that moves further errs further, and the share of its motion that is missed grows with
the push. The coefficients are the 95 % quantile of the ``chain`` recipe's lesion errors
against the independent P2 truth, fitted on the UC Davis breast and checked on the phantom,
which took no part in the fit (``benchmarks/error_bound.py``, ``benchmarks/results/
error-bound.json``; docs/tracker.md, "Error bound"). The bound is of the deformation model
only: not of the image, the segmentation, the probe's calibration or its tracking. It holds
for untilted pushes of that recipe inside the training envelope (on the default ``pushes``
recipe's networks it covers 88 % of the phantom's truth errors and 91 % of UC Davis's,
docs/tracker.md "Error bound"); out of it the tracker answers no position at all.
"""

from __future__ import annotations

import numpy as np

#: (c mm, a, b per mm) of ``c + |d| (a + b p)``, as benchmarks/error_bound.py fitted them
COEFFICIENTS = (0.1491, 0.02824, 0.002883)


def error_bound_mm(displacement: np.ndarray, probe_depth_mm: float) -> np.ndarray:
    """The 95 % bound (n,) mm of lesions moved by ``displacement`` (n, 3) mm at a push of
    ``probe_depth_mm``; 0 for a lesion that has not moved (the rest pose)."""
    c, a, b = COEFFICIENTS
    size = np.linalg.norm(np.asarray(displacement, dtype=np.float64).reshape(-1, 3), axis=1)
    return np.where(size > 0.0, c + size * (a + b * max(float(probe_depth_mm), 0.0)), 0.0)
