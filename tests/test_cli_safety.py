"""What a user names or shares is never damaged: output paths, concurrent writers, read-only
folders, full disks. Every failure is one line and exit status 2."""

from __future__ import annotations

import contextlib
import hashlib
import io
import os
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest

from biopsynav.cli import main

BIN = Path(sys.executable).with_name("biopsynav")


def run(argv: list[str]) -> tuple[int, str]:
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        rc = main([str(a) for a in argv])
    return rc, err.getvalue()


def one_line_error(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip() and "it/s]" not in line]
    assert len(lines) == 1 and lines[0].startswith("biopsynav: error: "), err
    assert "Traceback" not in err
    return lines[0]


def digests(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file() and p.name != ".biopsynav.lock"}


def test_track_out_refuses_symlink_fifo_and_folder(trained_case, poses_csv, tmp_path):
    target = tmp_path / "precious.txt"
    target.write_text("keep me\n")
    link = tmp_path / "link.csv"
    link.symlink_to(target)
    fifo = tmp_path / "fifo.csv"
    os.mkfifo(fifo)
    for out, what in ((link, "symbolic link"), (fifo, "FIFO"), (tmp_path, "folder")):
        rc, err = run(["track", trained_case, "--poses", poses_csv, "--out", out])
        assert rc == 2 and what in one_line_error(err) and str(out) in err
    assert link.is_symlink() and target.read_text() == "keep me\n"
    assert fifo.is_fifo()
    rc, err = run(["track", trained_case, "--poses", poses_csv, "--out",
                   tmp_path / "no" / "such" / "folder.csv"])
    assert rc == 2 and "does not exist" in one_line_error(err)
    rc, _ = run(["track", trained_case, "--poses", poses_csv, "--out", tmp_path / "ok.csv"])
    assert rc == 0 and (tmp_path / "ok.csv").read_text().startswith("frame,lesion_id")


def test_show_out_refuses_a_symlink(trained_case, tmp_path):
    target = tmp_path / "target.png"
    target.write_bytes(b"not a picture of ours")
    link = tmp_path / "pic.png"
    link.symlink_to(target)
    rc, err = run(["show", trained_case, "--out", link])
    assert rc == 2 and "symbolic link" in one_line_error(err)
    assert target.read_bytes() == b"not a picture of ours"
    rc, err = run(["show", trained_case, "--out", tmp_path / "notes.txt"])
    assert rc == 2 and "name a .png file" in one_line_error(err)
    assert not (tmp_path / "notes.txt").exists()


def test_latin1_poses_csv_is_one_line(trained_case, poses_csv, tmp_path):
    bad = tmp_path / "latin1.csv"
    bad.write_bytes(poses_csv.read_bytes().replace(b"frame", "fr\xe4me".encode("latin-1"), 1))
    rc, err = run(["track", trained_case, "--poses", bad, "--out", tmp_path / "o.csv"])
    assert rc == 2 and "not UTF-8" in one_line_error(err) and str(bad) in err


def test_second_writer_is_refused_and_names_the_first(reference, tmp_path):
    case = tmp_path / "case"
    shutil.copytree(reference, case)
    shutil.rmtree(case / "dataset.zarr")
    first = subprocess.Popen([str(BIN), "generate", str(case), "--workers", "1"],
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        lock = case / ".biopsynav.lock"
        deadline = time.monotonic() + 60
        while not (lock.is_file() and lock.read_text().startswith("generate")):
            assert time.monotonic() < deadline and first.poll() is None, "first never locked"
            time.sleep(0.05)
        rc, err = run(["generate", case, "--overwrite"])
        line = one_line_error(err)
        assert rc == 2 and "another command is writing" in line
        assert f"generate (pid {first.pid}" in line
        assert run(["train", case])[0] == 2
    finally:
        _, first_err = first.communicate(timeout=300)
    assert first.returncode == 0, first_err
    from biopsynav.network.data import load_dataset

    data = load_dataset(case)  # the first job's store is whole: nobody deleted it under it
    assert int(data.train_idx.numel() + data.test_idx.numel()) == 16


def _mount_tmpfs(path: Path, size: str) -> None:
    path.mkdir(parents=True, exist_ok=True)
    proc = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)],
                          capture_output=True, text=True)
    if proc.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here ({proc.stderr.strip() or 'not permitted'})")


@contextlib.contextmanager
def tmpfs(path: Path, size: str):
    _mount_tmpfs(path, size)
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


WRITING = [["show"], ["simulate", "--force", "0", "0", "-1", "--at", "0", "0", "75"],
           ["generate"], ["generate", "--overwrite"], ["train"], ["evaluate", "--table1-only"],
           ["report"], ["run"], ["init", "--phantom", "--overwrite", "--cell-size", "15"]]


