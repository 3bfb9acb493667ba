"""``CASE_DIR/dataset.zarr``: the training data of a case, one chunk per sample.

Layout (a Zarr v3 group; N = n_train + n_test; node arrays follow
:mod:`biopsynav.grid.index`):

* ``inputs`` (N, 4, nx, ny, nz) float32: channels 0-2 the contact-point displacement spread to
  the nodes as a trilinear-weighted average (mm, 0 away from the contact), channel 3 the
  trilinear weight sum ``W_P^T 1``;
* ``targets`` (N, 3, nx, ny, nz) float32: FE displacement of every node (mm, 0 at inactive
  nodes);
* ``done`` (N,) bool, one chunk per sample, written last: a sample is complete or absent;
* ``active_nodes`` (nx, ny, nz) bool;
* per-sample metadata (N,) or (N, 3): see :data:`META_FIELDS`;
* attrs: ``n_train``, ``n_test``, ``fingerprint`` (anatomy + grid), ``protocol_fingerprint``,
  ``protocol`` (what it hashes), ``node_shape``, ``format``, ``failures`` (the draws not kept:
  index, attempt, ``redraw`` for a same-place redraw (``[probe] too_deep_redraw``), ``kind``
  ``not_converged``, ``too_deep`` or ``implausible``, message, last Newton iterations).

Samples ``[0, n_train)`` are for training, ``[n_train, N)`` held out. Every chunk carries a
CRC-32C (:func:`checked_compressors`; stores written before it have none and are read unchecked).
Zarr's local store writes every chunk and metadata document through a temporary file and a
rename, so a kill leaves no torn chunk; the group itself is created in a temporary folder and
renamed into place.
"""

from __future__ import annotations

import hashlib
import json
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..config import CaseConfig, DatasetSection
from ..contact.constraints import is_elastic
from ..errors import FingerprintError, InputError
from ..fem.teacher import teacher_refinement
from ..layout import DATASET_NAME
from ..teacher_registry import builder_or_none

FORMAT = "biopsynav-dataset/1"
#: Bump when the protocol (draw order, input encoding) changes: old data is then refused.
PROTOCOL_VERSION = 1
#: ``[dataset] max_edge_stretch`` by default: not in the protocol (that of data sets made
#: before the check), any other value is.
DEFAULT_MAX_EDGE_STRETCH = DatasetSection().max_edge_stretch

#: name -> (trailing shape, dtype) of the per-sample metadata arrays.
META_FIELDS: dict[str, tuple[tuple[int, ...], str]] = {
    "center": ((3,), "float64"),
    "vertex": ((), "int64"),
    "long_axis": ((3,), "float64"),
    "direction": ((3,), "float64"),
    "force_n": ((), "float64"),
    "tilt_deg": ((), "float64"),
    "n_contact": ((), "int64"),
    "attempt": ((), "int64"),
    "max_disp_mm": ((), "float64"),
    "mean_disp_mm": ((), "float64"),
    "probe_disp_mm": ((), "float64"),
    "newton_iters": ((), "int64"),
    "residual": ((), "float64"),
    "solve_s": ((), "float64"),
}


def dataset_path(case_dir: str | Path) -> Path:
    return Path(case_dir) / DATASET_NAME


#: [probe] keys that only force patches use: not in the protocol of a data set of rigid
#: pushes alone (``rigid_share = 1``, as a ``[refine]`` data set), which a new force range
#: or its calibration then leaves valid.
FORCE_PATCH_KEYS = ("f_max_n", "train_force_exponent", "train_force_scale", "too_deep_redraw",
                    "calibrate_force", "max_tilt_deg", "depth_tolerance_mm")

#: [probe] values that a protocol leaves out, being what every data set had before the key
#: existed (:func:`protocol_dict`): a key missing from a stored protocol stands for them.
FORMER_PROBE_VALUES = {"train_force_exponent": 1.0, "train_force_scale": 1.0, "shape": "rectangle",
                       "rigid_share": 0.0, "too_deep_redraw": "elsewhere", "lesion_share": 0.0,
                       "max_chest_compression": 0.0, "train_depth_exponent": 1.0}


