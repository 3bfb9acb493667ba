"""Sparse direct solvers for the symmetric tangent, with the symbolic analysis done once.

Every backend receives the upper triangle of the matrix in CSR form (``indptr``, ``indices``
fixed per model, ``data`` new at each Newton iteration) and offers ``factor(data,
definite=False)`` and ``solve(rhs)``. ``factor`` raises :class:`FactorizationError` when the
matrix cannot be factored (singular, or not positive definite for a Cholesky-type backend);
with ``definite=True`` also when it is not positive definite, instead of factoring it by the
backend's indefinite fallback (``tests_definiteness`` says whether the backend can tell).

* ``pardiso``: MKL Pardiso through pypardiso's library handle, called directly: analysis
  (phase 11) once per model, then numerical factorisation (22) and solve (33). It first tries
  the SPD mode (``mtype=2``, Cholesky); when a tangent is not positive definite (neo-Hookean
  or SVK tangents near an instability) it switches for that matrix to symmetric indefinite
  (``mtype=-2``, Bunch-Kaufman pivoting, its own analysis done once on first need).
* ``cholmod``: scikit-sparse's CHOLMOD, when installed; ``analyze`` once, then
  ``cholesky_inplace``; an indefinite matrix falls back to SuperLU.
* ``superlu``: SciPy's SuperLU (always available), a full factorisation per call.
"""

from __future__ import annotations

import ctypes
import functools
import os
from typing import Protocol

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from ..errors import InputError

BACKENDS = ("pardiso", "cholmod", "superlu")
MKL_DOMAIN_PARDISO = 4


class FactorizationError(RuntimeError):
    """The tangent could not be factored (singular or, for Cholesky, not positive definite)."""


class LinearSolver(Protocol):
    name: str
    last_mode: str
    tests_definiteness: bool

    def factor(self, data: np.ndarray, definite: bool = False) -> None: ...

    def solve(self, rhs: np.ndarray) -> np.ndarray: ...


def available_backends() -> list[str]:
    """Installed backends, fastest first."""
    found = []
    try:
        _pypardiso()
        found.append("pardiso")
    except ImportError:
        pass
    try:
        import sksparse.cholmod  # noqa: F401
        found.append("cholmod")
    except ImportError:
        pass
    found.append("superlu")
    return found


def make_solver(backend: str, indptr: np.ndarray, indices: np.ndarray, threads: int = 0,
                single: bool = False) -> LinearSolver:
    """A solver for the upper-triangle pattern; ``backend``: auto, pardiso, cholmod, superlu.

    ``threads`` (Pardiso only; 0: MKL's default, all cores) and ``single`` (Pardiso only:
    factors in single precision, about a third faster; residuals stay in double precision,
    so Newton still converges to the double-precision tolerance)."""
    installed = available_backends()
    if backend == "auto":
        backend = installed[0]
    if backend not in BACKENDS:
        raise InputError(f"unknown solver backend {backend!r}; use auto, "
                         f"{', '.join(BACKENDS)}", "[solver] backend")
    if backend not in installed:
        raise InputError(f"solver backend {backend!r} is not installed (installed: "
                         f"{', '.join(installed)})", "[solver] backend")
    if backend == "pardiso":
        return PardisoSolver(indptr, indices, threads, single)
    cls = {"cholmod": CholmodSolver, "superlu": SuperLUSolver}[backend]
    return cls(indptr, indices)


def full_matrix(indptr: np.ndarray, indices: np.ndarray, data: np.ndarray) -> sp.csr_matrix:
    """The full symmetric matrix from its upper-triangle CSR arrays."""
    n = len(indptr) - 1
    upper = sp.csr_matrix((data, indices, indptr), shape=(n, n))
    return (upper + sp.triu(upper, k=1, format="csr").T).tocsr()


