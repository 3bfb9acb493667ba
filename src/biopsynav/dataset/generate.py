"""``biopsynav generate``: the training data of a case, in parallel, resumable.

Workers (local processes, or a Dask cluster given a scheduler address) compute samples and
return arrays; the main process alone writes them to ``dataset.zarr`` (:mod:`.store`), with at
most two samples in flight per worker. A kill of anything loses only the samples in flight;
running again computes just the missing ones. Sample ``i`` depends only on ``(seed, i, attempt)``
(:func:`biopsynav.probe.sample_rng`), and a draw whose solve does not converge, or that pushes
deeper than ``[probe] max_push_mm``, is recorded and replaced by the next attempt of the same
index (with ``[probe] too_deep_redraw = "same-place"`` a too-deep training push first by
weaker forces at the same place, within the same task), so the result is bit-identical
whatever the worker count, order or interruptions.
"""

from __future__ import annotations

import sys
import time
from collections import Counter, deque
from concurrent.futures import Future
from concurrent.futures.process import BrokenProcessPool
from pathlib import Path
from typing import Any

import numpy as np

from ..case import Case, as_case
from ..errors import BiopsynavError, InputError
from ..fileio import save_figure_atomic, write_json_atomic
from ..layout import DATASET_PLOT, DATASET_SUMMARY
from ..teacher_registry import builder_or_none
from .grow import grow_store, growth_summary, sizes_alone_differ
from .pool import WorkerProcesses, check_workers
from .store import (
    DatasetStore,
    check_compatible,
    create_store,
    dataset_path,
    open_store,
    protocol_dict,
    protocol_fingerprint,
    recorded_probe_value,
    remove_store,
)
from .worker import (
    IMPLAUSIBLE,
    NOT_CONVERGED,
    TOO_DEEP,
    WorkerSpec,
    dask_sample,
    init_process,
    process_sample,
)

SUMMARY_FILE, PLOT_FILE = DATASET_SUMMARY, DATASET_PLOT
#: The summary's counter of each kind of draw not kept.
STAT_OF_KIND = {NOT_CONVERGED: "failures", TOO_DEEP: "too_deep", IMPLAUSIBLE: "implausible"}
#: The failure share is judged once this many draws (or all requested, if fewer) were made.
MIN_DRAWS_FOR_SHARE = 20
#: A sample whose draw crashes the worker pool this many times stops the job.
MAX_POOL_CRASHES = 3
#: Samples in flight per worker (bounds memory and the work lost to a kill).
IN_FLIGHT_PER_WORKER = 2


def generate_case(case: Case | str | Path, workers: int = 0, scheduler: str | None = None,
                  overwrite: bool = False, n_train: int | None = None,
                  n_test: int | None = None, progress: bool = True) -> dict:
    """Generate (or complete) ``CASE_DIR/dataset.zarr``; returns the summary dict.

    Args:
        case: the loaded case, or its folder (``biopsynav init`` done).
        workers: local worker processes (0: all cores); ignored with ``scheduler``.
        scheduler: ``tcp://HOST:PORT`` of a Dask distributed scheduler (its workers get the
            case by value: no shared folder needed).
        overwrite: discard an existing data set made for another anatomy, grid or protocol.
        n_train, n_test: override ``[dataset]`` sizes (part of the protocol fingerprint).
        progress: show a tqdm progress bar (rate, ETA) on stderr.

    Returns the summary (also written to ``CASE_DIR/dataset_summary.json``; histograms in
    ``CASE_DIR/dataset.png``): count, failures (non-converged draws, this run and total),
    too_deep (draws beyond ``[probe] max_push_mm``, this run and total), minutes, samples/min,
    max and mean nodal displacement, max probe displacement.

    Raises:
        FingerprintError: the existing data set belongs to another anatomy, grid or protocol.
        InputError: a bad option, or an unreadable/foreign dataset.zarr.
        BiopsynavError: more than ``[dataset] max_failure_share`` of the draws did not converge,
            or went deeper than ``[probe] max_push_mm``.
    """
    start = time.perf_counter()
    case = as_case(case)
    n_train = int(case.cfg.dataset.n_train if n_train is None else n_train)
    n_test = int(case.cfg.dataset.n_test if n_test is None else n_test)
    if n_train < 1 or n_test < 1:
        raise InputError(f"n_train and n_test must be >= 1, got {n_train} and {n_test}",
                         "generate")
    check_workers(workers)
    preflight(case)  # input errors here, before a store or a worker exists
    store, grown = prepare_store(case, n_train, n_test, overwrite)
    work = working_case(case, store, workers)
    spec = WorkerSpec(work, case.fingerprint() + store.group.attrs["protocol_fingerprint"])
    done = store.done_mask()
    todo = np.flatnonzero(~done)
    stats = Counter()
    if todo.size:
        runner = make_runner(spec, workers, scheduler)
        try:
            _run(runner, store, todo, stats, case.cfg.dataset.max_failure_share, progress)
        finally:
            runner.close()
    summary = run_summary(store, stats, time.perf_counter() - start)
    summary["grown"] = grown
    write_json_atomic(case.dir / SUMMARY_FILE, summary)
    plot_distributions(store, case.dir / PLOT_FILE)
    return summary