#: [solver] keys added after data sets were made, with the behaviour those data sets had: a key
#: at its former value leaves the protocol (and its fingerprint) as it was.
FORMER_SOLVER_VALUES = {"indefinite_tangent": "ldlt"}


def drop_former_values(section: dict, formers: dict) -> None:
    """Remove from a config ``section`` every key at its ``formers`` value (the behaviour of
    data sets made before the key existed), so that their protocol stays as it was."""
    for key, former in formers.items():
        if section.get(key) == former:
            section.pop(key)


def recorded_probe_value(protocol: dict, key: str) -> Any:
    """The stored ``protocol``'s [probe] ``key``; a key it leaves out reads as its
    :data:`FORMER_PROBE_VALUES` entry."""
    return (protocol.get("probe") or {}).get(key, FORMER_PROBE_VALUES[key])


def protocol_dict(cfg: CaseConfig, n_train: int, n_test: int, anatomy: Any = None) -> dict:
    """Everything besides anatomy and grid that decides the samples' content (``anatomy``,
    the case's, is read by a teacher other than the grid's: :func:`teacher_protocol`).

    [material] (without ``fictitious_stiffness`` when 0), the FE-model inputs of other
    sections ([anatomy] tissue_labels, [grid] min_fraction, and with rigid pushes [tracker]
    fem_contact, with its contact_stiffness
    when elastic), [solver] without ``backend``
    and ``threads`` (speed and round-off only; workers always factor on one thread) and without
    keys at their :data:`FORMER_SOLVER_VALUES`, [probe]
    (without ``contact_tolerance_mm``, ``max_chest_compression``, ``train_depth_exponent`` and
    ``rigid_share`` when there
    are no rigid pushes: the
    protocol of force patches is what it was; without :data:`FORCE_PATCH_KEYS` when every
    push is rigid; without ``lesion_reach_mm`` when no push is centred near a lesion; never
    ``calibration_pushes``: the calibration it found is recorded in the
    data set), and the seed, sizes, Newton budget and contact input of [dataset] (with
    :data:`MIXED_DRAWS` for a data set of both kinds).
    """
    solver = cfg.section_dict("solver")
    for key in ("backend", "threads"):
        solver.pop(key, None)
    drop_former_values(solver, FORMER_SOLVER_VALUES)  # data made before the key existed
    probe = cfg.section_dict("probe")
    fe_model = {"tissue_labels": cfg.anatomy.tissue_labels, "min_fraction": cfg.grid.min_fraction}
    if probe.get("rigid_share", 0.0) > 0.0:  # rigid pushes: the tracker's contact set and holds
        fe_model["fem_contact"] = cfg.tracker.fem_contact
        if is_elastic(cfg.tracker.fem_contact):
            fe_model["contact_stiffness"] = cfg.tracker.contact_stiffness
    else:  # force patches only: the protocol of before rigid pushes (rigid_share 0: below)
        probe.pop("contact_tolerance_mm", None)
        probe.pop("max_chest_compression", None)
        probe.pop("train_depth_exponent", None)
    probe.pop("calibration_pushes", None)  # its calibration is recorded in the data set
    if probe.get("lesion_share", 0.0) == 0.0:  # no push is centred near a lesion
        probe.pop("lesion_reach_mm", None)
    drop_former_values(probe, FORMER_PROBE_VALUES)  # e.g. uniform forces: the former protocol
    stretch = cfg.dataset.max_edge_stretch
    checks = {} if stretch == DEFAULT_MAX_EDGE_STRETCH else {"max_edge_stretch": stretch}
    material = cfg.section_dict("material")
    if material.get("fictitious_stiffness") == 0.0:  # none: the protocol of before the key
        material.pop("fictitious_stiffness")
    return {"version": PROTOCOL_VERSION, "material": material,
            "fe_model": fe_model,
            "solver": solver, "probe": without_unused_force_keys(probe),
            "dataset": {"seed": cfg.dataset.seed, "n_train": int(n_train),
                        "n_test": int(n_test), "newton_budget": cfg.dataset.newton_budget,
                        "contact_input": cfg.dataset.contact_input,
                        **mixed_draws(cfg), **teacher_protocol(cfg, anatomy), **checks}}


