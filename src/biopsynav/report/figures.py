"""Figures the report makes itself (matplotlib, Agg): Table 2 summary and timing bars."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..evaluate.paper import PAPER_FE_MS, PAPER_FE_STD_MS, PAPER_TABLE1, PAPER_TABLE2_COL_MEAN
from ..evaluate.table import BIN_NAMES, METHOD_TITLES
from ..fileio import save_figure_atomic

COLORS = {"net": "tab:green", "fem": "tab:red", "rigid": "tab:gray"}


def _figure(size: tuple[float, float]):
    from matplotlib.figure import Figure

    return Figure(figsize=size)


def plot_table2(result: dict, path: Path) -> Path:
    """Two panels: column means (+- std) per bin and method with the paper's column means;
    histogram of all TREs per method. Saves a PNG at ``path``."""
    fig = _figure((12, 4.5))
    ax1, ax2 = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    methods = result["methods"]
    x = np.arange(len(BIN_NAMES))
    width = 0.8 / max(len(methods), 1)
    for k, m in enumerate(methods):
        t = result["tables"][m]
        mean = np.array([np.nan if v is None else v for v in t["col_mean"]])
        std = np.array([np.nan if v is None else v for v in t["col_std"]])
        ax1.bar(x + (k - (len(methods) - 1) / 2) * width, mean, width, yerr=std, capsize=3,
                color=COLORS.get(m), label=METHOD_TITLES.get(m, m))
        if m in PAPER_TABLE2_COL_MEAN:
            ax1.plot(x, PAPER_TABLE2_COL_MEAN[m], "o--", color=COLORS.get(m), mfc="white",
                     label=f"paper, {m} (phantom, US)")
    ax1.set_xticks(x, BIN_NAMES)
    ax1.set_ylabel("TRE (mm)")
    ax1.set_title("Table 2: mean TRE per probe displacement range")
    ax1.legend(fontsize=7)
    tres = {m: [r["tre_mm"] for r in result["records"]
                if r["method"] == m and r["tre_mm"] is not None] for m in methods}
    top = max((max(v) for v in tres.values() if v), default=1.0)
    bins = np.linspace(0.0, top * 1.05 + 1e-9, 25)
    for m in methods:
        if tres[m]:
            ax2.hist(tres[m], bins=bins, histtype="step", linewidth=2, color=COLORS.get(m),
                     label=f"{METHOD_TITLES.get(m, m)} (n={len(tres[m])})")
    ax2.set_xlabel("TRE (mm)")
    ax2.set_ylabel("pushes")
    ax2.set_title("TRE distribution")
    ax2.legend(fontsize=7)
    return save_figure_atomic(fig, path)


def timing_rows(summary: dict | None, table1: dict | None,
                table2: dict | None) -> list[tuple[str, float, float | None]]:
    """(label, mean ms, std ms or None) of every measured time, then the paper's."""
    rows: list[tuple[str, float, float | None]] = []
    if summary and summary.get("mean_solve_s"):
        rows.append(("FE solve, data generation (this machine)",
                     1e3 * float(summary["mean_solve_s"]), None))
    means = (table2 or {}).get("timing", {}).get("mean_ms", {})
    if "fem" in means:
        rows.append(("FE tracker, training grid, Table 2", float(means["fem"]), None))
    if "reference" in means:
        kind = (table2 or {}).get("reference", {}).get("kind", "fine_grid")
        label = ("P2 tetrahedral reference" if kind in ("p2", "stored")
                 else "fine-grid reference (the teacher's FE: not independent)")
        rows.append((f"{label}, Table 2", float(means["reference"]), None))
    if table1 and "predict_mean_ms" in table1:
        rows.append(("U-Net prediction, Table 1 (this machine)", float(table1["predict_mean_ms"]),
                     float(table1.get("predict_std_ms", 0.0))))
    if "net" in means:
        rows.append(("U-Net tracker update, Table 2", float(means["net"]), None))
    rows.append(("FE, the paper (SOFA)", PAPER_FE_MS, PAPER_FE_STD_MS))
    rows.append(("U-Net, the paper (GTX 1080 Ti)", PAPER_TABLE1["predict_mean_ms"],
                 PAPER_TABLE1["predict_std_ms"]))
    return rows


def plot_timing(rows: list[tuple[str, float, float | None]], path: Path) -> Path:
    """Horizontal bars (log scale) of the times in ``rows`` (ms). Saves a PNG at ``path``."""
    from matplotlib.colors import to_rgba

    fig = _figure((9, 0.5 * len(rows) + 1.5))
    ax = fig.add_subplot(1, 1, 1)
    labels = [r[0] for r in rows]
    vals = np.array([max(r[1], 1e-3) for r in rows])
    errs = np.array([r[2] or 0.0 for r in rows])
    colors = [to_rgba("tab:red" if "FE" in lab else "tab:green",
                      0.4 if "paper" in lab else 1.0) for lab in labels]
    y = np.arange(len(rows))[::-1]
    ax.barh(y, vals, xerr=np.minimum(errs, 0.9 * vals), color=colors, capsize=3)
    for yi, v in zip(y, vals, strict=True):
        ax.text(v * 1.1, yi, f"{v:.3g} ms", va="center", fontsize=8)
    ax.set_yticks(y, labels, fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel("time per deformation (ms, log scale)")
    ax.set_xlim(right=vals.max() * 8)
    ax.set_title("FE against network (lighter bars: the paper)")
    return save_figure_atomic(fig, path)