def working_case(case: Case, store: DatasetStore, workers: int = 1) -> Case:
    """The case the workers draw and solve with: ``case`` with the data set's own
    ``[dataset] n_train`` (a ``generate`` override may differ from case.toml; a training
    sample's force follows ``[probe] train_force_exponent``) and ``[probe] f_max_n`` set by the
    force calibration (:mod:`biopsynav.dataset.calibrate`, its solves in ``workers`` local
    processes, 0: one per core), run once per data set and kept in its attributes. The
    loaded case itself is left as it is; returned as it is when nothing differs."""
    import copy

    from .calibrate import calibrate_force

    f_max_n = case.cfg.probe.f_max_n
    if case.cfg.probe.calibrate_force and case.cfg.probe.rigid_share < 1.0:
        found = store.group.attrs.get("force_calibration")
        if found is None:
            found = calibrate_force(case, workers)
            store.group.attrs["force_calibration"] = found
        f_max_n = float(found["f_max_n"])
    n_train = int(store.group.attrs["n_train"])
    if (f_max_n, n_train) == (case.cfg.probe.f_max_n, case.cfg.dataset.n_train):
        return case
    work = copy.copy(case)
    work.cfg = copy.deepcopy(case.cfg)
    work.cfg.probe.f_max_n, work.cfg.dataset.n_train = f_max_n, n_train
    return work


def preflight(case: Any) -> None:
    """Raise here, in the main process, what every worker would raise while setting up (a skin
    vertex outside the active cells, no push centre, pushes near lesions of a case without
    any, a teacher that cannot teach the case), instead of a pool that keeps crashing."""
    from ..fem.tissues import label_tissues
    from ..grid.embedding import surface_embedding
    from ..probe import check_lesion_share, eligible_centers

    label_tissues(case.grid.label_values, case.cfg, case.anatomy)
    surface_embedding(case.grid, case.anatomy)
    eligible_centers(case.anatomy, case.cfg.probe.min_chest_distance_mm)
    check_lesion_share(case.anatomy, case.cfg.probe)
    builder = builder_or_none(case.cfg.dataset.teacher)
    if builder is not None:
        builder.check(case)


def prepare_store(case: Any, n_train: int, n_test: int, overwrite: bool
                  ) -> tuple[DatasetStore, str | None]:
    """Open the case's store if it matches, grown in place when only its sizes differ
    (:mod:`.grow`), else create it (after removal with overwrite); the store and, when it
    grew, one line saying how (also printed on stderr)."""
    path = dataset_path(case.dir)
    protocol = protocol_dict(case.cfg, n_train, n_test, case.anatomy)
    fingerprint = case.fingerprint()
    if path.exists():
        if overwrite:
            remove_store(path)
            for name in (SUMMARY_FILE, PLOT_FILE):
                (case.dir / name).unlink(missing_ok=True)
        else:
            store = open_store(path)
            grown = grow_if_sizes_alone_differ(store, case.cfg, fingerprint, protocol)
            check_compatible(store, fingerprint, protocol)
            return store, grown
    return create_store(path, case.cfg, fingerprint, protocol, n_train, n_test,
                        case.grid.node_shape, case.grid.active_nodes), None


