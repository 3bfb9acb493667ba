"""The paper's Table 1 on the held-out samples, measured with the deployed runtime and precision.

Writes ``OUT/table1.json``, ``OUT/error_histogram.png``, ``OUT/worst_sample.png`` and
``OUT/largest_deformation.png`` (``OUT`` = ``CASE_DIR/eval`` by default).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from ..case import Case, as_case
from ..contact.projection import ContactProjection, sample_projections
from ..dataset.contacts import sample_contact_matrices
from ..errors import FingerprintError
from ..fileio import write_json_atomic
from ..grid.index import tensor_to_field
from ..inference.model_files import meta_checksum
from ..inference.surrogate import Surrogate
from ..layout import TABLE1_FILE, CasePaths
from .data import Dataset, load_dataset
from .metrics import error_summary, mean_dof_error_np, mean_norm_error_np
from .plots import plot_error_histogram, plot_sample

Contacts = list[tuple[ContactProjection, np.ndarray]]


def predict_all(sur: Surrogate, x: np.ndarray, batch: int = 8,
                contacts: Contacts | None = None) -> np.ndarray:
    """Predictions (n, 3, nx, ny, nz) mm of inputs (n, 4, nx, ny, nz), in batches; with
    ``contacts`` (one (projection, contact displacement) per input, :func:`test_contacts`)
    one by one, projected."""
    if contacts is not None:
        return np.stack([sur.predict(x[i], *contacts[i]) for i in range(x.shape[0])])
    return np.concatenate([np.array(sur.predict(x[i:i + batch]))
                           for i in range(0, x.shape[0], batch)])


def test_contacts(sur: Surrogate, case: Case, data: Dataset) -> Contacts:
    """:func:`sample_contacts` of the held-out samples."""
    return sample_contacts(sur, case, data, data.test_idx.numpy())


def sample_contacts(sur: Surrogate, case: Case, data: Dataset, samples: np.ndarray
                    ) -> Contacts:
    """For each stored sample of ``samples`` (indices into the store), for a model that can
    project (``sur.can_project``): the contact projection of its probe's contact points
    (redrawn from the data set's protocol) and their displacement ``W_P u_FE`` (n, 3) mm,
    from which the dataset stage built the input
    (:func:`~biopsynav.contact.projection.sample_projections`; InputError when they do not
    give the stored input)."""
    return sample_projections(sur.baseline, sample_contact_matrices(case, data.path, samples),
                              data.inputs.numpy(), data.targets.numpy(), samples,
                              str(data.path))


def time_predictions(sur: Surrogate, x: np.ndarray, n: int = 1000,
                     contacts: Contacts | None = None) -> dict:
    """Batch-1 prediction times (ms) over ``n`` calls cycling through the samples ``x`` (and
    their ``contacts``: projected, each contact set prepared beforehand as the tracker does at
    its rest pose)."""
    k = min(len(x), 64)
    samples = [np.ascontiguousarray(x[i]) for i in range(k)]
    extra = [contacts[i] if contacts is not None else () for i in range(k)]
    sur.warm_up(20)
    t = np.empty(n)
    for i in range(n):
        s, c = samples[i % k], extra[i % k]
        t0 = time.perf_counter()
        sur.predict(s, *c)
        t[i] = time.perf_counter() - t0
    t *= 1e3
    return {"predict_p50_ms": float(np.median(t)), "predict_p99_ms": float(np.percentile(t, 99)),
            "predict_mean_ms": float(t.mean()), "predict_std_ms": float(t.std()),
            "predict_n": n}


def evaluate(model_dir: str | Path, dataset: str | Path, out_dir: str | Path,
             expected_fingerprint: str, *, runtime: str | None = None, threads: int = 0,
             n_timing: int = 1000, spacing_mm: float | None = None,
             contact_projection: bool = True, case: Case | None = None) -> dict:
    """Table 1 of the model in ``model_dir`` on the test samples of ``dataset``; see module doc.

    ``spacing_mm``: grid cell size for the figures (node units when unknown).
    ``contact_projection``: project the predictions onto the measured contact
    (:mod:`~biopsynav.contact.projection`) when the model allows it, as the tracker does
    (always for a model trained through the projection);
    the figures without it are kept as ``*_unprojected_mm``. ``case``: the loaded case
    (default: ``model_dir``'s parent folder)."""
    data = load_dataset(dataset)
    if data.fingerprint != expected_fingerprint:
        raise FingerprintError("the data set was generated for another anatomy or grid than "
                               "this case; regenerate it", str(data.path))
    sur = Surrogate.load(model_dir, expected_fingerprint, runtime=runtime, threads=threads,
                         case=case)
    x = data.inputs[data.test_idx].numpy()
    y = data.targets[data.test_idx].numpy()
    active = data.active.numpy()
    pred = predict_all(sur, x)
    e_plain = mean_norm_error_np(pred, y, active)
    project = sur.projects(contact_projection)
    home = Path(model_dir).parent
    if case is None and (project or CasePaths(home).config.is_file()):
        case = Case.load(home)  # needed to project; else for the inverted-cell count
    contacts = None
    if project:
        contacts = test_contacts(sur, case, data)
        pred = predict_all(sur, x, contacts=contacts)
    e = mean_norm_error_np(pred, y, active)
    disp = np.linalg.norm(y, axis=1)[:, active].max(axis=1)  # (n,) largest nodal displacement
    result = error_summary(e) | dof_figures(mean_dof_error_np(pred, y, active))
    result.update(baseline_figures(sur, x, y, active))
    rigid = held_out_rigid(data)
    if rigid is not None:
        result["by_kind"] = kind_figures(e, rigid)
    result.update(time_predictions(sur, x, n_timing, contacts))
    result.update({"contact_projection": contacts is not None,
                   "mean_e_unprojected_mm": float(e_plain.mean()),
                   "max_e_unprojected_mm": float(e_plain.max())})
    meta = sur.meta
    result.update({
        "model_checksum": meta_checksum(meta),  # the report tells a model trained since
        # the optimisation loop plus the per-sample set-up before it (baseline, projections)
        "train_min": (float(meta["training"]["train_time_s"])
                      + float(meta["training"].get("setup_s", 0.0))) / 60.0,
        "max_disp_mm": float(disp.max()),
        "largest_deformation_index": int(disp.argmax()),
        "worst_sample": int(data.test_idx[result["worst_index"]]),
        "largest_deformation_sample": int(data.test_idx[int(disp.argmax())]),
        "n_active_nodes": int(active.sum()),
        "runtime": sur.runtime, "precision": sur.precision,
        **({"runtime_chosen": sur.runtime_chosen} if sur.runtime_chosen else {}),
        "architecture": meta["architecture"], "n_parameters": meta["n_parameters"],
        "e_per_sample_mm": e.tolist(),
    })
    if case is not None:
        result.update(inverted_cell_figures(case, pred, y))
    _figures(Path(out_dir), pred, y, active, e, disp,
             spacing_mm or meta.get("spacing_mm") or 1.0)
    write_json_atomic(Path(out_dir) / TABLE1_FILE, result)
    return result


def dof_figures(e_dof: np.ndarray) -> dict:
    """Mean, standard deviation and maximum (mm) of the per-sample errors of the paper's
    eq. (3) read per degree of freedom (:func:`~.metrics.mean_dof_error_np`)."""
    return {"mean_e_dof_mm": float(e_dof.mean()), "std_e_dof_mm": float(e_dof.std()),
            "max_e_dof_mm": float(e_dof.max())}


def baseline_figures(sur: Surrogate, x: np.ndarray, y: np.ndarray, active: np.ndarray) -> dict:
    """Mean and max e (mm) of the surrogate's physics baseline alone on the inputs ``x`` (n,
    4, nx, ny, nz) against the targets ``y`` (n, 3, nx, ny, nz): the network with its head at
    zero, what training adds to (``baseline_mean_e_mm``, ``baseline_max_e_mm``); {} for a
    model without a baseline."""
    if sur.baseline is None:
        return {}
    e = mean_norm_error_np(sur.baseline.predict(x), y, active)
    return {"baseline_mean_e_mm": float(e.mean()), "baseline_max_e_mm": float(e.max())}


def held_out_rigid(data: Dataset) -> np.ndarray | None:
    """Which held-out samples of a data set of both kinds (``[probe] rigid_share`` between 0
    and 1) are rigid-probe pushes, (n_test,) bool; None for a data set of one kind, and for
    one of both made before the kinds were placed (no ``mixed_draws`` in its protocol: its
    kinds were drawn by chance, and Table 1 is then reported over both together)."""
    from ..dataset.store import recorded_probe_value
    from ..probe import both_kinds, is_rigid_draw

    protocol = data.attrs.get("protocol") or {}
    share = float(recorded_probe_value(protocol, "rigid_share"))
    if not both_kinds(share) or "mixed_draws" not in (protocol.get("dataset") or {}):
        return None
    return np.array([is_rigid_draw(share, int(i)) for i in data.test_idx], bool)


#: Table 1's kinds of held-out sample in a data set of both (``by_kind`` in table1.json)
KIND_LABELS = {"force_patches": "force patches (the paper's test set)",
               "rigid_pushes": "rigid-probe pushes (the tracker's)"}


def kind_figures(e: np.ndarray, rigid: np.ndarray) -> dict:
    """Mean, std and max e (mm) and count of each kind's held-out samples; ``e`` (n,) mm,
    ``rigid`` (n,) bool (:func:`held_out_rigid`). A kind with no sample is left out."""
    out = {}
    for kind, mask in (("force_patches", ~rigid), ("rigid_pushes", rigid)):
        if mask.any():
            out[kind] = {k: v for k, v in error_summary(e[mask]).items() if k != "worst_index"}
    return out


def inverted_cell_figures(case: Case, pred: np.ndarray, target: np.ndarray) -> dict:
    """How often the predicted fields (n, 3, nx, ny, nz) mm invert a cell of the case's FE
    model (det F <= 0 at a Gauss point: no physical deformation), against the FE targets.

    Returns ``inverted_samples`` (predictions with at least one inverted cell),
    ``inverted_cells_max`` (the most in one prediction), ``inverted_cells_total``,
    ``inverted_cells_per_sample`` (n,) and ``inverted_samples_fe`` (the same count for the
    targets: 0 for a converged data set)."""
    from ..fem import FEModel, smallest_det_f

    model = FEModel.from_case(case)
    shape = case.grid.node_shape

    def counts(fields: np.ndarray) -> np.ndarray:
        return np.array([int((smallest_det_f(model, tensor_to_field(f.reshape(3, *shape)))
                              <= 0.0).sum()) for f in fields])  # evaluation, not a hot path

    pred_counts, fe_counts = counts(pred), counts(target)
    return {"inverted_samples": int((pred_counts > 0).sum()),
            "inverted_cells_max": int(pred_counts.max(initial=0)),
            "inverted_cells_total": int(pred_counts.sum()),
            "inverted_cells_per_sample": pred_counts.tolist(),
            "inverted_samples_fe": int((fe_counts > 0).sum())}


def _figures(out: Path, pred: np.ndarray, y: np.ndarray, active: np.ndarray, e: np.ndarray,
             disp: np.ndarray, spacing: float) -> None:
    plot_error_histogram(e, out / "error_histogram.png")
    w, big = int(e.argmax()), int(disp.argmax())
    plot_sample(pred[w], y[w], active, spacing,
                f"worst sample: e = {e[w]:.4f} mm", out / "worst_sample.png")
    plot_sample(pred[big], y[big], active, spacing,
                f"largest deformation {disp[big]:.1f} mm: e = {e[big]:.4f} mm",
                out / "largest_deformation.png")


def baseline_words(r: dict) -> str:
    """Table 1 ``r``'s physics baseline alone (``baseline_mean_e_mm``, ``baseline_max_e_mm``)
    as words."""
    return (f"the physics baseline alone: mean e {r['baseline_mean_e_mm']:.4f} mm, max e "
            f"{r['baseline_max_e_mm']:.4f} mm")


def format_table1(r: dict) -> str:
    """Table 1 as text (mm, ms, min)."""
    return (f"mean e {r['mean_e_mm']:.4f} mm | std e {r['std_e_mm']:.4f} mm | "
            f"max e {r['max_e_mm']:.4f} mm"
            + (f" (per degree of freedom: {r['mean_e_dof_mm']:.4f} / {r['max_e_dof_mm']:.4f} mm)"
               if "mean_e_dof_mm" in r else "")
            + f" | prediction {r['predict_p50_ms']:.2f} ms median, "
            f"{r['predict_p99_ms']:.2f} ms p99 ({r['runtime']}, {r['precision']}"
            f"{', contact projection' if r.get('contact_projection') else ''}) | training "
            f"{r['train_min']:.1f} min | max nodal displacement {r['max_disp_mm']:.2f} mm | "
            f"{r['n_samples']} test samples, {r['n_active_nodes']} active nodes"
            + (f" | {baseline_words(r)}" if "baseline_mean_e_mm" in r else "")
            + (f" | {r['inverted_samples']} predictions invert a cell (at most "
               f"{r['inverted_cells_max']}; FE {r['inverted_samples_fe']})"
               if "inverted_samples" in r else "")
            + "".join(f" | {KIND_LABELS[k]}: mean e {v['mean_e_mm']:.4f} mm, max e "
                      f"{v['max_e_mm']:.4f} mm ({v['n_samples']})"
                      for k, v in r.get("by_kind", {}).items()))


def evaluate_network_case(case: Case | str | Path) -> dict:
    """CLI entry: Table 1 of the case's model on its ``dataset.zarr``, written to its eval/
    (``case``: loaded, or its folder)."""
    case = as_case(case)
    cfg = case.cfg
    return evaluate(case.paths.model, case.dir, case.paths.eval, case.fingerprint(),
                    runtime=cfg.network.runtime, threads=cfg.network.threads,
                    spacing_mm=case.grid.spacing, case=case,
                    contact_projection=cfg.network.contact_projection,
                    n_timing=cfg.evaluate.timed_predictions)