class PardisoHandle:
    """One MKL Pardiso instance (one matrix type) for a fixed pattern; phases 11/22/33."""

    def __init__(self, function, indptr: np.ndarray, indices: np.ndarray, mtype: int,
                 single: bool = False) -> None:
        self._pardiso = function
        self.mtype = mtype
        self.dtype = np.float32 if single else np.float64
        self.n = len(indptr) - 1
        self.ia = np.ascontiguousarray(indptr + 1, dtype=np.int32)
        self.ja = np.ascontiguousarray(indices + 1, dtype=np.int32)
        self.pt = np.zeros(64, dtype=np.int64)
        self.iparm = np.zeros(64, dtype=np.int32)
        self.iparm[0] = 1  # no solver defaults: every iparm below is explicit
        self.iparm[1] = 2  # METIS nested dissection ordering
        self.iparm[7] = 0  # no iterative refinement (Newton corrects inexact steps)
        self.iparm[9] = 8  # pivot perturbation 1e-8 (symmetric indefinite)
        self.iparm[10] = 0  # no scaling (symmetric)
        self.iparm[12] = 0  # no weighted matching (symmetric)
        self.iparm[17] = -1  # report factor non-zeros
        self.iparm[20] = 1  # Bunch-Kaufman pivoting for mtype -2
        self.iparm[27] = 1 if single else 0  # single-precision factors and solves
        self.iparm[34] = 0  # one-based indices (ia, ja above)
        self.perm = np.zeros(self.n, dtype=np.int32)
        self.analysed = False
        self._data = np.zeros(len(indices), dtype=self.dtype)

    def _call(self, phase: int, data: np.ndarray, rhs: np.ndarray, out: np.ndarray) -> int:
        err = ctypes.c_int32(0)
        i32 = ctypes.POINTER(ctypes.c_int32)
        f64 = ctypes.POINTER(ctypes.c_double)
        self._pardiso(self.pt.ctypes.data_as(ctypes.POINTER(ctypes.c_int64)),
                      ctypes.byref(ctypes.c_int32(1)), ctypes.byref(ctypes.c_int32(1)),
                      ctypes.byref(ctypes.c_int32(self.mtype)),
                      ctypes.byref(ctypes.c_int32(phase)), ctypes.byref(ctypes.c_int32(self.n)),
                      data.ctypes.data_as(f64), self.ia.ctypes.data_as(i32),
                      self.ja.ctypes.data_as(i32), self.perm.ctypes.data_as(i32),
                      ctypes.byref(ctypes.c_int32(1)), self.iparm.ctypes.data_as(i32),
                      ctypes.byref(ctypes.c_int32(0)), rhs.ctypes.data_as(f64),
                      out.ctypes.data_as(f64), ctypes.byref(err))
        return int(err.value)

    def factor(self, data: np.ndarray) -> None:
        self._data = np.ascontiguousarray(data, dtype=self.dtype)
        dummy = np.zeros(1, dtype=self.dtype)
        if not self.analysed:
            err = self._call(11, self._data, dummy, dummy)
            if err:
                raise FactorizationError(f"Pardiso analysis failed (error {err})")
            self.analysed = True
        err = self._call(22, self._data, dummy, dummy)
        if err:
            raise FactorizationError(f"Pardiso factorisation failed (error {err}, mtype "
                                     f"{self.mtype})")

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        rhs = np.ascontiguousarray(rhs, dtype=self.dtype)
        out = np.zeros_like(rhs)
        err = self._call(33, self._data, rhs, out)
        if err:
            raise FactorizationError(f"Pardiso solve failed (error {err})")
        return out.astype(np.float64)

    @property
    def negative_pivots(self) -> int:
        """Negative eigenvalues of the last factored matrix (mtype -2 only)."""
        return int(self.iparm[22])

    def release(self) -> None:
        if self.analysed:
            dummy = np.zeros(1, dtype=self.dtype)
            self._call(-1, self._data, dummy, dummy)
            self.analysed = False

    def __del__(self) -> None:
        try:
            self.release()
        except Exception:  # noqa: BLE001 - interpreter shutdown
            pass


def _unloadable(exc: OSError) -> InputError:
    return InputError(f"cannot load MKL's runtime library for Pardiso: {exc}; point "
                      "PYPARDISO_MKL_RT at libmkl_rt or unset it (pypardiso then searches)",
                      "PYPARDISO_MKL_RT")


def _pypardiso():
    """The pypardiso module (importing it makes its one default solver, ``pypardiso.ps``,
    which searches for MKL), its MKL in reproducible mode (:func:`reproducible_mkl`);
    InputError when the library cannot be loaded."""
    try:
        import pypardiso
    except OSError as exc:
        raise _unloadable(exc) from None
    reproducible_mkl(pypardiso.ps.libmkl)
    return pypardiso


#: MKL's ``MKL_CBWR_AUTO`` (mkl_cbwr.h): conditional numerical reproducibility on the code
#: branch MKL picks for this processor
MKL_CBWR_AUTO = 2


@functools.cache
def reproducible_mkl(libmkl) -> int:
    """Put the MKL library ``libmkl`` (a ``ctypes.CDLL``) in conditional numerical
    reproducibility (``MKL_CBWR_Set(MKL_CBWR_AUTO)``, the C interface: the lower-case
    symbol is the Fortran one, which takes a pointer) unless the user's ``MKL_CBWR`` chose a
    mode: Pardiso's factors and solves are then the same to the bit from run to run on one
    machine and thread count. Without it two threads sum in varying order, and a push near a
    limit point can land on another branch of the answer from one run to the next
    (docs/fem.md, "Kernels, assembly, linear solver"). Returns MKL's status (0: set; MKL
    refuses a change once it has computed), or -1 where the user's mode stands."""
    if "MKL_CBWR" in os.environ:
        return -1
    set_mode = libmkl.MKL_CBWR_Set
    set_mode.argtypes, set_mode.restype = [ctypes.c_int], ctypes.c_int
    return int(set_mode(MKL_CBWR_AUTO))


@functools.cache
def _mkl_runtime() -> str:
    """The MKL runtime library pypardiso found on import (its path or soname)."""
    return _pypardiso().ps.libmkl._name


