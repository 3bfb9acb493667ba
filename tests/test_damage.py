"""Damage suite: every file of a small trained case truncated, bit-flipped, emptied, deleted.

For each damaged file, the commands ``info``, ``track``, ``evaluate``, ``report`` and ``train``
run in process on a copy of the case. Each must end with exit 0 and a usable result, or exit 2
with one line that names the damaged file: never a traceback, never an internal error.

A command is run on a damaged file when it opens that file in an undamaged run (Python's
``open`` audit event, which every reader of a case file goes through: numpy, zarr, torch and the
checksums of the exported models); a command that never opens the file behaves as in the
undamaged run, which the first test checks.
"""

from __future__ import annotations

import contextlib
import fnmatch
import io
import json
import shutil
import signal
import sys
import time
from pathlib import Path

import pytest

from biopsynav.cli import main
from biopsynav.layout import CACHE_DIR, COMPLIANCE_CACHE

DAMAGES = ("truncate", "flip", "empty", "delete")
OPS = ("info", "track", "evaluate", "report", "train")

#: Every kind of file of a trained case. The data set's arrays are represented by the group's
#: metadata, the four data arrays (metadata and a chunk each) and one of the per-sample
#: metadata arrays, all of which are written and read by the same code.
CASE_FILES = (
    "case.toml", "anatomy.npz", "grid.npz", "inputs/facts.json", "inputs/phantom_lesions.csv",
    "anatomy.png", "dataset.png", "dataset_summary.json",
    "dataset.zarr/zarr.json",
    "dataset.zarr/inputs/zarr.json", "dataset.zarr/inputs/c/3/0/0/0/0",
    "dataset.zarr/targets/zarr.json", "dataset.zarr/targets/c/3/0/0/0/0",
    "dataset.zarr/targets/c/15/0/0/0/0",
    "dataset.zarr/done/zarr.json", "dataset.zarr/done/c/3",
    "dataset.zarr/active_nodes/zarr.json", "dataset.zarr/active_nodes/c/0/0/0",
    "dataset.zarr/probe_disp_mm/zarr.json", "dataset.zarr/probe_disp_mm/c/3",
    "model/meta.json", "model/model.onnx", "model/model.ts", "model/checkpoint.pt",
    "model/best.pt", "model/history.json", "model/loss_curve.png",
    "eval/table1.json", "eval/error_histogram.png", "eval/largest_deformation.png",
    "eval/worst_sample.png", "report.html", "report.md", "report_files/timing.png",
)

_opened: list[str] | None = None


def _audit(event: str, args: tuple) -> None:
    if _opened is not None and event == "open" and isinstance(args[0], (str, Path)):
        _opened.append(str(Path(args[0]).resolve()))


sys.addaudithook(_audit)


class RanTooLong(Exception):
    pass


def _alarm(signum, frame):
    raise RanTooLong("a command of the damage suite ran for more than a minute")


def _run(argv: list[str], limit_s: int = 60) -> tuple[int, str, str]:
    """Run the CLI in process; (exit status, stderr, stdout). A command that runs away (a
    damaged file read as a different, bigger job) fails instead of hanging the suite."""
    err, out = io.StringIO(), io.StringIO()
    previous = signal.signal(signal.SIGALRM, _alarm)
    outer_left, _ = signal.setitimer(signal.ITIMER_REAL, limit_s)  # pytest-timeout's, if set
    started = time.monotonic()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(out):
            try:
                rc = main(argv)
            except SystemExit as exc:  # argparse
                rc = int(exc.code or 0)
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)
        if outer_left > 0:  # the suite's own per-test limit runs on
            signal.setitimer(signal.ITIMER_REAL,
                             max(outer_left - (time.monotonic() - started), 1e-3))
    return rc, err.getvalue(), out.getvalue()


def _argv(op: str, case: Path, poses: Path) -> list[str]:
    return {"info": ["info", str(case)],
            "track": ["track", str(case), "--poses", str(poses), "--out",
                      str(case.parent / "tracked.csv")],
            "evaluate": ["evaluate", str(case), "--table1-only"],
            "report": ["report", str(case)],
            "train": ["train", str(case)]}[op]


@pytest.fixture(scope="module")
def readers(trained_case: Path, poses_csv: Path, tmp_path_factory) -> dict[str, set[str]]:
    """For each command, the case files (relative paths) it opens in an undamaged run."""
    global _opened
    case = tmp_path_factory.mktemp("clean") / "case"
    shutil.copytree(trained_case, case)
    root = case.resolve()
    out = {}
    for op in OPS:
        _opened = []
        try:
            rc, err, _ = _run(_argv(op, case, poses_csv))
        finally:
            opened, _opened = _opened, None
        assert rc == 0, (op, err)
        out[op] = {str(Path(p).relative_to(root)) for p in opened
                   if Path(p).is_relative_to(root)}
    return out