#: How a data set of both kinds places and draws them (:func:`biopsynav.probe.draw_index`);
#: such data sets made before it (kinds by chance, streams by sample index) have no such key.
MIXED_DRAWS = "interleaved-numbered-by-kind"


def mixed_draws(cfg: CaseConfig) -> dict:
    """The protocol's ``mixed_draws`` (:data:`MIXED_DRAWS`) for a data set of both kinds
    (``[probe] rigid_share`` between 0 and 1), nothing for one of one kind."""
    from ..probe import both_kinds

    return {"mixed_draws": MIXED_DRAWS} if both_kinds(cfg.probe.rigid_share) else {}


#: How a refined teacher's solutions reach the case grid: a least-squares fit that holds the
#: contact points of a rigid push (:class:`biopsynav.grid.transfer.FieldTransfer`); data sets
#: of before it (the fit alone) have no such key.
TEACHER_FIT = "holds-rigid-contact"


def without_unused_force_keys(probe: dict) -> dict:
    """The [probe] part of a protocol without :data:`FORCE_PATCH_KEYS` when every push is
    rigid (``rigid_share`` 1), else ``probe`` itself."""
    if probe.get("rigid_share", 0.0) < 1.0:
        return probe
    return {k: v for k, v in probe.items() if k not in FORCE_PATCH_KEYS}


def teacher_protocol(cfg: CaseConfig, anatomy: Any = None) -> dict:
    """The teacher grid's part of the protocol: nothing for the case grid itself (the protocol
    of before ``[dataset] teacher_refine``), else the refinement, the floor of its cells'
    weights (absent from data sets made before ``teacher_min_fraction``: 0.05 then) and how
    its solutions are fitted to the case grid (:data:`TEACHER_FIT`), and the order of a
    Richardson extrapolation from the case grid's solution (absent when off). Another
    teacher (``[dataset] teacher``, :mod:`biopsynav.teacher_registry`): its name and what its
    answers depend on (its ``protocol(cfg, anatomy)``; ValueError without the anatomy)."""
    builder = builder_or_none(cfg.dataset.teacher)
    if builder is not None:
        if anatomy is None:
            raise ValueError(f"the protocol of teacher {cfg.dataset.teacher!r} needs the "
                             "case's anatomy")
        return {"teacher": cfg.dataset.teacher,
                "teacher_protocol": builder.protocol(cfg, anatomy)}
    refine = teacher_refinement(cfg)
    if refine == 1:
        return {}
    order = float(cfg.dataset.teacher_extrapolation)
    extrapolation = {"teacher_extrapolation": order} if order > 0 else {}
    return {"teacher_refine": refine, "teacher_min_fraction": cfg.dataset.teacher_min_fraction,
            "teacher_fit": TEACHER_FIT, **extrapolation}


def protocol_fingerprint(protocol: dict) -> str:
    """SHA-256 of the canonical JSON of :func:`protocol_dict`."""
    return hashlib.sha256(json.dumps(protocol, sort_keys=True).encode()).hexdigest()


def failure_key(record: dict) -> tuple[int, int, int]:
    """What identifies a logged draw: its sample index, attempt and same-place redraw (0 for
    the attempt's own draw, and for records written before redraws existed)."""
    return int(record["index"]), int(record["attempt"]), int(record.get("redraw", 0))


