"""One error type for every bad input; the CLI prints it as one line and exits with status 2."""

from __future__ import annotations


class BiopsynavError(Exception):
    """A user-facing error: ``what`` is wrong, ``where`` names the input (file, key, message)."""

    def __init__(self, what: str, where: str | None = None) -> None:
        self.what = what
        self.where = where
        super().__init__(f"{where}: {what}" if where else what)


class InputError(BiopsynavError):
    """A file, a case.toml value or a command-line option that cannot be used."""


class SolverError(BiopsynavError):
    """A finite-element solve that did not converge; carries the Newton log and, where the
    solver sets it, ``reached``: the last converged state (load factor, solver-specific
    state) a retry can start from, or None."""

    def __init__(self, what: str, where: str | None = None, log: list[dict] | None = None,
                 reached: tuple | None = None) -> None:
        super().__init__(what, where)
        self.log = log or []
        self.reached = reached


class TrainingError(BiopsynavError):
    """A training that cannot go on: its loss or validation error is no longer finite."""


class FingerprintError(BiopsynavError):
    """Data or a model made for another anatomy or grid than the case at hand."""


class WriteError(BiopsynavError):
    """A file that cannot be written (read-only folder, full disk); nothing was replaced."""


class CaseBusyError(BiopsynavError):
    """Another biopsynav command is writing to the same case folder."""