def test_every_file_of_a_trained_case_is_covered(trained_case: Path, readers):
    files = {str(p.relative_to(trained_case)) for p in trained_case.rglob("*") if p.is_file()}
    files = {f for f in files if not f.startswith("dataset.zarr/")
             and not Path(f).name.startswith(".") and not _kept_compliance(f)}
    listed = {f for f in CASE_FILES if not f.startswith("dataset.zarr/")}
    assert files <= listed, files - listed
    for name in CASE_FILES:
        assert (trained_case / name).is_file(), name
    # the commands do read the case: the audit sees them
    assert "case.toml" in readers["info"] and "model/meta.json" in readers["track"]
    assert "dataset.zarr/targets/c/3/0/0/0/0" in readers["train"]


def _kept_compliance(rel: str) -> bool:
    """Whether ``rel`` is a kept contact compliance, named by a hash
    (``cache/contact_compliance-<sha256>.npz``): :func:`test_a_damaged_cache_is_harmless`."""
    return fnmatch.fnmatch(rel, f"{CACHE_DIR}/{COMPLIANCE_CACHE}-*.npz")


def _damage(path: Path, how: str) -> None:
    data = path.read_bytes()
    if how == "truncate":
        path.write_bytes(data[: len(data) // 2])
    elif how == "flip":
        flipped = bytearray(data)
        flipped[len(data) // 2] ^= 0x10
        path.write_bytes(bytes(flipped))
    elif how == "empty":
        path.write_bytes(b"")
    else:
        path.unlink()


def _names(message: str, rel: str) -> bool:
    """Whether an error line names the damaged file (a data set chunk: the store)."""
    target = "dataset.zarr" if rel.startswith("dataset.zarr/") else rel
    return target in message or Path(target).name in message


def _usable(op: str, case: Path, out: str) -> None:
    """The result of a command that exited 0 can be read back (``out``: its stdout)."""
    if op == "info":  # the whole summary, the stages that are done among it
        first = out.splitlines()[0] if out else ""
        assert first.startswith("case ") and first.endswith(f"({case})"), out
        assert "  tissues   label" in out, out
        assert "  stages    anatomy done, grid done" in out, out
    elif op == "track":
        lines = (case.parent / "tracked.csv").read_text().splitlines()
        assert lines[0].endswith("status,reason") and len(lines) > 1
    elif op == "evaluate":
        assert json.loads((case / "eval" / "table1.json").read_text())["mean_e_mm"] >= 0
    elif op == "report":
        assert "Table 1" in (case / "report.html").read_text()
    elif op == "train":
        from biopsynav.inference.model_files import read_meta

        assert read_meta(case / "model")["envelope"]["max_contact_disp_mm"] > 0


@pytest.mark.parametrize("how", DAMAGES)
@pytest.mark.parametrize("rel", CASE_FILES)
def test_damaged_file_is_named_or_harmless(rel, how, trained_case, poses_csv, readers,
                                           tmp_path):
    ops = [op for op in OPS if rel in readers[op]]
    if not ops:
        pytest.skip(f"no command opens {rel}")
    case = tmp_path / "case"
    shutil.copytree(trained_case, case)
    _damage(case / rel, how)
    for op in ops:
        rc, err, out = _run(_argv(op, case, poses_csv))
        assert "Traceback" not in err, (op, err)
        if rc == 0:
            _usable(op, case, out)
            continue
        lines = [line for line in err.splitlines() if not line.startswith("biopsynav: warning")]
        lines = [line for line in lines if "it/s]" not in line and line.strip()]
        assert rc == 2, (op, rc, err)
        assert len(lines) == 1 and lines[0].startswith("biopsynav: error: "), (op, err)
        assert _names(lines[0], rel), (op, lines[0])


@pytest.mark.parametrize("how", DAMAGES)
def test_a_damaged_cache_is_harmless(how, trained_case, poses_csv, readers, tmp_path):
    """The kept contact compliance is computed again, never read damaged: every command that
    opens it answers as with it whole, and leaves it whole."""
    kept = [f for op in OPS for f in readers[op] if _kept_compliance(f)]
    assert kept, "no command opened the kept contact compliance"
    ops = [op for op in OPS if set(kept) & set(readers[op])]
    case = tmp_path / "case"
    shutil.copytree(trained_case, case)
    _damage(case / kept[0], how)
    for op in ops:
        rc, err, out = _run(_argv(op, case, poses_csv))
        assert rc == 0 and "Traceback" not in err, (op, rc, err)
        _usable(op, case, out)
    import numpy as np

    from biopsynav.contact.greens import read_kept
    with np.load(case / kept[0]) as whole:
        assert read_kept(case / kept[0], whole["zt"].shape, np.float32) is not None
