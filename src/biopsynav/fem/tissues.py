"""Tissue labels to materials: which tissue each label value is, and each cell's mixture.

A label value (any integer) takes its tissue from ``[anatomy] tissue_labels`` (keyed by the
value or by its segment name), else from its segment's name (:data:`TISSUE_NAMES`), else
'lesion' when it is a lesion label; any other label is refused at ``init``. A cell holding
several tissues gets the volume-weighted (Voigt) mixture of their Lame constants, which is
the mixture of their strain energies under the cell's one deformation; the share of a cell
that carries no label is ``[material] default_tissue``.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from ..anatomy.labelmap import label_value
from ..errors import InputError
from ..layout import CASE_FILE
from ..materials import MATERIAL_LAWS

if TYPE_CHECKING:
    from ..anatomy.model import Anatomy
    from ..config import CaseConfig

TISSUE_NAMES = {"fat": "fat", "adipose": "fat", "gland": "gland", "glandular": "gland",
                "fibroglandular": "gland", "skin": "skin", "lesion": "lesion",
                "tumor": "lesion", "tumour": "lesion", "mass": "lesion"}


def label_tissues(values: np.ndarray, cfg: CaseConfig, anatomy: Anatomy,
                  where: str = CASE_FILE) -> list[str]:
    """Tissue name of each label value of ``values`` (k,); InputError naming every label that
    has none, reported against ``where`` (the file the labels came from at ``init``)."""
    names = {v: n for n, v in anatomy.segments.items()}
    lesion_values = {label_value(item, anatomy.segments) for item in cfg.anatomy.lesion_labels}
    tissues, unmapped = [], []
    for value in (int(v) for v in values):
        tissue = _tissue_of(value, names.get(value, ""), value in lesion_values, cfg)
        tissues.append(tissue)
        if tissue is None:
            unmapped.append(f"{value} ({names[value]})" if value in names else str(value))
    if unmapped:
        raise InputError(f"the anatomy has tissue labels {', '.join(unmapped)} with no tissue: "
                         "map them in [anatomy] tissue_labels (init --tissue-labels "
                         f"{','.join(f'{u.split()[0]}=fat' for u in unmapped)}, for example)",
                         where)
    return tissues  # type: ignore[return-value]


def _tissue_of(value: int, segment: str, is_lesion: bool, cfg: CaseConfig) -> str | None:
    given = cfg.anatomy.tissue_labels
    tissues = cfg.material.tissues
    if str(value) in given:
        return given[str(value)]
    if segment and segment in given:
        return given[segment]
    by_name = TISSUE_NAMES.get(segment.strip().lower())
    if by_name in tissues:
        return by_name
    return "lesion" if is_lesion and "lesion" in tissues else None


def cell_lame(share: np.ndarray, tissues: list[str], cfg: CaseConfig
              ) -> tuple[np.ndarray, np.ndarray]:
    """Lame constants (mu, lambda) (n,) in MPa of cells with label shares ``share`` (n, k)
    whose columns are the tissues ``tissues`` (k,); the unlabelled rest is the default
    tissue."""
    law = MATERIAL_LAWS[cfg.material.model]
    names = [*tissues, cfg.material.default_tissue]
    params = {key: np.array([cfg.material.tissues[n][key] for n in names], np.float64)
              for key in law.parameters}
    mu_t, lam_t = law.lame(params)
    share = np.asarray(share, np.float64).reshape(len(share), len(tissues))
    weights = np.hstack([share, np.clip(1.0 - share.sum(axis=1, keepdims=True), 0.0, 1.0)])
    return weights @ mu_t, weights @ lam_t


def grid_lame(grid, cfg: CaseConfig, anatomy: Anatomy) -> tuple[np.ndarray, np.ndarray]:
    """Lame constants (mu, lambda) (n_active_cells,) in MPa of the active cells of ``grid``,
    each the volume-weighted mixture of its tissues (``cfg``'s materials, ``anatomy``'s
    segments)."""
    tissues = label_tissues(grid.label_values, cfg, anatomy)
    return cell_lame(grid.active_label_share(), tissues, cfg)


def small_strain(mu: np.ndarray, lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Young's modulus (MPa) and Poisson ratio of Lame constants (mu, lambda) in MPa."""
    return mu * (3.0 * lam + 2.0 * mu) / (lam + mu), lam / (2.0 * (lam + mu))