def grow_if_sizes_alone_differ(store: DatasetStore, cfg: Any, fingerprint: str,
                               protocol: dict) -> str | None:
    """Grow ``store`` to ``protocol``'s sizes when they are all that differ from the stored
    protocol (same anatomy and grid); the line saying how (printed on stderr), else None."""
    attrs = store.group.attrs
    if attrs["fingerprint"] != fingerprint \
            or not sizes_alone_differ(attrs.get("protocol"), protocol):
        return None
    data = protocol["dataset"]
    line = growth_summary(grow_store(store, cfg, protocol, data["n_train"], data["n_test"]))
    print(f"biopsynav: {line} ({store.path})", file=sys.stderr, flush=True)
    return line


# ----- runners: local processes or Dask -----------------------------------------------------

class LocalRunner:
    """Samples in local worker processes (:class:`~.pool.WorkerProcesses`), the pool rebuilt
    when a worker dies."""

    def __init__(self, spec: WorkerSpec, workers: int) -> None:
        self.processes = WorkerProcesses(workers, init_process, (spec,))

    @property
    def capacity(self) -> int:
        return self.processes.workers

    def submit(self, index: int, attempt: int) -> Future:
        return self.processes.submit(process_sample, int(index), int(attempt))

    def wait_any(self, futures: list) -> set:
        return self.processes.wait_any(futures)

    def restart(self) -> None:
        self.processes.restart()

    def close(self) -> None:
        self.processes.close()


class DaskRunner:
    """Tasks on a Dask distributed cluster; the case is broadcast once to every worker."""

    def __init__(self, spec: WorkerSpec, address: str) -> None:
        from distributed import Client

        try:
            self.client = Client(address, timeout="20s")
        except Exception as exc:  # noqa: BLE001 - connection errors of any kind
            raise InputError(f"cannot reach the Dask scheduler: {exc}", address) from None
        self.spec = self.client.scatter(spec, broadcast=True)
        workers = self.client.scheduler_info().get("workers", {})
        self.threads = sum(int(w.get("nthreads", 1)) for w in workers.values()) or 1

    @property
    def capacity(self) -> int:
        return self.threads

    def submit(self, index: int, attempt: int) -> Any:
        return self.client.submit(dask_sample, self.spec, int(index), int(attempt), pure=False)

    def wait_any(self, futures: list) -> set:
        from distributed import wait as dask_wait

        return set(dask_wait(futures, return_when="FIRST_COMPLETED").done)

    def restart(self) -> None:  # pragma: no cover - Dask reschedules lost tasks itself
        raise BiopsynavError("the Dask cluster lost a task")

    def close(self) -> None:
        self.client.close()


def make_runner(spec: WorkerSpec, workers: int, scheduler: str | None):
    """A Dask runner when ``scheduler`` is given, else local processes."""
    if scheduler:
        if not scheduler.startswith(("tcp://", "tls://", "inproc://", "ws://", "wss://")):
            raise InputError(f"expected tcp://HOST:PORT, got {scheduler!r}", "--scheduler")
        return DaskRunner(spec, scheduler)
    return LocalRunner(spec, workers)


# ----- the main loop ------------------------------------------------------------------------

