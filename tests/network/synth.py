"""A small synthetic ``dataset.zarr`` in the exact format of the dataset stage (for tests).

Geometry: a half-ellipsoid "breast" of active nodes on a (nx, ny, nz) grid, chest wall at z = 0.
Each sample pushes a patch of top-surface nodes around one of a few centres by a random vector d
(mm); the target is the smooth field ``u(p) = d * exp(-|p - c|^2 / (2 L^2)) * z / z_top``
masked to active nodes: a learnable, localised response that vanishes at the chest wall.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import zarr

from biopsynav.config import NetworkSection

FINGERPRINT = "synthetic-fingerprint-0001"
SHAPE = (16, 8, 8)  # the node grid of the shared synthetic data set (tests/conftest.py)


def tiny_settings(**kw) -> NetworkSection:
    """The default architecture (width 8, SiLU, quadratic features) with a short schedule
    (seconds on one CPU thread), in fp32: ``auto`` would time both arithmetics, and on a
    near tie two runs of one test could train in different ones."""
    base = dict(preset="custom", base_channels=8, levels=3, activation="silu",
                features="quadratic", iterations=300, val_interval=100,
                warmup_iterations=20, learning_rate=3e-3, batch_size=4, threads=1, seed=0,
                baseline="none", prior="none",  # synthetic data have no case (FE model)
                precision="fp32")
    base.update(kw)
    return NetworkSection(**base)


def active_mask(shape: tuple[int, int, int]) -> np.ndarray:
    """Half-ellipsoid of active nodes (nx, ny, nz) bool."""
    i, j, k = np.meshgrid(*[np.arange(n) for n in shape], indexing="ij")
    cx, cy = (shape[0] - 1) / 2, (shape[1] - 1) / 2
    r = ((i - cx) / (0.5 * shape[0])) ** 2 + ((j - cy) / (0.5 * shape[1])) ** 2 + \
        (k / (shape[2] - 0.5)) ** 2
    return r <= 1.0


def make_samples(n: int, shape: tuple[int, int, int], rng: np.random.Generator,
                 spacing: float = 5.0, max_disp: float = 20.0,
                 n_sites: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Inputs (n, 4, *shape) and targets (n, 3, *shape), float32, for the mask of ``shape``.

    The probe sits at one of ``n_sites`` surface nodes (fixed by a separate seed), so that a
    few dozen samples suffice to learn the map.
    """
    act = active_mask(shape)
    ijk = np.stack(np.meshgrid(*[np.arange(s) for s in shape], indexing="ij"), axis=0)
    pos = ijk * spacing  # (3, nx, ny, nz) mm
    # top surface: the highest active node of each (i, j) column
    top_k = np.where(act.any(axis=2), act.shape[2] - 1 - np.argmax(act[:, :, ::-1], axis=2), -1)
    surf = np.zeros(shape, bool)
    ii, jj = np.nonzero(top_k >= 0)
    surf[ii, jj, top_k[ii, jj]] = True
    surf_idx = np.argwhere(surf)
    sites = np.random.default_rng(12345).choice(len(surf_idx), n_sites, replace=False)
    centres = surf_idx[sites[rng.integers(0, n_sites, n)]] * spacing  # (n, 3) mm
    d = rng.normal(size=(n, 3))
    d[:, 2] = -np.abs(d[:, 2]) * 2.0  # mostly pushing in
    d *= (max_disp * rng.uniform(0.2, 1.0, n) / np.linalg.norm(d, axis=1))[:, None]
    diff = pos[None] - centres[:, :, None, None, None]  # (n, 3, nx, ny, nz)
    dist2 = (diff**2).sum(axis=1)  # (n, nx, ny, nz)
    length = 4.0 * spacing
    g = np.exp(-dist2 / (2 * length**2)) * (pos[2] / pos[2].max())[None]
    targets = (d[:, :, None, None, None] * g[:, None]) * act[None, None]
    w = np.where(surf[None] & (dist2 <= (1.5 * spacing) ** 2), np.exp(-dist2 / spacing**2), 0.0)
    inputs = np.zeros((n, 4, *shape))
    inputs[:, :3] = np.where(w[:, None] > 0, targets, 0.0)
    inputs[:, 3] = w
    return inputs.astype(np.float32), targets.astype(np.float32)


def write_synthetic_dataset(case_dir: str | Path, shape: tuple[int, int, int] = (16, 16, 8),
                            n_train: int = 48, n_test: int = 16, seed: int = 0,
                            fingerprint: str = FINGERPRINT, spacing: float = 5.0,
                            not_done: tuple[int, ...] = ()) -> Path:
    """Write ``case_dir/dataset.zarr``; samples listed in ``not_done`` are flagged incomplete."""
    rng = np.random.default_rng(seed)
    n = n_train + n_test
    x, y = make_samples(n, shape, rng, spacing)
    path = Path(case_dir) / "dataset.zarr"
    g = zarr.open_group(str(path), mode="w")
    g.create_array("inputs", data=x, chunks=(1, 4, *shape))
    g.create_array("targets", data=y, chunks=(1, 3, *shape))
    done = np.ones(n, bool)
    done[list(not_done)] = False
    g.create_array("done", data=done)
    g.create_array("active_nodes", data=active_mask(shape))
    g.create_array("max_disp_mm", data=np.linalg.norm(y, axis=1).reshape(n, -1).max(axis=1))
    g.create_array("force", data=rng.normal(size=(n, 3)).astype(np.float32))
    g.attrs.update({"n_train": n_train, "n_test": n_test, "fingerprint": fingerprint,
                    "node_shape": list(shape), "spacing_mm": spacing})
    return path


def write_linear_elastic_dataset(case, n_train: int, n_test: int, seed: int,
                                 nodes_per_sample: int = 5) -> np.ndarray:
    """A ``dataset.zarr`` in the loaded phantom ``case``'s folder whose inputs press
    ``nodes_per_sample`` random contact candidates by one random vector (mm) each and whose
    targets are the hard linear-elastic response plus a smooth non-linear term; returns the
    inputs (n, 4, nx, ny, nz)."""
    from biopsynav.contact.baseline import LinearElasticBaseline
    from biopsynav.contact.greens import candidate_nodes

    shape, n = case.grid.node_shape, n_train + n_test
    hard = LinearElasticBaseline.from_case(case, spring=None)
    cand, rng = candidate_nodes(case), np.random.default_rng(seed)
    x = np.zeros((n, 4, int(np.prod(shape))), np.float32)
    for i in range(n):
        nodes = rng.choice(cand, nodes_per_sample, replace=False)
        x[i][:3, nodes] = (rng.normal(size=3) * 3.0)[:, None]
        x[i][3, nodes] = rng.uniform(0.5, 3.0, nodes_per_sample)
    x = x.reshape(n, 4, *shape)
    lin = hard.predict(x)
    g = zarr.open_group(str(case.dir / "dataset.zarr"), mode="w")
    g.create_array("inputs", data=x, chunks=(1, 4, *shape))
    g.create_array("targets", data=(lin + 0.02 * lin * np.abs(lin)).astype(np.float32),
                   chunks=(1, 3, *shape))
    g.create_array("done", data=np.ones(n, bool))
    g.create_array("active_nodes", data=np.asarray(case.grid.active_nodes, bool))
    g.attrs.update({"n_train": n_train, "n_test": n_test, "fingerprint": case.fingerprint(),
                    "node_shape": list(shape), "spacing_mm": float(case.grid.spacing),
                    "protocol": {"dataset": {"contact_input": "elastic"}}})
    return x