@dataclass
class DatasetStore:
    """An open ``dataset.zarr`` (read-write), with handles on its arrays."""

    path: Path
    group: Any
    arrays: dict[str, Any]

    @property
    def n_total(self) -> int:
        return int(self.group.attrs["n_train"]) + int(self.group.attrs["n_test"])

    def done_mask(self) -> np.ndarray:
        """(N,) bool: complete samples."""
        return np.asarray(self.arrays["done"][:], dtype=bool)

    def failures(self) -> list[dict]:
        return list(self.group.attrs.get("failures", []))

    def write_sample(self, result: dict) -> None:
        """Write one converged sample: arrays, metadata, then ``done`` last."""
        i = int(result["index"])
        self.arrays["inputs"][i] = result["inputs"]
        self.arrays["targets"][i] = result["targets"]
        for name in META_FIELDS:
            self.arrays[name][i] = result[name]
        self.arrays["done"][i] = True

    def add_failures(self, records: list[dict]) -> None:
        """Append records of draws not kept (deduplicated on index, attempt and redraw)."""
        known = self.failures()
        seen = {failure_key(f) for f in known}
        new = [r for r in records if failure_key(r) not in seen]
        if new:
            self.group.attrs["failures"] = known + new

    def read_meta(self) -> dict[str, np.ndarray]:
        """The metadata arrays of the complete samples only, and their ``index``."""
        done = self.done_mask()
        out = {name: np.asarray(self.arrays[name][:])[done] for name in META_FIELDS}
        out["index"] = np.flatnonzero(done)
        return out