def test_read_only_case_folder(trained_case, poses_csv, tmp_path):
    with tmpfs(tmp_path / "mnt", "64m") as mnt:
        case = mnt / "case"
        shutil.copytree(trained_case, case)
        before = digests(case)
        proc = subprocess.run(["mount", "-o", "remount,ro", str(mnt)], capture_output=True,
                              text=True)
        if proc.returncode != 0:
            pytest.skip(f"cannot remount read-only here ({proc.stderr.strip()})")
        assert run(["info", case])[0] == 0
        rc, _ = run(["track", case, "--poses", poses_csv, "--out", tmp_path / "t.csv"])
        assert rc == 0
        for argv in WRITING:
            rc, err = run([argv[0], case, *argv[1:]])
            assert rc == 2, (argv, err)
            assert "Read-only file system" in one_line_error(err), (argv, err)
        assert digests(case) == before


def test_full_disk_damages_nothing(trained_case, tmp_path):
    with tmpfs(tmp_path / "mnt", "48m") as mnt:
        case = mnt / "case"
        shutil.copytree(trained_case, case)
        (case / "report.html").unlink()
        (case / "eval" / "table1.json").unlink()
        before = digests(case)
        with open(mnt / "filler", "wb", buffering=0) as fh:  # fill the disk to the last byte
            for block in (1 << 16, 512, 1):
                with contextlib.suppress(OSError):
                    while True:
                        fh.write(b"\0" * block)
        # (not generate --overwrite nor init --overwrite: they discard the old files first, as
        # asked, which frees the disk)
        for argv in [a for a in WRITING if "--overwrite" not in a]:
            rc, err = run([argv[0], case, *argv[1:]])
            assert rc == 2, (argv, err)
            assert "No space left on device" in one_line_error(err), (argv, err)
            assert digests(case) == before, argv  # nothing damaged, nothing half-written


@pytest.mark.parametrize("iterations", ["-3", "0"])
def test_train_with_no_iterations_is_refused_and_keeps_the_model(trained_case, iterations):
    """`train --iterations -3` used to train for no iteration and write that untrained network
    over the case's model; the count is refused where it enters, the model left as it was."""
    from biopsynav.errors import InputError
    from biopsynav.network.train import train_case

    before = digests(trained_case / "model")
    rc, err = run(["train", trained_case, "--iterations", iterations])
    assert rc == 2 and "--iterations: must be >= 1" in one_line_error(err)
    with pytest.raises(InputError, match="--iterations: must be >= 1"):
        train_case(trained_case, iterations=int(iterations), progress=False)
    assert digests(trained_case / "model") == before


@pytest.mark.parametrize("command", ["run", "demo", "generate", "refine", "evaluate"])
def test_a_negative_worker_count_is_refused_before_any_stage(command, trained_case, tmp_path):
    """`run --workers -2` used to start its stages (and `demo` its estimate) first."""
    case = tmp_path / "new-case" if command == "demo" else trained_case
    before = digests(trained_case)
    rc, err = run([command, case, "--workers", "-1"])
    assert rc == 2 and "--workers: must be >= 0 (0: one per core), got -1" in one_line_error(err)
    assert not (tmp_path / "new-case").exists() and digests(trained_case) == before


def test_run_case_refuses_a_negative_worker_count_before_any_stage(tmp_path):
    from biopsynav.errors import InputError
    from biopsynav.pipeline import run_demo

    with pytest.raises(InputError, match="--workers: must be >= 0"):
        run_demo(tmp_path / "demo", workers=-1)
    assert not (tmp_path / "demo").exists()


@pytest.mark.parametrize("size", ["0", "-1", "nan", "inf"])
def test_init_refuses_a_cell_size_that_is_not_a_size(size, tmp_path):
    """`--cell-size 0` used to build the case with the default cell size."""
    rc, err = run(["init", tmp_path / "c", "--phantom", "--cell-size", size])
    assert rc == 2 and "[grid] cell_size_mm" in one_line_error(err)
    assert not (tmp_path / "c").exists()


def test_serve_checks_its_addresses_before_loading_the_tracker(tmp_path):
    """A bad --listen is named at once, not after the tracker loads: here the case has no
    model, whose error would otherwise come first."""
    from biopsynav.case import make_phantom_case
    from biopsynav.errors import InputError
    from biopsynav.igtl.service import serve

    case = make_phantom_case(tmp_path / "untrained")
    for kwargs, where in (({"listen_addr": "notaport"}, "--listen"),
                          ({"tracker_addr": "127.0.0.1:99999"}, "--tracker")):
        with pytest.raises(InputError) as caught:
            serve(case, **kwargs)
        assert caught.value.where == where, caught.value
