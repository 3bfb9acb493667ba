"""The paper's Table 2 layout: target registration errors binned by probe displacement.

Bins (mm of probe displacement from the rest pose, the paper's section 3.2): D10 below 12.5,
D15 [12.5, 17.5), D20 [17.5, 22.5), D25 [22.5, 27.5), D30 from 27.5 up. Rows are lesions,
columns bins; a cell is the mean TRE of the pushes of that lesion in that bin; each row and
each column carries the mean and the (population, ddof = 0, as the paper's figures) standard
deviation of its non-empty cells. Empty cells print as ``-``.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass

import numpy as np

BIN_NAMES: tuple[str, ...] = ("D10", "D15", "D20", "D25", "D30")
BIN_EDGES_MM: tuple[float, ...] = (12.5, 17.5, 22.5, 27.5)
#: Pseudo-method of Table 2: distance between the network's and the FE model's lesion centres
#: (same grid, same pose): how closely the network reproduces the model it was trained on.
AGREEMENT = "net_vs_fem"
METHOD_TITLES = {"net": "U-Net (network)", "fem": "FE model, training resolution",
                 "rigid": "Rigid (lesions do not move)",
                 AGREEMENT: "Network against the FE model of the training grid (distance "
                            "between their lesion centres, not a TRE)"}
EMPTY = "-"


def bin_index(displacement_mm: np.ndarray | float) -> np.ndarray:
    """Bin index (0 for D10 ... 4 for D30) of probe displacements in mm (any shape)."""
    return np.digitize(np.asarray(displacement_mm, dtype=np.float64), BIN_EDGES_MM)


def bin_name(displacement_mm: float) -> str:
    """Name of the bin (``"D10"`` ... ``"D30"``) of one probe displacement in mm."""
    return BIN_NAMES[int(bin_index(displacement_mm))]


@dataclass
class Record:
    """One lesion, one push, one method.

    ``tre_mm`` is None when the method (or the ground truth) gave no trustworthy position;
    ``reason`` then says why (solver failure, tracker status). ``bound_mm``: the tracker's
    95 % bound of that lesion (:mod:`biopsynav.tracker.bound`), where it gave one.
    """

    lesion: int
    push: int
    displacement_mm: float
    bin: str
    method: str
    tre_mm: float | None
    status: str = "ok"
    reason: str = ""
    time_ms: float | None = None
    frame: int | None = None  # measured data: the poses CSV frame
    sequence: str = ""  # measured data: the poses CSV sequence
    bound_mm: float | None = None

    def to_dict(self) -> dict:
        return asdict(self)


@dataclass
class Table:
    """Aggregated Table 2 of one method (mm); None marks an empty cell or statistic."""

    method: str
    lesions: list[int]
    cells: np.ndarray  # (n_lesions, 5) mean TRE per lesion and bin, NaN when empty
    counts: np.ndarray  # (n_lesions, 5) number of pushes averaged per cell

    def row_stats(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-lesion mean and std (n_lesions,) over non-empty cells (NaN if all empty)."""
        return _nan_stats(self.cells, axis=1)

    def col_stats(self) -> tuple[np.ndarray, np.ndarray]:
        """Per-bin mean and std (5,) over lesions with a value (NaN if none)."""
        return _nan_stats(self.cells, axis=0)

    def overall_mean(self) -> float | None:
        """Mean of all non-empty cells (the paper's 'average TRE for all tumors and all
        deformations')."""
        vals = self.cells[np.isfinite(self.cells)]
        return float(vals.mean()) if vals.size else None

    def to_dict(self) -> dict:
        rmean, rstd = self.row_stats()
        cmean, cstd = self.col_stats()
        return {
            "method": self.method,
            "title": METHOD_TITLES.get(self.method, self.method),
            "bins": list(BIN_NAMES),
            "rows": [{"lesion": lid, "cells": _none_list(self.cells[i]),
                      "counts": self.counts[i].astype(int).tolist(),
                      "mean": _none(rmean[i]), "std": _none(rstd[i])}
                     for i, lid in enumerate(self.lesions)],
            "col_mean": _none_list(cmean), "col_std": _none_list(cstd),
            "overall_mean": self.overall_mean(),
            "max_row_mean": _none(np.nanmax(rmean)) if np.isfinite(rmean).any() else None,
        }