def create_store(path: Path, cfg: CaseConfig, fingerprint: str, protocol: dict,
                 n_train: int, n_test: int, node_shape: tuple[int, int, int],
                 active_nodes: np.ndarray) -> DatasetStore:
    """Create an empty store at ``path`` (built in a temporary folder, then renamed)."""
    import zarr

    n = int(n_train) + int(n_test)
    chunk = int(min(cfg.dataset.chunk_samples, n))
    tmp = Path(tempfile.mkdtemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp"))
    checked = {"compressors": checked_compressors()}
    try:
        group = zarr.open_group(str(tmp), mode="w")
        for name, channels in (("inputs", 4), ("targets", 3)):
            group.create_array(name, shape=(n, channels, *node_shape),
                               chunks=(chunk, channels, *node_shape), dtype="float32",
                               fill_value=0.0, **checked)
        group.create_array("done", shape=(n,), chunks=(1,), dtype="bool", fill_value=False,
                           **checked)
        for name, (tail, dtype) in META_FIELDS.items():
            group.create_array(name, shape=(n, *tail), chunks=(chunk, *tail), dtype=dtype,
                               fill_value=0, **checked)
        active = group.create_array("active_nodes", shape=tuple(node_shape),
                                    chunks=tuple(node_shape), dtype="bool", fill_value=False,
                                    **checked)
        active[...] = np.asarray(active_nodes, dtype=bool)
        group.attrs.update({
            "format": FORMAT, "n_train": int(n_train), "n_test": int(n_test),
            "fingerprint": fingerprint, "protocol_fingerprint": protocol_fingerprint(protocol),
            "protocol": protocol, "node_shape": [int(s) for s in node_shape],
            "units": {"inputs": "mm (channels 0-2), weight (channel 3)", "targets": "mm",
                      "force_n": "N", "center": "mm"},
            "failures": [],
        })
        tmp.rename(path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return open_store(path)


def checked_compressors() -> list:
    """Zstandard, then a CRC-32C of each compressed chunk (Zarr v3's ``crc32c`` codec): a
    damaged chunk fails to read instead of decoding to wrong numbers."""
    from zarr.codecs import Crc32cCodec, ZstdCodec

    return [ZstdCodec(), Crc32cCodec()]


def open_store(path: Path, mode: str = "r+") -> DatasetStore:
    """Open an existing store; raise InputError when it is not a biopsynav dataset."""
    import zarr

    hint = "; use --overwrite to replace it"
    try:
        group = zarr.open_group(str(path), mode=mode)
        attrs = dict(group.attrs)
    except Exception as exc:  # noqa: BLE001 - any read failure means unusable
        raise InputError(f"not a readable Zarr group ({type(exc).__name__}: {exc}){hint}",
                         str(path)) from None
    if attrs.get("format") != FORMAT:
        raise InputError(f"not a biopsynav dataset (format {attrs.get('format')!r}, expected "
                         f"{FORMAT!r}){hint}", str(path))
    names = ["inputs", "targets", "done", "active_nodes", *META_FIELDS]
    try:
        arrays = {name: group[name] for name in names}
    except Exception as exc:  # noqa: BLE001
        raise InputError(f"incomplete dataset: {type(exc).__name__}: {exc}{hint}",
                         str(path)) from None
    store = DatasetStore(path, group, arrays)
    if mode == "r":
        check_no_pending_growth(attrs, str(path))
    else:
        finish_growth(store)
    _check_layout(store, hint)
    return store


def _check_layout(store: DatasetStore, hint: str) -> None:
    attrs = store.group.attrs
    try:
        n = int(attrs["n_train"]) + int(attrs["n_test"])
        shape = tuple(int(s) for s in attrs["node_shape"])
        for key in ("fingerprint", "protocol_fingerprint"):
            str(attrs[key])
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"dataset attributes are damaged ({exc}){hint}", str(store.path)) \
            from None
    expect = {"inputs": (n, 4, *shape), "targets": (n, 3, *shape), "done": (n,),
              "active_nodes": shape}
    expect.update({name: (n, *tail) for name, (tail, _) in META_FIELDS.items()})
    for name, want in expect.items():
        got = tuple(store.arrays[name].shape)
        if got != want:
            raise InputError(f"array {name!r} has shape {got}, expected {want}{hint}",
                             str(store.path))


#: The store attribute holding a growth plan (:mod:`.grow`) until it is carried out.
RESIZE_ATTR = "resizing"
#: The per-sample arrays, resized along their first axis when a store grows.
SAMPLE_ARRAYS = ("inputs", "targets", "done", *META_FIELDS)


def finish_growth(store: DatasetStore) -> None:
    """Carry out the store's growth plan (:func:`biopsynav.dataset.grow.grow_store`), if it
    holds one: the samples to solve again marked not done, every per-sample array resized,
    then the attributes (sizes, protocol, failure records without those samples, no plan)
    written in one document. Idempotent, so a run killed half-way is completed by the next."""
    plan = store.group.attrs.get(RESIZE_ATTR)
    if plan is None:
        return
    again, n = checked_growth_plan(plan, store)
    for i in again:
        store.arrays["done"][i] = False
    for name in SAMPLE_ARRAYS:
        array = store.arrays[name]
        if array.shape[0] != n:
            array.resize((n, *array.shape[1:]))
    attrs = dict(store.group.attrs)
    attrs.pop(RESIZE_ATTR)
    dropped = set(again)
    attrs["failures"] = [f for f in attrs.get("failures", []) if failure_key(f)[0] not in dropped]
    attrs.update({key: plan[key] for key in ("n_train", "n_test", "protocol",
                                            "protocol_fingerprint")})
    store.group.attrs.put(attrs)


def checked_growth_plan(plan: Any, store: DatasetStore) -> tuple[list[int], int]:
    """The samples to solve again and the new sample count of a stored growth ``plan``;
    InputError, before anything is changed, when the plan is damaged (a missing or malformed
    field, a sample the store does not hold, fewer samples than stored)."""
    hint = "; run with --overwrite to discard the data set"
    try:
        again = [int(i) for i in plan["solve_again"]]
        n = int(plan["n_train"]) + int(plan["n_test"])
        for key in ("protocol", "protocol_fingerprint"):
            plan[key]  # noqa: B018  (present, or KeyError)
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f"the data set's growth plan ({RESIZE_ATTR!r}) is damaged "
                         f"({type(exc).__name__}: {exc}){hint}", str(store.path)) from None
    stored = int(store.arrays["done"].shape[0])
    if n < stored or any(not 0 <= i < stored for i in again):
        raise InputError(f"the data set's growth plan ({RESIZE_ATTR!r}) does not fit its "
                         f"{stored} samples{hint}", str(store.path))
    return again, n


