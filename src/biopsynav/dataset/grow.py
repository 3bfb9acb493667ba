"""Growing a stored data set in place when only its sizes changed.

Raising ``[dataset] n_train`` / ``n_test`` (or ``[refine] samples`` / ``held_out``, which set
them in the refine case) changes the protocol only in the sizes. Every sample's push follows
from ``(seed, index, attempt)`` alone (:func:`biopsynav.probe.sample_rng`), so a stored sample
is still the sample of that index in the larger data set, as long as its role (training or
held out) is the same in both or does not change its push. Samples ``[0, n_train)`` are for
training and ``[n_train, N)`` held out, so growing turns the old held-out samples below the new
``n_train`` into training samples: a rigid push, or a force patch whose training force follows
the held-out law (``[probe] train_force_exponent`` = ``train_force_scale`` = 1 and
``too_deep_redraw = "elsewhere"``), is the same either way and is kept; any other is solved
again as a training sample. Shrinking is refused: it would drop solved samples.

The growth is written as a plan in the store's attributes (``resizing``) before any array
changes; :func:`biopsynav.dataset.store.finish_growth` carries it out (whenever the store
is opened for writing) and is idempotent, so a run killed half-way is
completed by the next ``generate`` (and refused, with that advice, by a read-only reader).
"""

from __future__ import annotations

import copy

from ..config import CaseConfig
from ..errors import FingerprintError
from ..probe import is_rigid_sample
from .store import (
    RESIZE_ATTR,
    DatasetStore,
    comparable_protocol,
    finish_growth,
    protocol_fingerprint,
)


def without_sizes(protocol: dict) -> dict:
    """``protocol`` without ``[dataset] n_train`` and ``n_test``."""
    out = copy.deepcopy(comparable_protocol(protocol))
    for key in ("n_train", "n_test"):
        (out.get("dataset") or {}).pop(key, None)
    return out


def sizes_alone_differ(stored: object, protocol: dict) -> bool:
    """Whether a stored protocol and ``protocol`` differ, and only in the data set's sizes."""
    if not isinstance(stored, dict):
        return False
    return sizes_of(stored) != sizes_of(protocol) and \
        protocol_fingerprint(without_sizes(stored)) == protocol_fingerprint(without_sizes(protocol))


def sizes_of(protocol: dict) -> tuple:
    """``[dataset] n_train`` and ``n_test`` of a protocol (None where missing)."""
    data = protocol.get("dataset") or {}
    return data.get("n_train"), data.get("n_test")


def growth_refusal(attrs: dict, n_train: int, n_test: int) -> str | None:
    """Why a store with ``attrs`` cannot grow to ``n_train`` + ``n_test`` samples (None: it
    can): fewer training samples, or fewer in all, would drop solved ones."""
    old_train, old_test = int(attrs["n_train"]), int(attrs["n_test"])
    if n_train >= old_train and n_train + n_test >= old_train + old_test:
        return None
    return (f"the data set holds {old_train} training and {old_test} held-out samples and the "
            f"case asks for {n_train} and {n_test}: a data set grows in place but never shrinks "
            "(that would drop solved samples); set [dataset] n_train and n_test ([refine] samples "
            "and held_out for a refine data set) back in case.toml to keep it, "
            "or run with --overwrite to discard it")


def push_is_role_free(cfg: CaseConfig, index: int) -> bool:
    """Whether sample ``index``'s push is the same as a training and as a held-out sample: a
    rigid push, or a force patch under the held-out force law."""
    probe = cfg.probe
    if is_rigid_sample(probe, index):
        return True
    return (probe.train_force_exponent == 1.0 and probe.train_force_scale == 1.0
            and probe.too_deep_redraw == "elsewhere")


def samples_to_solve_again(cfg: CaseConfig, attrs: dict, n_train: int) -> list[int]:
    """The stored held-out samples that become training samples (indices below the new
    ``n_train``) and whose push changes with that role."""
    old_train = int(attrs["n_train"])
    old_total = old_train + int(attrs["n_test"])
    moved = range(old_train, min(old_total, n_train))
    return [i for i in moved if not push_is_role_free(cfg, i)]


def grow_store(store: DatasetStore, cfg: CaseConfig, protocol: dict, n_train: int,
               n_test: int) -> dict:
    """Grow ``store`` in place to ``n_train`` + ``n_test`` samples under ``protocol`` (which
    differs from the stored one in its sizes alone); the plan carried out (sizes before and
    after, ``solve_again``: the stored samples no longer valid).

    Raises:
        FingerprintError: the new sizes would drop stored samples.
    """
    attrs = dict(store.group.attrs)
    refusal = growth_refusal(attrs, n_train, n_test)
    if refusal:
        raise FingerprintError(refusal, str(store.path))
    again = samples_to_solve_again(cfg, attrs, n_train)
    done = store.done_mask()
    plan = {"from": [int(attrs["n_train"]), int(attrs["n_test"])],
            "kept": int(done.sum() - done[again].sum()),
            "n_train": int(n_train), "n_test": int(n_test), "protocol": protocol,
            "protocol_fingerprint": protocol_fingerprint(protocol),
            "solve_again": again}
    store.group.attrs[RESIZE_ATTR] = plan
    finish_growth(store)
    return plan


def growth_summary(plan: dict) -> str:
    """One line saying how a data set grew."""
    (old_train, old_test), again = plan["from"], len(plan["solve_again"])
    return (f"data set grown from {old_train} + {old_test} to {plan['n_train']} + "
            f"{plan['n_test']} samples (training + held out): {plan['kept']} solved samples "
            "kept" + (f", {again} held-out ones to be solved again as training samples"
                      if again else ""))


__all__ = ["grow_store", "growth_refusal", "growth_summary", "samples_to_solve_again",
           "sizes_alone_differ"]