def aggregate(records: Iterable[Record], method: str, lesions: Sequence[int]) -> Table:
    """Table of ``method`` from the records (those with ``tre_mm`` None are left out)."""
    row_of = {lid: i for i, lid in enumerate(lesions)}
    sums = np.zeros((len(lesions), len(BIN_NAMES)))
    counts = np.zeros_like(sums)
    for r in records:
        if r.method != method or r.tre_mm is None or r.lesion not in row_of:
            continue
        i, j = row_of[r.lesion], BIN_NAMES.index(r.bin)
        sums[i, j] += r.tre_mm
        counts[i, j] += 1
    with np.errstate(invalid="ignore", divide="ignore"):
        cells = np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)
    return Table(method, list(lesions), cells, counts)


def format_text(table: Table, title: str | None = None, digits: int = 3) -> str:
    """The table as aligned plain text (mm), '-' where empty."""
    header, body, footer = _table_strings(table, digits)
    widths = [max(len(row[c]) for row in [header, *body, *footer]) for c in range(len(header))]
    lines = [title or METHOD_TITLES.get(table.method, table.method)]
    for row in [header, *body, *footer]:
        lines.append("  ".join(cell.rjust(w) for cell, w in zip(row, widths, strict=True)))
        if row is header:
            lines.append("  ".join("-" * w for w in widths))
    return "\n".join(lines)


def format_markdown(table: Table, digits: int = 3) -> str:
    """The table as a GitHub-flavoured Markdown table (mm), '-' where empty."""
    header, body, footer = _table_strings(table, digits)
    lines = ["| " + " | ".join(header) + " |", "|" + "---:|" * len(header)]
    lines += ["| " + " | ".join(row) + " |" for row in [*body, *footer]]
    return "\n".join(lines)


def table_from_dict(d: dict) -> Table:
    """Inverse of :meth:`Table.to_dict` (for tables read back from ``table2.json``)."""
    cells = np.array([[np.nan if v is None else v for v in r["cells"]] for r in d["rows"]],
                     dtype=np.float64).reshape(-1, len(BIN_NAMES))
    counts = np.array([r.get("counts", [0] * len(BIN_NAMES)) for r in d["rows"]],
                      dtype=np.float64).reshape(-1, len(BIN_NAMES))
    return Table(d["method"], [r["lesion"] for r in d["rows"]], cells, counts)


def _table_strings(table: Table, digits: int) -> tuple[list[str], list[list[str]],
                                                        list[list[str]]]:
    rmean, rstd = table.row_stats()
    cmean, cstd = table.col_stats()
    header = ["Lesion", *BIN_NAMES, "Mean", "STD"]
    body = [[str(lid), *(_fmt(v, digits) for v in table.cells[i]), _fmt(rmean[i], digits),
             _fmt(rstd[i], digits)] for i, lid in enumerate(table.lesions)]
    footer = [["Mean", *(_fmt(v, digits) for v in cmean), "", ""],
              ["STD", *(_fmt(v, digits) for v in cstd), "", ""]]
    return header, body, footer


def _nan_stats(cells: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray]:
    ok = np.isfinite(cells)
    n = ok.sum(axis=axis)
    filled = np.where(ok, cells, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = filled.sum(axis=axis) / n
        dev = np.where(ok, cells - np.expand_dims(mean, axis), 0.0)
        std = np.sqrt((dev ** 2).sum(axis=axis) / n)
    return np.where(n > 0, mean, np.nan), np.where(n > 0, std, np.nan)


def _fmt(value: float, digits: int) -> str:
    return EMPTY if value is None or not np.isfinite(value) else f"{value:.{digits}f}"


def _none(value: float) -> float | None:
    return float(value) if value is not None and np.isfinite(value) else None


def _none_list(values: np.ndarray) -> list[float | None]:
    return [_none(v) for v in values]
