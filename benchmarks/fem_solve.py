"""FE solve speed: biopsynav against scikit-fem on the built-in phantom.

The same problem in both: the phantom at the default grid (about 2,200 active cells), the
default material (neo-Hookean) and stiffness, a probe push at 30 degrees from the inward
normal on a 50 x 10 mm patch, large enough for >= 30 mm maximum displacement, the same
Newton tolerance (|R| <= 1e-8 |R0| and |du| <= 1e-8 |u|). scikit-fem assembles its own weak
form (``tests/peers/skfem_peer.py``) and solves with SciPy's default sparse solver. Also
times biopsynav at two and four times the cell count.

Usage: ``python benchmarks/fem_solve.py [--repeats N] [--peer-repeats N] [--force F]``.
The last line reads ``RESULT fem_ms=... peer_ms=... ratio=... max_disp_mm=... newton_iters=...``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from biopsynav.case import make_phantom_case
from biopsynav.fem import FEModel, Loads, SolverSettings, solve
from biopsynav.grid.embedding import Embedding
from biopsynav.probe import nodal_forces
from biopsynav.simulate import patch_at

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository: tests.peers
from tests.peers.skfem_peer import SkfemModel  # noqa: E402

from resultfile import write_result  # noqa: E402  (benchmarks/, this script's folder)
from speedprobe import speed_probes  # noqa: E402

PUSH_AT_MM = np.array([20.0, 10.0, 80.0])
TILT_DEG = 30.0


def push_forces(case, total_force_n: float) -> np.ndarray:
    """Node forces (n_nodes, 3) N of a push at TILT_DEG from the inward normal."""
    anatomy, cfg = case.anatomy, case.cfg
    patch = patch_at(anatomy, PUSH_AT_MM, tuple(cfg.probe.footprint_mm),
                     cfg.probe.depth_tolerance_mm)
    tilt = np.radians(TILT_DEG)
    direction = np.cos(tilt) * -patch.normal + np.sin(tilt) * patch.long_axis
    embedding = Embedding.build(case.grid, patch.points)
    return nodal_forces(embedding.matrix, total_force_n * direction)


def time_ours(model: FEModel, forces: np.ndarray, settings: SolverSettings,
              repeats: int) -> tuple[list[float], list, np.ndarray]:
    """Wall times (s) of ``repeats`` solves after one warm-up (JIT, analysis)."""
    u, report = solve(model, Loads(forces=forces), settings)
    times, reports = [], []
    for _ in range(repeats):
        start = time.perf_counter()
        u, report = solve(model, Loads(forces=forces), settings)
        times.append(time.perf_counter() - start)
        reports.append(report)
    return times, reports, u


def time_peer(model: FEModel, forces: np.ndarray, repeats: int, tol: float):
    peer = SkfemModel(model.nodes, model.hexes, model.weight, model.E_mpa, model.nu,
                      model.fixed, model.material)
    start = time.perf_counter()
    x, info = peer.solve(forces, tol=tol)
    times = [time.perf_counter() - start]
    for _ in range(repeats - 1):
        start = time.perf_counter()
        x, info = peer.solve(forces, tol=tol, increments=info["increments"])
        times.append(time.perf_counter() - start)
    return times, info, peer.dofs_to_nodal(x, model.n_nodes)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--peer-repeats", type=int, default=2)
    parser.add_argument("--force", type=float, default=3.0, help="total probe force, N")
    parser.add_argument("--fine-force", type=float, default=2.0,
                        help="force on the finer grids (N): they lock less, so the default "
                             "grid's force takes them past the push's stability limit")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        case = make_phantom_case(Path(tmp) / "phantom")
        settings = SolverSettings.from_config(case.cfg.solver)
        model = FEModel.from_case(case)
        forces = push_forces(case, args.force)
        print(f"phantom: {model.n_elements} active cells, {model.n_eq} unknowns, "
              f"E = {model.E_mpa.min() * 1e3:g} kPa, {model.material}, push {args.force} N "
              f"at {TILT_DEG:g} deg")
        times, reports, u = time_ours(model, forces, settings, args.repeats)
        fem_ms = 1e3 * float(np.median(times))
        iters = float(np.median([r.iterations for r in reports]))
        max_disp = reports[-1].max_displacement_mm
        factorisations = sum(1 for e in reports[-1].log if e["mode"] not in
                             ("reuse", "k0-cached"))
        print(f"biopsynav: median {fem_ms:.1f} ms per solve (min {1e3 * min(times):.1f}), "
              f"{iters:g} Newton iterations ({factorisations} factorisations), "
              f"{reports[-1].increments} increment(s), max displacement {max_disp:.1f} mm, "
              f"backend {reports[-1].backend}")
        peer_times, info, u_peer = time_peer(model, forces, args.peer_repeats,
                                             settings.tol_residual)
        peer_ms = 1e3 * float(np.median(peer_times))
        diff = float(np.abs(u - u_peer).max() / np.abs(u).max())
        print(f"scikit-fem: median {peer_ms:.0f} ms per solve, {info['iterations']} Newton "
              f"iterations in {info['increments']} increment(s); max nodal difference "
              f"{diff:.2e} of the max displacement")
        for factor in (2, 4):
            size = case.cfg.grid.cell_size_mm / factor ** (1.0 / 3.0)
            fine = make_phantom_case(Path(tmp) / f"phantom{factor}", cell_size_mm=size)
            fine_model = FEModel.from_case(fine)
            fine_times, fine_reports, _ = time_ours(
                fine_model, push_forces(fine, args.fine_force), settings, 2)
            print(f"{factor}x cells ({fine_model.n_elements} cells, {fine_model.n_eq} "
                  f"unknowns, {size:.2f} mm, {args.fine_force} N): median "
                  f"{1e3 * np.median(fine_times):.0f} ms per solve, "
                  f"{np.median([r.iterations for r in fine_reports]):g} iterations, max "
                  f"displacement {fine_reports[-1].max_displacement_mm:.1f} mm")
    print(f"RESULT fem_ms={fem_ms:.1f} peer_ms={peer_ms:.0f} ratio={peer_ms / fem_ms:.1f} "
          f"max_disp_mm={max_disp:.1f} newton_iters={iters:g}")
    write_result("fem-solve", {"fem_ms": fem_ms, "peer_ms": peer_ms,
                               "ratio": peer_ms / fem_ms, "max_disp_mm": max_disp,
                               "newton_iters": iters},
                 speed_probes=speed_probes())  # after the timings: it would load the machine


if __name__ == "__main__":
    main()
