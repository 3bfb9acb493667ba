"""What the P2 teacher of `[refine]` costs (`[refine] teacher = "p2"`, docs/dataset.md, "The
P2 teacher"): its rigid pushes solved through a Dask LocalCluster, and what a larger cluster
would take.

    python benchmarks/p2_teacher.py [CASE] [--samples 24] [--workers 2] [--fine 4]
                                    [--size 10] [--result-name NAME | --no-result-file]
    python benchmarks/p2_teacher.py --store CASE/refine [--result-name NAME]

CASE: a case folder of one material (default: the built-in phantom, made in a temporary
folder). A copy of its anatomy and grid gets ``[refine] teacher = "p2"`` with ``--samples``
pushes (one held out), tetrahedra of ``--fine`` mm within 35 mm of each push and ``--size``
mm elsewhere, and ``generate`` solves them through a ``distributed.LocalCluster`` of
``--workers`` single-threaded processes (as ``generate --scheduler tcp://...`` does on a
cluster). Printed: the wall time, each push's solve time (mean, median, 90th percentile),
the data a push sends back (its input and target arrays), the time a worker spends on a
push beyond its solve (scheduling, transfer, writing: ``(wall x workers - sum of solves) /
pushes``), and from these the wall time of N = 50, 100, 200 and 400 pushes on 16 and 64
workers (``N (solve + overhead) / workers``, the workers' start-up once: the pushes are
independent, and the store is written by the client alone). A push's time grows about
exponentially with its depth, so a few pushes' mean says little of the protocol's: with three
pushes or more the estimate takes ``solve`` from the fit ``a exp(b depth)`` of their times,
averaged over the protocol's depths (uniform up to ``[refine] max_push_mm``, capped at the
push's time limit; :func:`biopsynav.runtime.p2_push_seconds`); the plain mean is printed
beside it. ``--store CASE/refine``: no pushes solved; the figures of those a P2 refine data
set already holds (a ``refine`` run, stopped or complete), no wall time or overhead (taken as
0). Run it alone on the machine.

Writes ``benchmarks/results/p2-teacher-<case>.json``; the last line reads ``RESULT
push_s_mean=... push_s_p90=... wall_min=... overhead_s=... est_16w_400_min=...
est_64w_400_min=...``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from biopsynav.config import load_config
from biopsynav.runtime import p2_push_seconds
from pushes_only import copy_case_files
from resultfile import write_result
from speedprobe import speed_probes

ESTIMATE_WORKERS = (16, 64)
ESTIMATE_PUSHES = (50, 100, 200, 400)


def source_case(path: str | None, scratch: Path) -> tuple[Path, str]:
    """The case to copy and its name: ``path``, or the built-in phantom made in ``scratch``."""
    from biopsynav.case import make_phantom_case

    if path is None:
        return make_phantom_case(scratch / "phantom").paths.dir, "phantom"
    return Path(path), Path(path).name


def p2_refine_case(case_dir: Path, work: Path, args: argparse.Namespace) -> Path:
    """A copy of ``case_dir``'s anatomy and grid whose refine case is taught by P2; the refine
    case's folder."""
    from biopsynav.case import Case
    from biopsynav.config import load_config, save_config
    from biopsynav.refine import refine_case

    work.mkdir(parents=True)
    copy_case_files(case_dir, work)
    cfg = load_config(work)
    cfg.refine.teacher, cfg.refine.samples, cfg.refine.held_out = "p2", args.samples, 1
    cfg.refine.teacher_fine_mm, cfg.refine.teacher_size_mm = args.fine, args.size
    save_config(work, cfg)
    return refine_case(Case.load(work)).paths.dir


def solve_through_cluster(refine_dir: Path, workers: int) -> tuple[float, dict]:
    """Generate the refine case's pushes through a LocalCluster: wall seconds, the summary."""
    from distributed import LocalCluster

    from biopsynav.dataset.generate import generate_case

    with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                      dashboard_address=None) as cluster:
        start = time.perf_counter()
        summary = generate_case(refine_dir, scheduler=cluster.scheduler_address,
                                progress=False)
        return time.perf_counter() - start, summary


def push_figures(refine_dir: Path) -> dict:
    """Per-push solve seconds (kept pushes), data a push sends back (bytes), failures."""
    import zarr

    g = zarr.open_group(str(refine_dir / "dataset.zarr"), mode="r")
    done = g["done"][...]
    solve = np.asarray(g["solve_s"][...])[done]
    sample_bytes = 4 * (int(np.prod(g["inputs"].shape[1:])) + int(np.prod(g["targets"].shape[1:])))
    return {"pushes": int(done.sum()), "failures": len(g.attrs.get("failures", [])),
            "push_s": solve.tolist(), "push_s_mean": float(solve.mean()),
            "push_s_median": float(np.median(solve)),
            "push_s_p90": float(np.percentile(solve, 90)), "sample_bytes": sample_bytes,
            "probe_disp_mm": np.asarray(g["probe_disp_mm"][...])[done].tolist()}


def depth_model(fig: dict) -> tuple[float, float] | None:
    """(a, b) of the least-squares fit ``ln t = ln a + b depth`` of the pushes' solve seconds
    ``t`` against their depths (mm); None with fewer than three pushes or depths within 2 mm."""
    depth, seconds = np.asarray(fig["probe_disp_mm"]), np.asarray(fig["push_s"])
    if len(depth) < 3 or np.ptp(depth) < 2.0:
        return None
    b, ln_a = np.polyfit(depth, np.log(seconds), 1)
    return float(np.exp(ln_a)), float(b)


