"""Material laws: one registry (``register_material_law``), read by case.toml and the FE model.

Each tissue of ``[material.tissues]`` is a dict of the law's parameters (``E_mpa`` and ``nu``
for the laws registered here). A :class:`MaterialLaw` names those parameters with their open
ranges, turns per-element parameter arrays into the numba kernel's per-element Lame constants
(mu, lambda) in MPa, gives the small-strain (E, nu) that the linear-elastic baseline and the
contact compliance use, and names the kernel branch that evaluates it (the kernels keep their
branches: ``KERNEL_SVK``, ``KERNEL_NEO_HOOKEAN``, ``KERNEL_NEO_HOOKEAN_SRI``,
``KERNEL_NEO_HOOKEAN_SPLIT_SRI``, ``KERNEL_NEO_HOOKEAN_SPLIT_SRI_INNER``; a law with a new
energy adds one there).

Registered: ``neo-hookean`` (compressible, ``W = mu/2 (I1 - 3) - mu ln J + lam/2 (ln J)^2``),
``neo-hookean-sri`` (the same energy, its ``lam`` term integrated at the cell centre:
selective reduced integration, free of volumetric locking near nu = 0.5),
``neo-hookean-split-sri`` (the decoupled neo-Hookean ``mu/2 (J^-2/3 I1 - 3) + K/2 (ln J)^2``,
``K = lam + 2 mu / 3``, its volumetric term at the cell centre: the same small-strain
response as the others, and no cheap crushing of a cell's corner at constant cell volume),
``neo-hookean-split-sri-inner`` (that law in the cells wholly inside the tissue, the
compressible ``neo-hookean`` at 2x2x2 points in the cells the surface cuts, whose centre
and averaged gradients say little about their tissue) and ``svk``.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

KERNEL_SVK = 0
KERNEL_NEO_HOOKEAN = 1
KERNEL_NEO_HOOKEAN_SRI = 2
KERNEL_NEO_HOOKEAN_SPLIT_SRI = 3
KERNEL_NEO_HOOKEAN_SPLIT_SRI_INNER = 4

Arrays = dict[str, np.ndarray]


@dataclass(frozen=True)
class MaterialLaw:
    """``parameters``: name -> (low, high) open range; ``lame(params) -> (mu, lam)`` and
    ``small_strain(params) -> (E_mpa, nu)`` on per-element arrays (n_el,)."""

    name: str
    kernel: int
    parameters: dict[str, tuple[float, float]]
    lame: Callable[[Arrays], tuple[np.ndarray, np.ndarray]]
    small_strain: Callable[[Arrays], tuple[np.ndarray, np.ndarray]]

    def tissue_problem(self, tissue) -> str:
        """Why ``tissue`` (a case.toml dict) is not a valid parameter set, or ""."""
        if not isinstance(tissue, dict) or set(tissue) != set(self.parameters):
            return f"needs exactly {' and '.join(self.parameters)} (law {self.name!r})"
        for key, (lo, hi) in self.parameters.items():
            v = tissue[key]
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) \
                    or not lo < v < hi:
                return f"{key} must be in ({lo:g}, {hi:g}) (a number, not a boolean), got {v!r}"
        return ""


MATERIAL_LAWS: dict[str, MaterialLaw] = {}


def register_material_law(law: MaterialLaw) -> None:
    """Make ``law.name`` a ``[material] model``."""
    MATERIAL_LAWS[law.name] = law


def material_law_names() -> tuple[str, ...]:
    """The registered laws: the allowed ``[material] model`` values."""
    return tuple(MATERIAL_LAWS)


def lame_constants(e_mpa: np.ndarray, nu: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lame constants (mu, lambda) in MPa from Young's modulus (MPa) and Poisson ratio."""
    e_mpa = np.asarray(e_mpa, dtype=np.float64)
    nu = np.asarray(nu, dtype=np.float64)
    mu = e_mpa / (2.0 * (1.0 + nu))
    lam = e_mpa * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))
    return mu, lam


ELASTIC_PARAMETERS = {"E_mpa": (0.0, 1e3), "nu": (-1.0, 0.5)}


def _lame(p: Arrays) -> tuple[np.ndarray, np.ndarray]:
    return lame_constants(p["E_mpa"], p["nu"])


def _e_nu(p: Arrays) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(p["E_mpa"], dtype=np.float64), np.asarray(p["nu"], dtype=np.float64)


register_material_law(MaterialLaw("neo-hookean", KERNEL_NEO_HOOKEAN, ELASTIC_PARAMETERS,
                                  _lame, _e_nu))
register_material_law(MaterialLaw("neo-hookean-sri", KERNEL_NEO_HOOKEAN_SRI,
                                  ELASTIC_PARAMETERS, _lame, _e_nu))
register_material_law(MaterialLaw("neo-hookean-split-sri", KERNEL_NEO_HOOKEAN_SPLIT_SRI,
                                  ELASTIC_PARAMETERS, _lame, _e_nu))
register_material_law(MaterialLaw("neo-hookean-split-sri-inner",
                                  KERNEL_NEO_HOOKEAN_SPLIT_SRI_INNER, ELASTIC_PARAMETERS, _lame,
                                  _e_nu))
register_material_law(MaterialLaw("svk", KERNEL_SVK, ELASTIC_PARAMETERS, _lame, _e_nu))
