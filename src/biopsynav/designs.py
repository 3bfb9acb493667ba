"""Designs of the training force patches: how their random numbers are drawn
(``[probe] train_design``).

A force patch's draw takes five uniform numbers in [0, 1): its centre among the eligible skin
vertices, its in-plane angle, its tilt axis, its tilt and its force (in that order,
:func:`biopsynav.probe.draw_push`). Registered in :data:`TRAIN_DESIGNS`
(:func:`register_design`):

* ``random`` (default): independent draws, the paper's protocol;
* ``sobol``: the first attempt of training patch ``k`` (its number among the data set's
  training force patches) takes point ``k`` of a scrambled Sobol sequence in five dimensions
  (``scipy.stats.qmc.Sobol``, scrambled from the data set's seed), so the training patches
  fill the joint space of place, angle, tilt and force evenly instead of in random clumps;
  the centre's number picks a vertex along a Hilbert curve through the eligible centres
  (:func:`hilbert_order`), so that numbers near each other are places near each other.
  Each patch is still drawn from the protocol's distribution (every centre, angle, tilt and
  force as likely as under ``random``); only their joint spread differs. Redraws (a
  patch with too few contact points, a failed or too-deep solve) are random, and held-out
  patches and rigid pushes always are.

Plain functions of numbers: no anatomy or configuration here (:mod:`biopsynav.probe` applies
them).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from functools import lru_cache

import numpy as np

#: The uniform numbers a force patch's draw takes (centre, angle, tilt axis, tilt, force)
DRAW_DIMENSIONS = 5
#: The stream that scrambles the Sobol sequence (``SeedSequence([seed, SOBOL_STREAM])``),
#: apart from every draw's own
SOBOL_STREAM = 17
#: Bits per axis of the Hilbert curve's grid (2^10 cells along the centres' longest extent)
HILBERT_BITS = 10


def random_design(seed: int, k: int) -> None:
    """The ``random`` design: no designed numbers (every draw from its own generator)."""
    return None


def sobol_design(seed: int, k: int) -> np.ndarray:
    """The ``sobol`` design: point ``k`` (0, 1, ...) of the scrambled Sobol sequence of
    ``seed``, (:data:`DRAW_DIMENSIONS`,) uniform numbers in [0, 1)."""
    m = max(10, int(k).bit_length())
    return sobol_points(int(seed), m)[int(k)]


@lru_cache(maxsize=4)
def sobol_points(seed: int, m: int) -> np.ndarray:
    """The first 2^m points of the scrambled Sobol sequence of ``seed``, (2^m, 5), read-only;
    a longer sequence begins with the same points."""
    from scipy.stats import qmc

    rng = np.random.default_rng(np.random.SeedSequence([int(seed), SOBOL_STREAM]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # balance warnings of partial sequences
        points = qmc.Sobol(d=DRAW_DIMENSIONS, scramble=True, rng=rng).random_base2(m)
    points.setflags(write=False)
    return points


#: name -> design(seed, k): the designed numbers of training force patch ``k``, or None
TRAIN_DESIGNS: dict[str, Callable[[int, int], np.ndarray | None]] = {}
DEFAULT_DESIGN = "random"


def register_design(name: str, design: Callable[[int, int], np.ndarray | None]) -> None:
    """Make ``name`` a ``[probe] train_design``: ``design(seed, k)`` returns the
    :data:`DRAW_DIMENSIONS` uniform numbers of training force patch ``k``'s first attempt,
    or None to draw it at random."""
    TRAIN_DESIGNS[name] = design


def design_names() -> tuple[str, ...]:
    """The registered designs: the allowed ``[probe] train_design``."""
    return tuple(TRAIN_DESIGNS)


register_design("random", random_design)
register_design("sobol", sobol_design)


def hilbert_keys(points: np.ndarray, bits: int = HILBERT_BITS) -> np.ndarray:
    """(n,) int64: each point's position along a 3D Hilbert curve through the cube that holds
    ``points`` (n, 3) mm, cut into 2^bits cells a side (Skilling's transpose algorithm,
    vectorised over the points). Cells next to each other along the curve share a face."""
    cells = quantised(np.asarray(points, dtype=float), bits)
    top = 1 << (bits - 1)
    q = top
    while q > 1:  # inverse undo of excess work (Skilling 2004, AxestoTranspose)
        low = q - 1
        for axis in range(3):
            on = (cells[:, axis] & q) != 0
            cells[on, 0] ^= low
            swap = (cells[~on, 0] ^ cells[~on, axis]) & low
            cells[~on, 0] ^= swap
            cells[~on, axis] ^= swap
        q >>= 1
    for axis in (1, 2):  # Gray encode
        cells[:, axis] ^= cells[:, axis - 1]
    flip = np.zeros(len(cells), dtype=np.int64)
    q = top
    while q > 1:
        flip[(cells[:, 2] & q) != 0] ^= q - 1
        q >>= 1
    cells ^= flip[:, None]
    return interleaved(cells, bits)


def quantised(points: np.ndarray, bits: int) -> np.ndarray:
    """(n, 3) int64 cell indices 0 .. 2^bits - 1 of ``points`` (n, 3) in the cube of their
    bounding box's longest side (the same scale along every axis)."""
    low = points.min(axis=0) if len(points) else np.zeros(3)
    side = float(np.ptp(points, axis=0).max()) if len(points) else 0.0
    scale = ((1 << bits) - 1) / side if side > 0 else 0.0
    return np.rint((points - low) * scale).astype(np.int64)


def interleaved(cells: np.ndarray, bits: int) -> np.ndarray:
    """(n,) int64 keys from the transposed Hilbert index ``cells`` (n, 3): bit ``b`` of axis
    0, 1, 2, from the most significant ``b`` down."""
    key = np.zeros(len(cells), dtype=np.int64)
    for b in range(bits - 1, -1, -1):
        for axis in range(3):
            key = (key << 1) | ((cells[:, axis] >> b) & 1)
    return key


def hilbert_order(points: np.ndarray) -> np.ndarray:
    """(n,) indices that sort ``points`` (n, 3) along the Hilbert curve
    (:func:`hilbert_keys`; ties by index)."""
    return np.argsort(hilbert_keys(points), kind="stable")


__all__ = ["DEFAULT_DESIGN", "DRAW_DIMENSIONS", "TRAIN_DESIGNS", "design_names",
           "hilbert_keys", "hilbert_order", "register_design", "sobol_design"]
