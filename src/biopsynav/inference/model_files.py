"""Reading and checking a model folder for deployment: ``meta.json`` (checksum, schema), the
exported files' checksums and the anatomy+grid fingerprint."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from ..config import is_finite_number
from ..errors import FingerprintError, InputError
from ..layout import META

FORMAT = "biopsynav-unet/1"


def sha256(path: Path) -> str:
    """Hex SHA-256 of a file."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def meta_checksum(meta: dict) -> str:
    """``sha256:`` + SHA-256 of the canonical JSON of ``meta`` without its ``checksum`` key."""
    body = {k: v for k, v in meta.items() if k != "checksum"}
    text = json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=True)
    return "sha256:" + hashlib.sha256(text.encode()).hexdigest()


RETRAIN = "retrain with `biopsynav train CASE` (after removing the model folder)"


def read_meta(model_dir: str | Path) -> dict:
    """``meta.json`` of a model folder, checked: its checksum (models written before it have
    none and are read unchecked) and the type and finiteness of every value the inference and
    the tracker use. InputError naming the file and what is wrong otherwise."""
    path = Path(model_dir) / META
    where = str(path)
    if not path.is_file():
        raise InputError("no trained model here (meta.json missing); run `biopsynav train`",
                         where)
    try:
        meta = json.loads(path.read_bytes().decode("utf-8"))
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise InputError(f"meta.json is corrupt ({exc}); {RETRAIN}", where) from None
    except OSError as exc:
        raise InputError(f"cannot read meta.json: {exc.strerror}", where) from None
    if not isinstance(meta, dict) or meta.get("format") != FORMAT:
        raise InputError(f"meta.json is not a {FORMAT} model description; {RETRAIN}", where)
    if "checksum" in meta and meta["checksum"] != meta_checksum(meta):
        raise InputError(f"meta.json does not match its checksum (damaged or edited by hand: "
                         f"the safety envelope it holds cannot be trusted); {RETRAIN}", where)
    problem = _meta_problem(meta)
    if problem:
        raise InputError(f"meta.json is damaged: {problem}; {RETRAIN}", where)
    return meta


def _finite(value: object, positive: bool = False) -> bool:
    return is_finite_number(value) and (not positive or value > 0)


def _meta_problem(meta: dict) -> str:
    """What is wrong with the values of ``meta`` ("" when nothing)."""
    shape = meta.get("node_shape")
    if not (isinstance(shape, list) and len(shape) == 3
            and all(isinstance(n, int) and not isinstance(n, bool) and n > 1 for n in shape)):
        return f"node_shape must be three node counts > 1, got {shape!r}"
    if not isinstance(meta.get("fingerprint"), str):
        return "fingerprint is missing"
    env = meta.get("envelope")
    if not isinstance(env, dict) or not env:
        return "the safety envelope is missing"
    bad = [k for k, v in env.items() if not _finite(v, positive=True)]
    if bad or "max_contact_disp_mm" not in env:
        return f"envelope values must be finite positive numbers ({', '.join(bad) or env})"
    norm = meta.get("normalisation")
    if not isinstance(norm, dict):
        return "normalisation is missing"
    for key, size in (("in_scale", 4), ("out_scale", 3)):
        values = norm.get(key)
        if not (isinstance(values, list) and len(values) == size
                and all(_finite(v, positive=True) for v in values)):
            return f"normalisation {key} must be {size} finite positive numbers"
    for key in ("architecture", "inference", "training", "baseline"):
        if not isinstance(meta.get(key, {}), dict):
            return f"{key} must be a table"
    return ""


def check_fingerprint(meta: dict, expected: str, where: str) -> None:
    """Refuse a model trained for another anatomy or grid than ``expected``."""
    stored = meta.get("fingerprint")
    if stored != expected:
        raise FingerprintError(
            f"this model was trained for another anatomy or grid (model fingerprint "
            f"{str(stored)[:16]}..., case fingerprint {str(expected)[:16]}...); a model must "
            f"never run on another patient: retrain it for this case with `biopsynav train`",
            where)


def check_file(model_dir: Path, name: str, meta: dict) -> Path:
    """Path of an exported file after checking that it exists and matches its checksum."""
    path = Path(model_dir) / name
    if not path.is_file():
        raise InputError(f"exported model {name} is missing; {RETRAIN}", str(path))
    expected = meta.get("inference", {}).get("files", {}).get(name)
    if expected is not None and sha256(path) != expected:
        raise InputError(f"exported model {name} is corrupt (checksum mismatch); {RETRAIN}",
                         str(path))
    return path
