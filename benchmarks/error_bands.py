"""Where the network misses its teacher: the error of a case's tracking model on its own
training and held-out samples, by each node's distance from the probe's centre and by whether
the node lies inside the breast, and at the lesion centres.

Usage: ``python benchmarks/error_bands.py CASE_DIR [--train-samples 80] [--out FILE]``.

The model is the one the tracker loads (``Case.tracking_model``: ``refine/model`` with
``[refine] samples > 0``) and the samples are those of the data set that taught it
(``refine/dataset.zarr`` then), predicted as Table 1 does (with the contact projection when
the model has one). For each sample set it prints the mean e (mm, Table 1's per-sample mean
over active nodes), then the mean nodal error (mm) and the mean target displacement (mm) in
bands of distance from the push's centre vertex (mm, at rest), for all active nodes and for
those inside and outside the breast surface (immersed-grid nodes outside it carry the field's
extension, not tissue), and the same at the lesion centres (the trilinear interpolation of
the nodal error there, by the lesion's distance from the push's centre), and the mean and max
e by the push's probe displacement (:data:`DEPTHS_MM`). A training error as
large as the held-out one says that the network cannot fit its teacher there (the targets
are not smooth enough for the grid, or the network too small), not that it lacks samples.
The last line reads ``RESULT train_e_mm=... test_e_mm=... test_band_10_20_mm=...
test_band_20_40_mm=... test_lesion_mm=...``.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

BANDS_MM = ((0.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, np.inf))
#: Bins of the push's probe displacement (mm; Table 1's depth bins, the paper's D30 from 27.5).
DEPTHS_MM = ((0.0, 10.0), (10.0, 20.0), (20.0, 27.5), (27.5, np.inf))


def predictions(sur, case, data, idx: np.ndarray) -> np.ndarray:
    """Predictions (n, 3, nx, ny, nz) mm of the stored samples ``idx``, projected onto their
    contact points when the model projects (as Table 1)."""
    from biopsynav.network.evaluate import predict_all, sample_contacts

    contacts = (sample_contacts(sur, case, data, idx)
                if sur.projects(case.cfg.network.contact_projection) else None)
    return predict_all(sur, data.inputs.numpy()[idx], contacts=contacts)


def band_rows(err: np.ndarray, disp: np.ndarray, dist: np.ndarray, keep: np.ndarray) -> list:
    """Per distance band: [lo, hi (None: open), nodal values, mean error mm, mean
    displacement mm] over the (sample, node) entries ``keep`` (all arrays (n, n_active))."""
    rows = []
    for lo, hi in BANDS_MM:
        m = keep & (dist >= lo) & (dist < hi)
        n = int(m.sum())
        rows.append([lo, hi if np.isfinite(hi) else None, n,
                     float(err[m].mean()) if n else None,
                     float(disp[m].mean()) if n else None])
    return rows


def depth_rows(e: np.ndarray, depth: np.ndarray) -> list:
    """Per probe-displacement bin of :data:`DEPTHS_MM`: [lo, hi (None: open), samples, mean
    e mm, max e mm] of the per-sample errors ``e`` (n,) with probe displacements ``depth``
    (n,) mm; an empty bin has None for both errors."""
    rows = []
    for lo, hi in DEPTHS_MM:
        m = (depth >= lo) & (depth < hi)
        n = int(m.sum())
        rows.append([lo, hi if np.isfinite(hi) else None, n,
                     float(e[m].mean()) if n else None, float(e[m].max()) if n else None])
    return rows


def lesion_errors(case, pred: np.ndarray, y: np.ndarray, centres: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """At every lesion centre of ``case`` for each sample: the prediction's error (n, n_les)
    mm, the target displacement (n, n_les) mm and the distance from the push's centre
    ``centres`` (n, 3) mm; ``pred``, ``y`` (n, 3, nx, ny, nz) mm."""
    from biopsynav.grid.embedding import Embedding
    from biopsynav.grid.index import tensor_to_field

    lesions = np.array([lesion.center for lesion in case.anatomy.lesions], dtype=np.float64)
    at = Embedding.build(case.grid, lesions, where="lesion centres")
    err = np.stack([np.linalg.norm(at.interpolate(tensor_to_field(p - t)), axis=1)
                    for p, t in zip(pred, y, strict=True)])
    disp = np.stack([np.linalg.norm(at.interpolate(tensor_to_field(t)), axis=1) for t in y])
    return err, disp, np.linalg.norm(lesions[None] - centres[:, None], axis=2)


def sample_set_figures(sur, case, data, idx: np.ndarray, nodes: np.ndarray,
                       inside: np.ndarray) -> dict:
    """Mean e and the band rows (all / inside / outside nodes, lesion centres) of the
    samples ``idx``; ``nodes`` (n_active, 3) mm the active nodes, ``inside`` (n_active,)
    whether each lies inside the breast."""
    import zarr

    from biopsynav.network.metrics import mean_norm_error_np

    active = data.active.numpy()
    pred, y = predictions(sur, case, data, idx), data.targets.numpy()[idx]
    e = mean_norm_error_np(pred, y, active)
    err = np.linalg.norm(pred - y, axis=1)[:, active]
    disp = np.linalg.norm(y, axis=1)[:, active]
    store = zarr.open_group(str(data.path), mode="r")
    centres = np.asarray(store["center"][:])[idx]
    depth = np.asarray(store["probe_disp_mm"][:])[idx]
    dist = np.linalg.norm(nodes[None] - centres[:, None], axis=2)
    every = np.ones_like(err, dtype=bool)
    inner = np.broadcast_to(inside, err.shape)
    l_err, l_disp, l_dist = lesion_errors(case, pred, y, centres)
    return {"samples": len(idx), "mean_e_mm": float(e.mean()), "max_e_mm": float(e.max()),
            "lesion_mm": float(l_err.mean()), "by_depth": depth_rows(e, depth),
            "bands": {"all": band_rows(err, disp, dist, every),
                      "inside": band_rows(err, disp, dist, inner),
                      "outside": band_rows(err, disp, dist, ~inner),
                      "lesions": band_rows(l_err, l_disp, l_dist,
                                           np.ones_like(l_err, dtype=bool))}}


def band_label(lo: float, hi: float | None) -> str:
    """"lo-hi", or ">lo" for an open band (``hi`` None)."""
    return f">{lo:g}" if hi is None else f"{lo:g}-{hi:g}"


def print_figures(name: str, f: dict) -> None:
    print(f"\n{name}: {f['samples']} samples, mean e {f['mean_e_mm']:.3f} mm, max e "
          f"{f['max_e_mm']:.3f} mm, at the lesion centres {f['lesion_mm']:.3f} mm")
    print(f"{'nodes':>8} {'band mm':>10} {'values':>8} {'error mm':>9} {'|u| mm':>8}")
    for where, rows in f["bands"].items():
        for lo, hi, n, err, disp in rows:
            if n:
                print(f"{where:>8} {band_label(lo, hi):>10} {n:>8} {err:>9.3f} {disp:>8.2f}")
    print(f"{'probe displacement mm':>22} {'samples':>8} {'mean e mm':>10} {'max e mm':>9}")
    for lo, hi, n, mean, worst in f["by_depth"]:
        if n:
            print(f"{band_label(lo, hi):>22} {n:>8} {mean:>10.3f} {worst:>9.3f}")


def run(case_dir: Path, train_samples: int) -> dict:
    from biopsynav.anatomy.model import winding_number
    from biopsynav.case import Case
    from biopsynav.inference.surrogate import Surrogate
    from biopsynav.network.data import load_dataset
    from biopsynav.refine import tracking_teacher_case

    case = Case.load(case_dir)
    teacher_case = tracking_teacher_case(case)
    data = load_dataset(teacher_case.dir)
    sur = Surrogate.load(case.tracking_model, data.fingerprint, case=teacher_case)
    nodes = case.grid.node_coords()[data.active.numpy().reshape(-1)]
    inside = np.abs(winding_number(nodes, case.anatomy.vertices, case.anatomy.faces)) > 0.5
    train = data.train_idx.numpy()[:train_samples]
    return {"model": str(case.tracking_model), "dataset": str(data.path),
            "train": sample_set_figures(sur, teacher_case, data, train, nodes, inside),
            "test": sample_set_figures(sur, teacher_case, data, data.test_idx.numpy(), nodes,
                                       inside)}


def result_line(r: dict) -> str:
    rows = r["test"]["bands"]["all"]  # in the order of BANDS_MM: 0-10, 10-20, 20-40, > 40
    band = [np.nan if row[3] is None else row[3] for row in rows]  # None: no node in it
    return (f"RESULT train_e_mm={r['train']['mean_e_mm']:.4f} "
            f"test_e_mm={r['test']['mean_e_mm']:.4f} "
            f"test_band_10_20_mm={band[1]:.3f} test_band_20_40_mm={band[2]:.3f} "
            f"test_lesion_mm={r['test']['lesion_mm']:.3f}")


def positive_int(text: str) -> int:
    """An argument that must be a whole number of at least 1."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 1:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number of at least 1")
    return value


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("case_dir", type=Path)
    ap.add_argument("--train-samples", type=positive_int, default=80,
                    help="training samples evaluated (the first of the training set)")
    ap.add_argument("--out", type=Path, default=None, help="write the figures as JSON")
    args = ap.parse_args(argv)
    from biopsynav.errors import BiopsynavError

    try:
        r = run(args.case_dir, args.train_samples)
    except BiopsynavError as exc:
        raise SystemExit(f"error: {exc}") from None
    print(f"model {r['model']}\ndata {r['dataset']}")
    print_figures("training samples", r["train"])
    print_figures("held-out samples", r["test"])
    if args.out:
        from biopsynav.fileio import write_text_atomic

        write_text_atomic(args.out, json.dumps(r, indent=1))
    print(result_line(r))
    return r


if __name__ == "__main__":
    main()