def pypardiso_solver(mtype: int = 11):
    """A ``pypardiso.PyPardisoSolver(mtype)`` that does not search for MKL again.
    pypardiso searches at every construction (``ctypes.util.find_library``, then a recursive
    glob of the environment), about 0.8 s each; the library it found on import is handed to
    the later ones through pypardiso's ``PYPARDISO_MKL_RT`` (a path the user set is kept).
    Raises InputError naming that variable when the library cannot be loaded."""
    pypardiso = _pypardiso()
    os.environ.setdefault("PYPARDISO_MKL_RT", _mkl_runtime())
    try:
        return pypardiso.PyPardisoSolver(mtype=mtype)
    except OSError as exc:
        raise _unloadable(exc) from None


def pardiso_handle(indptr: np.ndarray, indices: np.ndarray, mtype: int,
                   single: bool = False) -> PardisoHandle:
    """A :class:`PardisoHandle` of matrix type ``mtype`` (2 SPD, -2 symmetric indefinite)
    for the upper-triangle CSR pattern ``indptr``, ``indices`` (zero-based), on MKL's
    Pardiso as pypardiso loads it; ``single`` factors in single precision."""
    return PardisoHandle(pypardiso_solver()._mkl_pardiso, indptr, indices, mtype, single)


class PardisoSolver:
    """MKL Pardiso: SPD Cholesky first, symmetric indefinite LDL^T when that fails."""

    name = "pardiso"
    tests_definiteness = True

    def __init__(self, indptr: np.ndarray, indices: np.ndarray, threads: int = 0,
                 single: bool = False) -> None:
        wrapper = pypardiso_solver()
        function = wrapper._mkl_pardiso  # argtypes already declared by pypardiso
        if threads > 0:
            wrapper.libmkl.MKL_Domain_Set_Num_Threads(int(threads), MKL_DOMAIN_PARDISO)
        self._spd = PardisoHandle(function, indptr, indices, 2, single)
        self._make_indefinite = lambda: PardisoHandle(function, indptr, indices, -2, single)
        self._indefinite: PardisoHandle | None = None
        self._active = self._spd
        self.last_mode = "spd"

    def factor(self, data: np.ndarray, definite: bool = False) -> None:
        """Cholesky, or LDL^T where that fails (not with ``definite``). After an LDL^T with
        negative pivots the next matrix (a Newton iteration's, near the last) goes to LDL^T
        at once, sparing a failing Cholesky; one with none sends the next to Cholesky again."""
        after_negative = (self._active is self._indefinite
                          and self._indefinite.negative_pivots > 0)
        if definite or not after_negative:
            try:
                self._spd.factor(data)
                self._active, self.last_mode = self._spd, "spd"
                return
            except FactorizationError:
                if definite:
                    raise
        if self._indefinite is None:
            self._indefinite = self._make_indefinite()
        self._indefinite.factor(data)
        self._active = self._indefinite
        self.last_mode = f"indefinite({self._indefinite.negative_pivots} neg)"

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        return self._active.solve(rhs)


class CholmodSolver:
    """CHOLMOD (scikit-sparse): symbolic analysis once; SuperLU when not positive definite."""

    name = "cholmod"
    tests_definiteness = True

    def __init__(self, indptr: np.ndarray, indices: np.ndarray) -> None:
        self.indptr, self.indices = indptr, indices
        self._factor = None
        self._lu: SuperLUSolver | None = None
        self.last_mode = "spd"

    def factor(self, data: np.ndarray, definite: bool = False) -> None:
        from sksparse.cholmod import CholmodNotPositiveDefiniteError, analyze

        matrix = full_matrix(self.indptr, self.indices, data).tocsc()
        if self._factor is None:
            self._factor = analyze(matrix)
        try:
            self._factor.cholesky_inplace(matrix)
            self._lu, self.last_mode = None, "spd"
        except CholmodNotPositiveDefiniteError:
            if definite:
                raise FactorizationError("not positive definite (CHOLMOD)") from None
            self._lu = SuperLUSolver(self.indptr, self.indices)
            self._lu.factor(data)
            self.last_mode = "lu"

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        if self._lu is not None:
            return self._lu.solve(rhs)
        return np.asarray(self._factor(rhs)).ravel()


class SuperLUSolver:
    """SciPy SuperLU on the full matrix (no reusable analysis in SciPy)."""

    name = "superlu"
    tests_definiteness = False  # LU factors any non-singular matrix

    def __init__(self, indptr: np.ndarray, indices: np.ndarray) -> None:
        self.indptr, self.indices = indptr, indices
        self._lu = None
        self.last_mode = "lu"

    def factor(self, data: np.ndarray, definite: bool = False) -> None:
        matrix = full_matrix(self.indptr, self.indices, data).tocsc()
        try:
            self._lu = spla.splu(matrix, permc_spec="MMD_AT_PLUS_A")
        except RuntimeError as exc:
            raise FactorizationError(f"SuperLU failed: {exc}") from None

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        return self._lu.solve(rhs)
