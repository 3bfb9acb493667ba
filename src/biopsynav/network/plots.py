"""Figures of training and evaluation (matplotlib Agg, written atomically)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..fileio import save_figure_atomic


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_loss_curve(history: list[dict], path: str | Path) -> Path:
    """Training loss and validation mean/max e (mm) against iterations, log scale."""
    plt = _plt()
    it = [h["iteration"] for h in history]
    fig, ax = plt.subplots(figsize=(7, 4))
    ax.semilogy(it, [h["train_loss"] for h in history], label="training loss (normalised)")
    ax.semilogy(it, [h["val_mean_e_mm"] for h in history], label="validation mean e (mm)")
    ax.semilogy(it, [h["val_max_e_mm"] for h in history], "--", label="validation max e (mm)")
    ax.set_xlabel("iteration")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    try:
        return save_figure_atomic(fig, path)
    finally:
        plt.close(fig)


def plot_error_histogram(e: np.ndarray, path: str | Path) -> Path:
    """Histogram of per-sample mean norm errors e (mm)."""
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.hist(np.asarray(e), bins=30, color="tab:blue", alpha=0.8)
    ax.axvline(float(np.mean(e)), color="k", ls="--", label=f"mean {np.mean(e):.4f} mm")
    ax.set_xlabel("e: mean nodal error norm (mm)")
    ax.set_ylabel("test samples")
    ax.legend()
    try:
        return save_figure_atomic(fig, path)
    finally:
        plt.close(fig)


def plot_sample(pred: np.ndarray, target: np.ndarray, active: np.ndarray, spacing: float,
                title: str, path: str | Path) -> Path:
    """Displaced active nodes of one sample: rest (grey), FE (red), prediction (green).

    ``pred``/``target`` (3, nx, ny, nz) mm, ``active`` (nx, ny, nz) bool; ``spacing`` mm between
    nodes (1.0 when unknown: positions are then in node units plus mm displacements). Three
    views: 3D points, the mid-y slice (x-z) and the mid-x slice (y-z) with error arrows.
    """
    plt = _plt()
    ijk = np.argwhere(active)
    rest = ijk * spacing
    p = rest + pred[:, active].T
    t = rest + target[:, active].T
    fig = plt.figure(figsize=(15, 5))
    ax = fig.add_subplot(1, 3, 1, projection="3d")
    ax.scatter(*rest.T, s=2, c="0.75", label="rest")
    ax.scatter(*t.T, s=4, c="red", label="FE")
    ax.scatter(*p.T, s=4, c="green", label="U-Net")
    ax.set_title(title)
    ax.legend(loc="upper left")
    for k, (axis, other, name) in enumerate(((1, 0, "x-z, mid y"), (0, 1, "y-z, mid x"))):
        mid = active.shape[axis] // 2
        sel = ijk[:, axis] == mid
        a2 = fig.add_subplot(1, 3, 2 + k)
        a2.scatter(rest[sel, other], rest[sel, 2], s=4, c="0.75")
        a2.scatter(t[sel, other], t[sel, 2], s=8, c="red", label="FE")
        a2.scatter(p[sel, other], p[sel, 2], s=8, c="green", marker="x", label="U-Net")
        a2.set_aspect("equal")
        a2.set_title(f"slice {name} (mm)")
        a2.legend(loc="best", fontsize=7)
    try:
        return save_figure_atomic(fig, path)
    finally:
        plt.close(fig)