def check_no_pending_growth(attrs: dict, path: str) -> None:
    """InputError for a read-only reader of a store whose growth was interrupted."""
    plan = attrs.get(RESIZE_ATTR)
    if plan is None:
        return
    to = (f"to {plan.get('n_train')} + {plan.get('n_test')} samples"
          if isinstance(plan, dict) else f"(its plan, {RESIZE_ATTR!r}, is damaged)")
    raise InputError(f"growing the data set {to} was interrupted; run `biopsynav generate` "
                     "(or `refine`) on the case to finish it", path)


def check_compatible(store: DatasetStore, fingerprint: str, protocol: dict) -> None:
    """Refuse (FingerprintError) a store made for another anatomy/grid or protocol."""
    attrs = store.group.attrs
    hint = "; run with --overwrite to discard it and start again"
    if attrs["fingerprint"] != fingerprint:
        raise FingerprintError("the data set was generated for another anatomy or grid "
                               f"(fingerprint {str(attrs['fingerprint'])[:12]}..., case "
                               f"{fingerprint[:12]}...){hint}", str(store.path))
    if not same_protocol(attrs, protocol):
        changed = _changed_sections(comparable_protocol(attrs.get("protocol")), protocol)
        raise FingerprintError("the data set was generated with another protocol (changed: "
                               f"{'; '.join(changed) or 'unknown'}){hint}, or set those "
                               "values in case.toml to keep it", str(store.path))


def same_protocol(attrs: Any, protocol: dict) -> bool:
    """Whether a store's attributes ``attrs`` record ``protocol``: the same fingerprint, or a
    store of rigid pushes alone made when its protocol still named the force patches' keys
    (:data:`FORCE_PATCH_KEYS`), which is the same protocol once they are left out."""
    if attrs["protocol_fingerprint"] == protocol_fingerprint(protocol):
        return True
    return protocol_fingerprint(comparable_protocol(attrs.get("protocol"))) == \
        protocol_fingerprint(protocol)


def comparable_protocol(stored: Any) -> dict:
    """A store's recorded protocol as today's :func:`protocol_dict` writes it (the force
    patches' keys left out of a protocol of rigid pushes alone)."""
    out = dict(stored) if isinstance(stored, dict) else {}  # a damaged record: compares unequal
    if isinstance(out.get("probe"), dict):
        out["probe"] = without_unused_force_keys(dict(out["probe"]))
    return out


def _changed_sections(old: dict, new: dict) -> list[str]:
    """What differs between a stored protocol ``old`` and the case's ``new``, one entry per
    key with both values, e.g. ``[probe] f_max_n (data set 3.0, case 4.0)``."""
    out = []
    for section in sorted(set(old) | set(new)):
        a, b = old.get(section), new.get(section)
        if a == b:
            continue
        if isinstance(a, dict) and isinstance(b, dict):
            keys = sorted(k for k in set(a) | set(b) if a.get(k) != b.get(k))
            out += [f"[{section}] {k} (data set {_recorded(a, section, k)}, case "
                    f"{_recorded(b, section, k)})" for k in keys]
        else:
            out.append(f"[{section}]")
    return out


def _recorded(values: dict, section: str, key: str) -> str:
    """One protocol value as text; a key left out reads as its former value."""
    if key in values:
        return repr(values[key])
    former = FORMER_PROBE_VALUES.get(key) if section == "probe" else None
    return "not recorded" if former is None else repr(former)


def remove_store(path: Path) -> None:
    """Delete a store folder (or a file squatting its name)."""
    if path.is_dir():
        shutil.rmtree(path)
    elif path.exists():
        path.unlink()