def _run(runner: Any, store: DatasetStore, todo: np.ndarray, stats: Counter,
         max_failure_share: float, progress: bool) -> None:
    """Keep the workers busy with the missing samples; write results as they come."""
    from ..progress import progress_bar

    n_total = store.n_total
    next_attempt = _next_attempts(store.failures())
    queue = deque((int(i), next_attempt.get(int(i), 0)) for i in todo)
    in_flight: dict[Any, tuple[int, int]] = {}
    crashes: Counter = Counter()
    limit = IN_FLIGHT_PER_WORKER * runner.capacity
    bar = progress_bar(total=n_total, initial=n_total - len(todo), unit="sample",
                       smoothing=0.05, disable=not progress, desc="generate",
                       dynamic_ncols=True)
    try:
        while queue or in_flight:
            while queue and len(in_flight) < limit:
                index, attempt = queue.popleft()
                try:
                    in_flight[runner.submit(index, attempt)] = (index, attempt)
                except BrokenProcessPool:  # a worker died before its future said so
                    queue.appendleft((index, attempt))
                    _recover_pool(runner, queue, in_flight, crashes, None, stats)
            if not in_flight:
                continue
            try:
                finished = runner.wait_any(list(in_flight))
            except BrokenProcessPool:  # a worker died and no future said so
                _recover_pool(runner, queue, in_flight, crashes, None, stats)
                continue
            for future in finished:
                if future not in in_flight:
                    continue  # resubmitted after a pool crash
                index, attempt = in_flight.pop(future)
                try:
                    result = future.result()
                except BrokenProcessPool:
                    _recover_pool(runner, queue, in_flight, crashes, (index, attempt), stats)
                    break
                except BiopsynavError:
                    raise  # an input error found in a worker: its own one line
                except Exception as exc:
                    if type(exc).__name__ != "KilledWorker":
                        raise BiopsynavError(f"sample {index} (attempt {attempt}) failed in "
                                             f"its worker: {type(exc).__name__}: {exc}",
                                             "generate") from None
                    raise BiopsynavError(
                        f"the Dask cluster lost the workers running sample {index} (attempt "
                        f"{attempt}) several times ({exc}); the samples written so far are "
                        "kept: check the workers' memory and logs, then run the same command "
                        "again to resume", "generate") from None
                if _record_same_place_redraws(store, result, stats):
                    _check_failure_share(store, max_failure_share, n_total)
                if result["ok"]:
                    store.write_sample(result)
                    stats["computed"] += 1
                    stats["solve_s"] += result["solve_s"]
                    bar.update(1)
                else:
                    store.add_failures([_failure_record(result)])
                    stats[STAT_OF_KIND.get(result["kind"], "failures")] += 1
                    bar.set_postfix(failed=stats["failures"], too_deep=stats["too_deep"],
                                    implausible=stats["implausible"], refresh=False)
                    queue.appendleft((index, attempt + 1))
                    _check_failure_share(store, max_failure_share, n_total)
    finally:
        bar.close()


def _record_same_place_redraws(store: DatasetStore, result: dict, stats: Counter) -> int:
    """Log the too-deep draws that ``result`` redrew at the same place (``[probe]
    too_deep_redraw``), before its own outcome is written; how many."""
    before = result.get("too_deep_before") or []
    if before:
        store.add_failures([_failure_record(r) for r in before])
        stats["too_deep"] += len(before)
    return len(before)


def _recover_pool(runner: Any, queue: deque, in_flight: dict, crashes: Counter,
                  lost: tuple[int, int] | None, stats: Counter) -> None:
    """A worker died: restart the pool (counted in ``stats["pool_restarts"]``) and put every
    sample that was in flight back."""
    lost_all = ([lost] if lost else []) + list(in_flight.values())
    in_flight.clear()
    for item in lost_all:
        crashes[item] += 1
        if crashes[item] >= MAX_POOL_CRASHES:
            raise BiopsynavError(f"sample {item[0]} (attempt {item[1]}) was in flight in "
                                 f"{MAX_POOL_CRASHES} crashes of its worker process "
                                 "(the process died: killed by the system, for instance "
                                 "out of memory, or a crash in a native library; input "
                                 "errors are checked before the workers start); stopping",
                                 "generate")
    runner.restart()
    stats["pool_restarts"] += 1
    queue.extendleft(sorted(lost_all, reverse=True))


def _next_attempts(failures: list[dict]) -> dict[int, int]:
    """First attempt not known to fail, per index (failures are deterministic)."""
    out: dict[int, int] = {}
    for f in failures:
        out[int(f["index"])] = max(out.get(int(f["index"]), 0), int(f["attempt"]) + 1)
    return out


def _failure_record(result: dict) -> dict:
    """What the failures log keeps of a draw that was not kept (``kind``: why)."""
    extra = {k: round(result[k], 3) for k in ("probe_disp_mm", "push_mm") if k in result}
    redraw = {"redraw": result["redraw"]} if result.get("redraw") else {}
    return {"index": result["index"], "attempt": result["attempt"], **redraw,
            "kind": result["kind"],
            "error": result["error"], **extra,
            "force_n": result["force_n"], "tilt_deg": result["tilt_deg"],
            "vertex": result["vertex"], "newton_iters": result["newton_iters"],
            "solve_s": round(float(result["solve_s"]), 3),
            "last_iterations": _plain(result["diagnostics"])}


