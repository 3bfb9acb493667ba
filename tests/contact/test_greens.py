"""The contact compliance ``Z`` is computed once per case and kept in its cache folder: a later
process reads it, a damaged or foreign file is computed again, another model gets its own and
the old one is deleted."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

import biopsynav.contact.greens as G
from biopsynav.case import Case
from biopsynav.config import load_config, save_config
from biopsynav.layout import COMPLIANCE_CACHE


@pytest.fixture()
def case_dir(base_case: Path, tmp_path: Path) -> Path:
    dst = tmp_path / "case"
    shutil.copytree(base_case, dst, ignore=shutil.ignore_patterns("cache"))
    return dst


def kept_files(case_dir: Path) -> list[Path]:
    cache = Case.load(case_dir).paths.cache
    return sorted(cache.glob(f"{COMPLIANCE_CACHE}-*.npz")) if cache.is_dir() else []


def never_solved(*_args, **_kw):
    raise AssertionError("Z was computed again instead of read from the case's cache")


def test_the_second_load_reads_what_the_first_computed(case_dir, monkeypatch):
    first = G.ContactCompliance.from_case(Case.load(case_dir))
    assert len(kept_files(case_dir)) == 1
    monkeypatch.setattr(G, "solved_rows", never_solved)
    second = G.ContactCompliance.from_case(Case.load(case_dir))
    assert second.zt.dtype == np.float32 and np.array_equal(first.zt, second.zt)
    assert np.array_equal(first.cols, second.cols)


def test_a_damaged_kept_file_is_computed_again_and_replaced(case_dir):
    first = G.ContactCompliance.from_case(Case.load(case_dir))
    (path,) = kept_files(case_dir)
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte among Z's: the zip's CRC-32 sees it
    path.write_bytes(bytes(data))
    again = G.ContactCompliance.from_case(Case.load(case_dir))
    assert np.array_equal(first.zt, again.zt)
    assert G.read_kept(path, first.zt.shape, np.float32) is not None  # whole again
    path.write_bytes(b"")  # an empty file likewise
    assert np.array_equal(G.ContactCompliance.from_case(Case.load(case_dir)).zt, first.zt)


def test_what_a_killed_write_left_is_deleted_when_the_file_is_written(case_dir):
    cache = Case.load(case_dir).paths.cache
    G.ContactCompliance.from_case(Case.load(case_dir))
    (path,) = kept_files(case_dir)
    path.unlink()
    debris = cache / f".{path.name}.abc123.tmp"
    debris.write_bytes(b"half a file")
    G.ContactCompliance.from_case(Case.load(case_dir))
    assert not debris.exists() and kept_files(case_dir) == [path]


def test_another_material_gets_its_own_file_which_replaces_the_old(case_dir):
    soft = G.ContactCompliance.from_case(Case.load(case_dir))
    (old,) = kept_files(case_dir)
    cfg = load_config(case_dir)
    cfg.material.tissues = {name: {**law, "E_mpa": 2 * law["E_mpa"]}
                            for name, law in cfg.material.tissues.items()}
    save_config(case_dir, cfg)
    stiff = G.ContactCompliance.from_case(Case.load(case_dir))
    (new,) = kept_files(case_dir)  # the case's model changed: its old Z is deleted
    assert new != old and not old.exists()
    np.testing.assert_allclose(stiff.zt, soft.zt / 2, rtol=1e-4, atol=1e-9)
    other = new.with_name(old.name)  # one that cannot be deleted stays, and is no harm
    other.mkdir()
    assert G.remove_other_compliances(new) == [] and other.is_dir()


def test_a_cache_that_cannot_be_written_only_costs_the_computation(case_dir):
    Case.load(case_dir).paths.cache.write_text("a file where the cache folder would be")
    a = G.ContactCompliance.from_case(Case.load(case_dir))
    b = G.ContactCompliance.from_case(Case.load(case_dir))
    assert np.array_equal(a.zt, b.zt)
    assert Case.load(case_dir).paths.cache.is_file()