def estimates(push_s: float, overhead_s: float) -> dict:
    """Minutes for N pushes on W workers: ``N (push_s + overhead_s) / W``."""
    return {f"{w}w_{n}": n * (push_s + overhead_s) / w / 60.0
            for w in ESTIMATE_WORKERS for n in ESTIMATE_PUSHES}


def print_table(fig: dict, wall_s: float, workers: int, est: dict) -> None:
    model = fig.get("depth_model")
    where = (f"read from {fig['store']}" if "store" in fig
             else f"on {workers} workers in {wall_s / 60:.1f} min")
    print(f"{fig['pushes']} pushes ({fig['failures']} draws not answered and redrawn) {where}: "
          f"a push {fig['push_s_mean']:.1f} s "
          f"(median {fig['push_s_median']:.1f}, 90 % {fig['push_s_p90']:.1f}); "
          + ("" if model is None else
             f"fitted {model[0]:.3g} exp({model[1]:.3g} depth) s, over the protocol's depths "
             f"(0-{fig['max_push_mm']:g} mm) {fig['push_s_expected']:.0f} s a push; ")
          + f"{fig['sample_bytes'] / 1e3:.0f} kB sent back a push; {fig['overhead_s']:.2f} s "
          "a push beyond its solve")
    print("estimated wall time (min): " + "; ".join(
        f"{w} workers: " + ", ".join(f"N={n} {est[f'{w}w_{n}']:.1f}" for n in ESTIMATE_PUSHES)
        for w in ESTIMATE_WORKERS))


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("case", nargs="?", help="a case folder (default: the built-in phantom)")
    p.add_argument("--samples", type=int, default=24, help="pushes solved (one held out)")
    p.add_argument("--workers", type=int, default=2, help="LocalCluster worker processes")
    p.add_argument("--fine", type=float, default=4.0, help="tetrahedra near the push, mm")
    p.add_argument("--size", type=float, default=10.0, help="tetrahedra elsewhere, mm")
    p.add_argument("--store", type=Path, help="a P2 refine case folder whose pushes to read "
                   "instead of solving new ones")
    p.add_argument("--result-name", help="result file name (default p2-teacher-<case>)")
    p.add_argument("--no-result-file", action="store_true", help="write no result file")
    return p


def solved_figures(args: argparse.Namespace) -> tuple[dict, str]:
    """``--samples`` pushes solved through the LocalCluster: their figures, the case's name."""
    with tempfile.TemporaryDirectory(prefix="p2teacher-") as scratch:
        case_dir, name = source_case(args.case, Path(scratch))
        refine_dir = p2_refine_case(case_dir, Path(scratch) / "work", args)
        wall_s, _ = solve_through_cluster(refine_dir, args.workers)
        fig = push_figures(refine_dir)
        fig["max_push_mm"] = float(load_config(refine_dir).probe.max_push_mm)
    fig["wall_s"], fig["workers"] = wall_s, args.workers
    fig["overhead_s"] = max(0.0, (wall_s * args.workers - sum(fig["push_s"])) / fig["pushes"])
    fig["fine_mm"], fig["size_mm"] = args.fine, args.size
    return fig, name


def stored_figures(refine_dir: Path) -> tuple[dict, str]:
    """The figures of the pushes ``refine_dir`` (a P2 refine case) holds, no wall time or
    overhead; the name of the case it refines."""
    cfg = load_config(refine_dir)
    if cfg.dataset.teacher != "p2":
        raise SystemExit(f"error: {refine_dir}: not a P2 teacher's data set "
                         f"([dataset] teacher = {cfg.dataset.teacher!r})")
    fig = push_figures(refine_dir)
    fig.update(max_push_mm=float(cfg.probe.max_push_mm), wall_s=0.0, workers=0, overhead_s=0.0,
               fine_mm=float(cfg.dataset.teacher_fine_mm),
               size_mm=float(cfg.dataset.teacher_size_mm), store=str(refine_dir))
    return fig, refine_dir.resolve().parent.name


def main(argv: list[str] | None = None) -> int:
    args = parser().parse_args(argv)
    if args.samples < 2 or args.workers < 1 or not (0 < args.fine <= args.size):
        print("error: --samples >= 2, --workers >= 1 and 0 < --fine <= --size",
              file=sys.stderr)
        return 2
    if args.store is not None:
        fig, name = stored_figures(args.store)
    else:
        fig, name = solved_figures(args)
    model = depth_model(fig)
    fig["depth_model"] = model
    fig["push_s_expected"] = (fig["push_s_mean"] if model is None
                              else p2_push_seconds(fig["max_push_mm"], model))
    est = estimates(fig["push_s_expected"], fig["overhead_s"])
    fig["estimate_min"] = est
    print_table(fig, fig["wall_s"], fig["workers"], est)
    if not args.no_result_file:
        write_result(args.result_name or f"p2-teacher-{name}", fig, speed_probes=speed_probes())
    print(f"RESULT push_s_mean={fig['push_s_mean']:.1f} push_s_p90={fig['push_s_p90']:.1f} "
          f"push_s_expected={fig['push_s_expected']:.1f} wall_min={fig['wall_s'] / 60:.2f} "
          f"overhead_s={fig['overhead_s']:.2f} "
          f"est_16w_400_min={est['16w_400']:.1f} est_64w_400_min={est['64w_400']:.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