def _plain(obj: Any) -> Any:
    """JSON-safe copy (numpy scalars to Python)."""
    if isinstance(obj, dict):
        return {str(k): _plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not np.isfinite(obj):
        return str(obj)
    return obj


def failure_counts(records: list[dict]) -> Counter:
    """How many logged draws were not kept for each reason (``NOT_CONVERGED``, ``TOO_DEEP``,
    ``IMPLAUSIBLE``;
    records written before ``kind`` existed were all non-converged solves)."""
    return Counter(str(r.get("kind", NOT_CONVERGED)) for r in records)


def _check_failure_share(store: DatasetStore, share: float, n_total: int) -> None:
    """Stop when more than ``share`` of all draws so far failed to converge, went deeper
    than ``[probe] max_push_mm``, or were implausible (each on its own; after enough draws)."""
    records = store.failures()
    draws = len(records) + int(store.done_mask().sum())
    if draws < min(MIN_DRAWS_FOR_SHARE, n_total):
        return
    kinds = failure_counts(records)
    if kinds[NOT_CONVERGED] > share * draws:
        raise BiopsynavError(
            f"{kinds[NOT_CONVERGED]} of {draws} probe pushes did not converge, more than "
            f"[dataset] max_failure_share = {share:g}; the FE solve cannot follow these "
            "pushes: lower [probe] f_max_n or max_tilt_deg, or raise the tissue stiffness or "
            "[solver] max_iterations (failures are logged in dataset.zarr attrs 'failures')",
            "generate")
    if kinds[TOO_DEEP] > share * draws:
        raise BiopsynavError(
            f"{kinds[TOO_DEEP]} of {draws} probe pushes went deeper than [probe] max_push_mm, "
            f"more than [dataset] max_failure_share = {share:g}: this breast is softer than "
            "[probe] f_max_n assumes; lower f_max_n (dataset.png and dataset_summary.json show "
            "the probe displacements kept)", "generate")
    if kinds[IMPLAUSIBLE] > share * draws:
        raise BiopsynavError(
            f"{kinds[IMPLAUSIBLE]} of {draws} probe pushes converged to states no tissue "
            f"reaches (a cell edge stretched beyond [dataset] max_edge_stretch), more than "
            f"[dataset] max_failure_share = {share:g}: the material law or the grid's nearly "
            "empty cells do not hold these pushes; use [material] model = \"neo-hookean\" or "
            "raise [grid] min_fraction (the failures log in dataset.zarr attrs 'failures' names "
            "each)", "generate")


# ----- summary and plot ---------------------------------------------------------------------

def run_summary(store: DatasetStore, stats: Counter, seconds: float) -> dict:
    """Summary of the whole data set plus the figures of this run."""
    meta = store.read_meta()
    kinds = failure_counts(store.failures())
    count = int(meta["index"].size)
    minutes = seconds / 60.0
    computed = int(stats["computed"])

    def stat(name: str, fn) -> float:
        return round(float(fn(meta[name])), 4) if count else 0.0

    return {
        "dataset": str(store.path),
        "count": count,
        "requested": store.n_total,
        "n_train": int(store.group.attrs["n_train"]),
        "n_test": int(store.group.attrs["n_test"]),
        "computed_this_run": computed,
        "failures": int(stats["failures"]),
        "failures_total": kinds[NOT_CONVERGED],
        "too_deep": int(stats["too_deep"]),
        "too_deep_total": kinds[TOO_DEEP],
        "implausible": int(stats["implausible"]),
        "implausible_total": kinds[IMPLAUSIBLE],
        "pool_restarts": int(stats["pool_restarts"]),
        "minutes": round(minutes, 3),
        "samples_per_min": round(computed / minutes, 2) if computed and minutes > 0 else 0.0,
        "mean_solve_s": round(stats["solve_s"] / computed, 3) if computed else 0.0,
        "max_disp_mm": stat("max_disp_mm", np.max),
        "mean_max_disp_mm": stat("max_disp_mm", np.mean),
        "mean_disp_mm": stat("mean_disp_mm", np.mean),
        "max_probe_disp_mm": stat("probe_disp_mm", np.max),
        "force_calibration": store.group.attrs.get("force_calibration"),
        "train_force_scale": float(recorded_probe_value(store.group.attrs["protocol"],
                                                        "train_force_scale")),
        "mean_probe_disp_mm": stat("probe_disp_mm", np.mean),
        "max_force_n": stat("force_n", np.max),
        "rigid_pushes": int(np.count_nonzero(meta["force_n"] == 0.0)),  # force patches: > 0 N
        "mean_newton_iters": stat("newton_iters", np.mean),
    }


def format_run_summary(s: dict) -> str:
    """The summary of :func:`run_summary` as a few lines for people (mm, N, minutes)."""
    folder = Path(s["dataset"]).parent
    lines = [f"data set: {s['count']} of {s['requested']} samples ({s['n_train']} training, "
             f"{s['n_test']} held out) in {s['dataset']}",
             f"  this run: {s['computed_this_run']} samples in {s['minutes']:.1f} min "
             f"({s['samples_per_min']:.0f} per min, mean solve {s['mean_solve_s']:.2f} s)",
             f"  redrawn this run: {s['failures']} not converged, {s['too_deep']} deeper than "
             f"[probe] max_push_mm, {s['implausible']} implausible (in all runs: "
             f"{s['failures_total']}, {s['too_deep_total']}, {s['implausible_total']})",
             f"  pushes: probe displacement up to {s['max_probe_disp_mm']:.1f} mm (mean "
             f"{s['mean_probe_disp_mm']:.1f}), largest nodal displacement "
             f"{s['max_disp_mm']:.1f} mm, {s['rigid_pushes']} by the rigid probe face"]
    lines += _calibration_line(s.get("force_calibration"), s["train_force_scale"])
    lines += [f"  {s['grown']}"] if s.get("grown") else []
    lines.append(f"  figures: {folder / SUMMARY_FILE}, histograms: {folder / PLOT_FILE}")
    return "\n".join(lines)


def _calibration_line(found: dict | None, scale: float) -> list[str]:
    """The force calibration's line of :func:`format_run_summary` (none when it did not run);
    ``scale``: ``[probe] train_force_scale`` of the data set."""
    if not found:
        return []
    training = f" (training pushes up to {scale * found['f_max_n']:.2f} N)" if scale != 1 else ""
    return [f"  force range: up to {found['f_max_n']:.2f} N{training}, calibrated "
            f"({found['pushes']} pushes, {100 * found['quantile']:.0f}th percentile depth "
            f"{found['quantile_depth_mm']:.1f} mm for a target of {found['target_mm']:.1f} mm)"]


def plot_distributions(store: DatasetStore, path: Path) -> Path:
    """PNG with histograms of force, tilt, maximal nodal and probe displacement."""
    import matplotlib

    matplotlib.use("Agg")
    from matplotlib.figure import Figure

    meta = store.read_meta()
    panels = [("force_n", "total probe force (N)"), ("tilt_deg", "tilt (degrees)"),
              ("max_disp_mm", "max nodal displacement (mm)"),
              ("probe_disp_mm", "probe displacement (mm)")]
    fig = Figure(figsize=(10, 7))
    for k, (name, label) in enumerate(panels):
        ax = fig.add_subplot(2, 2, k + 1)
        ax.hist(meta[name], bins=30, color="tab:blue", alpha=0.8)
        ax.set_xlabel(label)
        ax.set_ylabel("samples")
    kinds = failure_counts(store.failures())
    fig.suptitle(f"{meta['index'].size} samples; redrawn: {kinds[NOT_CONVERGED]} not converged, "
                 f"{kinds[TOO_DEEP]} too deep, {kinds[IMPLAUSIBLE]} implausible")
    fig.tight_layout()
    return save_figure_atomic(fig, path)


__all__ = ["generate_case", "make_runner", "plot_distributions", "prepare_store", "run_summary",
           "format_run_summary",
           "protocol_fingerprint"]
