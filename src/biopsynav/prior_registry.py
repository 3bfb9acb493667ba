"""The registry of pretrained networks of other breasts that a case's training starts from
(``[network] prior``; exported by :mod:`biopsynav.network.priors`).

The U-Net is fully convolutional: its weights do not depend on the grid's node counts, and
the local response of soft tissue to a moved skin patch is much the same from breast to
breast. A case's network that starts from the network of another anatomy (its own
normalisation, the other's weights) reaches the mean held-out error of a training from
scratch in about a third of the iterations, not its largest error (docs/network.md, "Starting
from a prior"), so ``none`` is the default. The package ships
the case networks of the built-in phantom and of the UC Davis breast (``data/priors``), each
trained from scratch with the defaults; ``auto`` takes the first one registered whose
surface is not the case's own, so that no case starts from a network taught by its own
breast.

One registry (``register_prior``); ``[network] prior`` takes its choices from it. A prior is
plain data: ``NAME.npz`` (the U-Net's state dict, float16) and ``NAME.json`` (architecture,
the surface's fingerprint, what taught it and the command that made it).
"""

from __future__ import annotations

import hashlib
import json
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import InputError

WHERE = "[network] prior"
PRIOR_DIR = Path(__file__).resolve().parent / "data" / "priors"
#: what reading a weights file that is not an ``.npz`` of arrays raises (a ``.npy`` in its
#: place: TypeError; a damaged zip: BadZipFile; pickled objects: ValueError)
UNREADABLE = (OSError, ValueError, EOFError, TypeError, AttributeError, zipfile.BadZipFile)


@dataclass(frozen=True)
class Prior:
    """A pretrained network: ``weights`` (``NAME.npz``) and ``info`` (``NAME.json``: keys
    ``architecture``, ``surface_fingerprint``, ``description``, ``source``)."""

    name: str
    weights_path: Path
    info: dict = field(hash=False, compare=False)

    @property
    def architecture(self) -> dict:
        return dict(self.info["architecture"])

    def checksum(self) -> str:
        """SHA-256 of the weights file (part of a training's signature); InputError naming
        the prior when the file cannot be read."""
        try:
            return hashlib.sha256(self.weights_path.read_bytes()).hexdigest()
        except OSError as exc:
            raise self._unreadable(exc) from None

    def state_dict(self) -> dict:
        """The U-Net's weights as float32 tensors; InputError naming the prior when its file
        is not a readable ``.npz`` of arrays."""
        import torch

        try:
            with np.load(self.weights_path, allow_pickle=False) as z:
                return {k: torch.from_numpy(z[k].astype(np.float32)) for k in z.files}
        except UNREADABLE as exc:
            raise self._unreadable(exc) from None

    def load_into(self, unet: Any) -> None:
        """Load the weights into ``unet`` (a :class:`~biopsynav.network.unet.UNet3d`), every
        weight and no other; InputError naming the prior when they do not fit it."""
        try:
            unet.load_state_dict(self.state_dict())
        except RuntimeError as exc:
            first = str(exc).strip().splitlines()[0]
            raise InputError(f"the prior {self.name!r} ({self.weights_path}) does not fit this "
                             f"network: {first}", WHERE) from None

    def _unreadable(self, exc: Exception) -> InputError:
        return InputError(f"the prior {self.name!r}: cannot read its weights "
                          f"{self.weights_path} ({type(exc).__name__}: {exc})", WHERE)

    def summary(self) -> dict:
        """What a model trained from it records in meta.json."""
        return {"name": self.name, "checksum": self.checksum(),
                "description": self.info.get("description", ""),
                "source": self.info.get("source", {})}


PRIORS: dict[str, Prior] = {}


def register_prior(prior: Prior) -> None:
    """Add (or replace) a prior; ``[network] prior`` accepts its name. ``auto`` tries them in
    the order registered."""
    PRIORS[prior.name] = prior


def prior_choices() -> tuple[str, ...]:
    """The allowed ``[network] prior`` values: ``auto``, ``none`` and every registered name."""
    return ("auto", "none", *PRIORS)


def surface_fingerprint(anatomy: Any) -> str:
    """SHA-256 of the skin surface (vertices and triangles): the breast, whatever its lesions,
    tissues or grid."""
    h = hashlib.sha256()
    for a in (np.ascontiguousarray(anatomy.vertices, np.float64),
              np.ascontiguousarray(anatomy.faces, np.int64)):
        h.update(str(a.shape).encode() + a.tobytes())
    return h.hexdigest()


def choose_prior(choice: str, anatomy: Callable[[], Any], architecture: dict
                 ) -> tuple[Prior | None, str]:
    """The prior a training with the network ``architecture`` starts from, and one sentence
    saying which or why none. ``choice``: ``none``, ``auto`` (the first registered prior of
    the same architecture and another surface than that of ``anatomy()``, the case's anatomy,
    read only then) or a registered name (InputError when its architecture differs)."""
    if choice == "none":
        return None, "from scratch ([network] prior = \"none\")"
    if choice != "auto":
        prior = named_prior(choice)
        if prior.architecture != architecture:
            raise InputError(f"the prior {choice!r} is a network of architecture "
                             f"{prior.architecture}, this training's is {architecture}; use "
                             "prior = \"auto\" or \"none\"", WHERE)
        return prior, prior_line(prior)
    same = [p for p in PRIORS.values() if p.architecture == architecture]
    own = surface_fingerprint(anatomy()) if same else ""
    for prior in same:
        if prior.info["surface_fingerprint"] != own:
            return prior, prior_line(prior)
    return None, ("from scratch: no prior of this network architecture and another breast "
                  f"(registered: {', '.join(PRIORS) or 'none'})")


def named_prior(name: str) -> Prior:
    """The registered prior ``name``; InputError naming the choices otherwise."""
    if name not in PRIORS:
        raise InputError(f"unknown prior {name!r}; choose one of {', '.join(prior_choices())}",
                         WHERE)
    return PRIORS[name]


def prior_line(prior: Prior) -> str:
    """One line: the prior's name and what taught it."""
    return f"from the prior {prior.name!r}, {prior.info.get('description', '')}"


def register_packaged() -> None:
    """Register the priors shipped in ``data/priors``, in the order of ``ORDER``."""
    for name in ORDER:
        weights, info = PRIOR_DIR / f"{name}.npz", PRIOR_DIR / f"{name}.json"
        if weights.is_file() and info.is_file():
            register_prior(Prior(name, weights, json.loads(info.read_text())))


#: The packaged priors, most breast-like first: a patient starts from the UC Davis breast,
#: the UC Davis breast from the phantom.
ORDER = ("ucdavis-breast3", "phantom")

register_packaged()
