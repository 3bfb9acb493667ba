"""Integrity of what generation and training write: checksummed chunks, complete data sets,
checksummed model descriptions, unmapped tissue labels refused before any worker starts."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from biopsynav.errors import InputError
from biopsynav.network.data import load_dataset


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def test_flipped_bit_in_a_targets_chunk_is_refused(reference, tmp_path):
    case = _copy(reference, tmp_path / "case")
    chunk = case / "dataset.zarr" / "targets" / "c" / "5" / "0" / "0" / "0" / "0"
    data = bytearray(chunk.read_bytes())
    data[len(data) // 3] ^= 0x04  # one bit
    chunk.write_bytes(bytes(data))
    with pytest.raises(InputError, match="array 'targets' is damaged") as err:
        load_dataset(case)
    assert "dataset.zarr" in str(err.value) and "generate" in str(err.value)


def test_deleted_active_nodes_chunk_is_refused(reference, tmp_path):
    case = _copy(reference, tmp_path / "case")
    (case / "dataset.zarr" / "active_nodes" / "c" / "0" / "0" / "0").unlink()
    with pytest.raises(InputError, match="'active_nodes' lacks 1 of its 1 chunks"):
        load_dataset(case)


def test_train_refuses_an_unfinished_data_set(reference, tmp_path):
    from biopsynav.network.train import train_case

    case = _copy(reference, tmp_path / "case")
    for i in (3, 15):  # as a generate killed before these samples were written
        (case / "dataset.zarr" / "done" / "c" / str(i)).unlink()
    with pytest.raises(InputError, match="incomplete: 14 of 16 samples"):
        train_case(case, iterations=2, progress=False)
    assert not (case / "model" / "meta.json").exists()


def test_edited_envelope_in_meta_json_is_refused(trained_case, tmp_path):
    from biopsynav.inference.model_files import read_meta

    case = _copy(trained_case, tmp_path / "case")
    path = case / "model" / "meta.json"
    meta = json.loads(path.read_text())
    meta["envelope"]["max_probe_disp_mm"] *= 3  # a wider safety envelope than trained
    path.write_text(json.dumps(meta, indent=2))
    with pytest.raises(InputError, match="does not match its checksum"):
        read_meta(case / "model")
    meta["envelope"]["max_probe_disp_mm"] = float("inf")
    del meta["checksum"]  # a model description without checksum is still checked for values
    path.write_text(json.dumps(meta))
    with pytest.raises(InputError, match="envelope values must be finite"):
        read_meta(case / "model")
    meta["envelope"]["max_probe_disp_mm"] = 10.0
    meta["node_shape"] = "11,9,7"
    path.write_text(json.dumps(meta))
    with pytest.raises(InputError, match="node_shape must be three node counts"):
        read_meta(case / "model")


def test_truncated_checkpoint_is_reported_and_kept_aside(trained_case, tmp_path, capfd):
    from biopsynav.network.train import CHECKPOINT, train_case

    case = _copy(trained_case, tmp_path / "case")
    ckpt = case / "model" / CHECKPOINT
    damaged = ckpt.read_bytes()[: ckpt.stat().st_size // 2]
    ckpt.write_bytes(damaged)
    summary = train_case(case, iterations=20, progress=False)
    err = capfd.readouterr().err
    assert "warning" in err and str(ckpt) in err and "iteration 0" in err
    kept = list(ckpt.parent.glob(f"{CHECKPOINT}.damaged-*"))
    assert len(kept) == 1 and kept[0].read_bytes() == damaged  # kept aside, not overwritten
    assert summary.resumed_from == 0 and summary.finished
    assert ckpt.is_file() and ckpt.read_bytes() != damaged


def test_unmapped_tissue_label_is_refused_before_workers_start(reference, tmp_path, capfd):
    """A cell label with no [anatomy] tissue_labels entry: one line naming it, at `init` (via
    the same check) and at `generate`, never a crash of the worker pool."""
    from biopsynav.case import Case
    from biopsynav.cli import main
    from biopsynav.fem.tissues import label_tissues

    case_dir = _copy(reference, tmp_path / "case")
    case = Case.load(case_dir)
    with pytest.raises(InputError, match="tissue labels 7 with no tissue"):
        label_tissues(np.array([7]), case.cfg, case.anatomy)
    share = np.zeros((*case.grid.cell_shape, 1), np.float32)
    share[tuple(np.argwhere(case.grid.active_cells)[:5].T)] = 1.0
    case.grid.label_values, case.grid.label_share = np.array([7]), share
    case.grid.save(case_dir / "grid.npz")
    shutil.rmtree(case_dir / "dataset.zarr")
    rc = main(["generate", str(case_dir), "--workers", "1"])
    out = capfd.readouterr()
    assert rc == 2 and "Traceback" not in out.err
    assert out.err.strip().splitlines() == [line for line in out.err.strip().splitlines()
                                            if "tissue labels 7 with no tissue" in line]
    assert not (case_dir / "dataset.zarr").exists()


def test_a_negative_worker_count_is_refused_before_the_calibration_and_the_store(
        reference, base_case, tmp_path, capfd):
    """`generate --workers -1` (the force calibration's processes as well as the samples'):
    one line naming the option, exit 2, and no data set created or touched."""
    import hashlib

    from biopsynav.cli import main
    from biopsynav.config import load_config, save_config

    def tree(folder: Path) -> dict:
        return {p.relative_to(folder): hashlib.sha256(p.read_bytes()).hexdigest()
                for p in sorted(folder.rglob("*")) if p.is_file()}

    done = _copy(reference, tmp_path / "done")
    fresh = _copy(base_case, tmp_path / "fresh")
    cfg = load_config(fresh)
    cfg.probe.calibrate_force = True  # a calibration would run first
    save_config(fresh, cfg)
    before = tree(done / "dataset.zarr")
    for case_dir in (done, fresh):
        rc = main(["generate", str(case_dir), "--workers", "-1"])
        err = capfd.readouterr().err
        assert rc == 2 and "Traceback" not in err
        assert "--workers: must be >= 0 (0: one per core), got -1" in err
        assert len(err.strip().splitlines()) == 1
    assert tree(done / "dataset.zarr") == before
    assert not (fresh / "dataset.zarr").exists()
