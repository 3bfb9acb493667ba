"""Atomic file writes: a file is either complete or absent, never half-written."""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np

from .errors import InputError, WriteError


def _current_umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _current_umask()


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` through a temporary file in the same folder and a rename."""
    return write_atomic(path, lambda fh: fh.write(data))


def write_atomic(path: str | os.PathLike, writer: Callable[[BinaryIO], Any]) -> Path:
    """Write ``path`` through a temporary file in the same folder and a rename: ``writer``
    writes into the open temporary file (streamed, not first built in memory). WriteError
    when the folder or the file cannot be written (the previous file, if any, unchanged)."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as exc:
        raise WriteError(f"cannot write here: {exc.strerror}", str(path)) from None
    try:
        with os.fdopen(fd, "wb") as fh:
            writer(fh)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the usual permissions
        os.replace(tmp, path)
    except OSError as exc:
        Path(tmp).unlink(missing_ok=True)
        raise WriteError(f"cannot write: {exc.strerror}; the previous file, if any, is "
                         "unchanged", str(path)) from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def check_output_path(path: str | os.PathLike, option: str) -> Path:
    """Refuse (InputError) an output file a user named that is not a regular file or a new
    path in an existing, writable folder: a symbolic link, a folder, a device or a FIFO is
    never replaced."""
    path = Path(path)
    where = f"{option} {path}"
    if path.is_symlink():
        raise InputError("is a symbolic link; name a regular file or a new path", where)
    if path.exists() and not path.is_file():
        kind = "a folder" if path.is_dir() else "a device, FIFO or socket"
        raise InputError(f"is {kind}, not a regular file; name a regular file or a new path",
                         where)
    parent = path.parent
    if not parent.is_dir():
        raise InputError(f"folder {parent} does not exist", where)
    if not os.access(parent, os.W_OK):
        raise InputError(f"folder {parent} is not writable", where)
    return path


def remove_partial_writes(folder: str | os.PathLike, names: Iterable[str]) -> list[Path]:
    """Delete the temporary files that :func:`write_bytes_atomic` leaves in ``folder`` when its
    process is killed mid-write (``.NAME.*.tmp`` for each file name in ``names``); the files
    themselves are untouched. Returns the deleted paths."""
    folder = Path(folder)
    removed = []
    for name in names:
        for tmp in folder.glob(f".{name}.*.tmp"):
            tmp.unlink(missing_ok=True)
            removed.append(tmp)
    return removed


def write_text_atomic(path: str | os.PathLike, text: str) -> Path:
    """Write UTF-8 text atomically."""
    return write_bytes_atomic(path, text.encode("utf-8"))


def write_json_atomic(path: str | os.PathLike, obj: Any) -> Path:
    """Write an object as indented JSON atomically."""
    return write_text_atomic(path, json.dumps(obj, indent=2, default=json_default) + "\n")


def save_npz_atomic(path: str | os.PathLike, **arrays: np.ndarray) -> Path:
    """Save arrays to a compressed ``.npz`` atomically."""
    return write_atomic(path, lambda fh: np.savez_compressed(fh, **arrays))


def load_npz(path: str | os.PathLike, keys: Iterable[str], rebuild: str) -> dict[str, np.ndarray]:
    """The arrays ``keys`` of an ``.npz`` written by :func:`save_npz_atomic`, read eagerly.

    A missing, truncated, damaged (zip CRC) or incomplete file is one InputError naming it and
    ``rebuild``, the command that writes it again."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"missing; {rebuild}", str(path))
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in keys if k not in data.files]
            if missing:
                raise InputError(f"damaged: lacks {', '.join(missing)}; {rebuild}", str(path))
            return {k: data[k] for k in data.files}
    except InputError:
        raise
    except Exception as exc:  # noqa: BLE001 - zipfile, zlib, numpy and the OS raise many kinds
        raise InputError(f"damaged ({type(exc).__name__}: {str(exc)[:120]}); {rebuild}",
                         str(path)) from None


def read_json(path: str | os.PathLike, rebuild: str, missing_ok: bool = False) -> Any:
    """The JSON document at ``path``; None when missing and ``missing_ok``. A missing (unless
    ``missing_ok``), unreadable or damaged file is one InputError naming it and ``rebuild``."""
    path = Path(path)
    if not path.is_file():
        if missing_ok:
            return None
        raise InputError(f"missing; {rebuild}", str(path))
    try:
        return json.loads(path.read_bytes().decode("utf-8"))
    except (ValueError, UnicodeDecodeError) as exc:
        raise InputError(f"damaged, not valid JSON ({str(exc)[:80]}); {rebuild}",
                         str(path)) from None
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror}", str(path)) from None


def save_figure_atomic(fig: Any, path: str | os.PathLike, dpi: int = 120) -> Path:
    """Save a matplotlib figure as PNG atomically."""
    return write_atomic(path, lambda fh: fig.savefig(fh, format="png", dpi=dpi,
                                                     bbox_inches="tight"))


def json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")
