"""CHOLMOD called through ctypes: the GIL released while it works, wide solves split over the cores.

scikit-sparse holds the GIL through CHOLMOD's analysis, factorization and
solves, so nothing else of the process runs meanwhile, and its solves of many
right-hand sides get little from a second core (the supernodal solve is a
sequence of small triangular and matrix products: 157 columns at 200k DOF
took 1.9 s on two BLAS threads, 2.0 s on one). Called here through ctypes
(which releases the GIL for the call), the same library

* analyses a pattern on a background thread while the caller goes on
  (:func:`femodel.analyze_ahead`), and
* solves a block of columns as two (or more) blocks on as many threads, one
  BLAS thread each: 157 columns in 0.94-0.99 s instead of 1.9 s.

The factor is CHOLMOD's own (same ordering, same supernodes, same numbers
as scikit-sparse's but for the BLAS's order of additions). What is read from
CHOLMOD's structures is checked when the library is loaded: the fields of
``cholmod_common`` that are set (``supernodal``, ``print``) are found at the
offsets where the defaults written by ``cholmod_start`` must be; on any
mismatch this path is not used (:func:`available` says why) and
:mod:`femodel._factor` calls scikit-sparse as before; ``FRFCAL_CHOLMOD_DIRECT=0`` does the same on
purpose (read when the module is first imported).
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import threading
import weakref

import numpy as np

from femodel._blas import blas_threads, data_threads

#: Columns per thread below which a solve is not split (8 columns gain nothing on two threads at 200k DOF,
#: 16 gain 10-15 %, 78 gain 40 %).
SPLIT_MIN_COLUMNS = 12

_CHOLMOD_SUPERNODAL = 2
_CHOLMOD_A = 0
_REAL, _PATTERN = 1, 0
#: Bytes reserved for one ``cholmod_common`` (the struct is 2.5-3 kB in CHOLMOD 3 to 5).
_COMMON_BYTES = 1 << 16


class _Sparse(ctypes.Structure):
    _fields_ = [("nrow", ctypes.c_size_t), ("ncol", ctypes.c_size_t), ("nzmax", ctypes.c_size_t),
                ("p", ctypes.c_void_p), ("i", ctypes.c_void_p), ("nz", ctypes.c_void_p),
                ("x", ctypes.c_void_p), ("z", ctypes.c_void_p),
                ("stype", ctypes.c_int), ("itype", ctypes.c_int), ("xtype", ctypes.c_int),
                ("dtype", ctypes.c_int), ("sorted", ctypes.c_int), ("packed", ctypes.c_int)]


class _Dense(ctypes.Structure):
    _fields_ = [("nrow", ctypes.c_size_t), ("ncol", ctypes.c_size_t), ("nzmax", ctypes.c_size_t),
                ("d", ctypes.c_size_t), ("x", ctypes.c_void_p), ("z", ctypes.c_void_p),
                ("xtype", ctypes.c_int), ("dtype", ctypes.c_int)]


class _FactorHead(ctypes.Structure):
    """The first two fields of ``cholmod_factor``: its order and, after a factorization, the column
    where it stopped (``minor == n``: positive definite)."""

    _fields_ = [("n", ctypes.c_size_t), ("minor", ctypes.c_size_t)]


#: (offset, type, the value cholmod_start writes) of ``cholmod_common`` fields, in CHOLMOD 3-5's layout:
#: dbound, grow0, grow1, grow2, maxrank, supernodal_switch, supernodal, zrelax[3], nrelax[3], print.
_LAYOUT = ((0, ctypes.c_double, 0.0), (8, ctypes.c_double, 1.2), (16, ctypes.c_double, 1.2),
           (24, ctypes.c_size_t, 5), (32, ctypes.c_size_t, 8), (40, ctypes.c_double, 40.0),
           (48, ctypes.c_int, 1), (80, ctypes.c_double, 0.8), (88, ctypes.c_double, 0.1),
           (96, ctypes.c_double, 0.05), (104, ctypes.c_size_t, 4), (112, ctypes.c_size_t, 16),
           (120, ctypes.c_size_t, 48), (144, ctypes.c_int, 3))
_OFFSET_SUPERNODAL, _OFFSET_PRINT = 48, 144


#: Environment variable: ``0`` keeps this path off (scikit-sparse is called instead, as before stop 43).
ENV_VAR = "FRFCAL_CHOLMOD_DIRECT"


def _load():
    """(library or None, what was loaded or why not): the system's CHOLMOD."""
    if os.environ.get(ENV_VAR, "").strip() == "0":
        return None, f"the ctypes path is off ({ENV_VAR}=0)"
    name = ctypes.util.find_library("cholmod")
    if name is None:
        return None, "libcholmod not found (Debian: apt-get install libsuitesparse-dev)"
    return _open(name, name)


def _open(path: str, label: str):
    """(library or None, detail) for the shared object at ``path`` that holds CHOLMOD's API."""
    try:
        lib = ctypes.CDLL(path)
    except OSError as exc:
        return None, f"{label} does not load: {exc}"
    vp = ctypes.c_void_p
    try:
        lib.cholmod_start.argtypes = [vp]
        lib.cholmod_finish.argtypes = [vp]
        lib.cholmod_analyze.argtypes = [ctypes.POINTER(_Sparse), vp]
        lib.cholmod_analyze.restype = vp
        lib.cholmod_copy_factor.argtypes = [vp, vp]
        lib.cholmod_copy_factor.restype = vp
        lib.cholmod_factorize.argtypes = [ctypes.POINTER(_Sparse), vp, vp]
        lib.cholmod_free_factor.argtypes = [ctypes.POINTER(vp), vp]
        lib.cholmod_free_dense.argtypes = [ctypes.POINTER(vp), vp]
        lib.cholmod_solve2.argtypes = [ctypes.c_int, vp, ctypes.POINTER(_Dense), vp,
                                       ctypes.POINTER(ctypes.POINTER(_Dense)), vp, ctypes.POINTER(vp),
                                       ctypes.POINTER(vp), vp]
    except AttributeError as exc:
        return None, f"{label} lacks a CHOLMOD entry point ({exc})"
    common = ctypes.create_string_buffer(_COMMON_BYTES)
    if not lib.cholmod_start(common):
        return None, f"{label}: cholmod_start failed"
    try:
        for offset, ctype, value in _LAYOUT:
            got = ctype.from_buffer(common, offset).value
            if got != value:
                return None, (f"{label}: cholmod_common field at byte {offset} holds {got!r} where CHOLMOD's "
                              f"default {value!r} belongs (unknown layout)")
    finally:
        lib.cholmod_finish(common)
    version = ""
    if hasattr(lib, "cholmod_version"):
        v = (ctypes.c_int * 3)()
        lib.cholmod_version(v)
        version = f" {v[0]}.{v[1]}.{v[2]}"
    return lib, f"{label} (CHOLMOD{version}, called through ctypes)"


_LIB, DETAIL = _load()


def available() -> bool:
    """Whether the system's CHOLMOD can be used (:data:`DETAIL` says what was loaded, or why not)."""
    return _LIB is not None


_BUNDLED: tuple | None = None


def bundled():
    """(library or None, detail): the CHOLMOD inside cholespy's wheel (its extension module exports the
    API; its BLAS is the reference BLAS bundled with it), loaded on first call."""
    global _BUNDLED
    if _BUNDLED is None:
        if os.environ.get(ENV_VAR, "").strip() == "0":
            _BUNDLED = (None, f"the ctypes path is off ({ENV_VAR}=0)")
        else:
            try:
                import cholespy._cholespy_core as core
            except ImportError as exc:
                _BUNDLED = (None, f"cholespy not importable ({exc})")
            else:
                _BUNDLED = _open(core.__file__, "cholespy's extension module")
    return _BUNDLED


class CholmodError(RuntimeError):
    """CHOLMOD returned failure (out of memory, a problem too large for its int indices)."""


class NotPositiveDefinite(CholmodError):
    """The numeric factorization met a non-positive pivot (``column`` is where)."""

    def __init__(self, column: int, n: int):
        super().__init__(f"matrix not positive definite (pivot of column {column} of {n})")
        self.column = column


def _common(lib):
    c = ctypes.create_string_buffer(_COMMON_BYTES)
    if not lib.cholmod_start(c):
        raise CholmodError("cholmod_start failed")
    ctypes.c_int.from_buffer(c, _OFFSET_PRINT).value = 0  # no messages on stdout (they would corrupt --json)
    ctypes.c_int.from_buffer(c, _OFFSET_SUPERNODAL).value = _CHOLMOD_SUPERNODAL
    return c


def _free_factor(lib, pointer: int, common) -> None:
    handle = ctypes.c_void_p(pointer)
    lib.cholmod_free_factor(ctypes.byref(handle), common)


def _finish(lib, commons) -> None:
    for c in commons:
        lib.cholmod_finish(c)


class _Matrix:
    """A CSC matrix as CHOLMOD's lower-triangle symmetric ``cholmod_sparse`` (int indices), with the
    arrays it points at kept alive."""

    def __init__(self, indptr, indices, data, n: int):
        if n >= 2**31 - 1 or indices.shape[0] >= 2**31 - 1:
            raise CholmodError(f"{n} DOF / {indices.shape[0]} entries exceed CHOLMOD's int indices")
        self.indptr = np.ascontiguousarray(indptr, dtype=np.int32)
        self.indices = np.ascontiguousarray(indices, dtype=np.int32)
        self.data = None if data is None else np.ascontiguousarray(data, dtype=np.float64)
        self.struct = _Sparse(n, n, self.indices.shape[0], self.indptr.ctypes.data, self.indices.ctypes.data,
                              None, None if self.data is None else self.data.ctypes.data, None,
                              -1, 0, _PATTERN if self.data is None else _REAL, 0, 1, 1)


class Symbolic:
    """CHOLMOD's analysis of a symmetric pattern (fill-reducing ordering, supernodes), reusable for every
    matrix of that pattern (:meth:`factor`)."""

    def __init__(self, indptr, indices, n: int, lib=None):
        self.n = int(n)
        self._lib = lib = _LIB if lib is None else lib
        if lib is None:
            raise CholmodError(DETAIL)
        matrix = _Matrix(indptr, indices, None, self.n)
        self._common = _common(lib)
        pointer = lib.cholmod_analyze(ctypes.byref(matrix.struct), self._common)  # GIL released meanwhile
        if not pointer:
            _finish(lib, [self._common])
            raise CholmodError("cholmod_analyze failed (out of memory, or the factor too large for int indices)")
        self._pointer = pointer
        self._finalizer = weakref.finalize(self, _release, lib, pointer, self._common)

    def factor(self, A) -> "Numeric":
        """The numeric factorization of A (CSC, this pattern, symmetric positive definite).

        Raises
        ------
        NotPositiveDefinite
            A non-positive pivot.
        """
        return Numeric(self, A)


def _release(lib, pointer: int, common) -> None:
    _free_factor(lib, pointer, common)
    _finish(lib, [common])


class Numeric:
    """L L^T = P A P^T, callable as ``solve(F)`` = A^-1 F."""

    def __init__(self, symbolic: Symbolic, A):
        n = symbolic.n
        matrix = _Matrix(A.indptr, A.indices, A.data, n)
        self.n = n
        self._lib = lib = symbolic._lib
        self._commons = [_common(lib)]
        pointer = lib.cholmod_copy_factor(symbolic._pointer, self._commons[0])
        if not pointer:
            _finish(lib, self._commons)
            raise CholmodError("cholmod_copy_factor failed (out of memory)")
        self._finalizer = weakref.finalize(self, _release_numeric, lib, pointer, self._commons)
        self._pointer = pointer
        ok = lib.cholmod_factorize(ctypes.byref(matrix.struct), pointer, self._commons[0])  # GIL released
        if not ok:
            raise CholmodError("cholmod_factorize failed (out of memory)")
        minor = _FactorHead.from_address(pointer).minor
        if minor < n:
            raise NotPositiveDefinite(int(minor), n)
        self._lock = threading.Lock()

    def _solve_block(self, F: np.ndarray, out: np.ndarray, a: int, b: int, slot: int, failed: list) -> None:
        """out[:, a:b] = A^-1 F[:, a:b] with the slot's own cholmod_common (its workspace)."""
        try:
            B = np.asfortranarray(F[:, a:b])
            X = np.empty((self.n, b - a), order="F")
            bd = _Dense(self.n, b - a, self.n * (b - a), self.n, B.ctypes.data, None, _REAL, 0)
            xd = _Dense(self.n, b - a, self.n * (b - a), self.n, X.ctypes.data, None, _REAL, 0)
            xp = ctypes.pointer(xd)  # X of exactly the solve's shape and type: CHOLMOD writes into it
            Y, E = ctypes.c_void_p(), ctypes.c_void_p()
            common = self._commons[slot]
            ok = self._lib.cholmod_solve2(_CHOLMOD_A, self._pointer, ctypes.byref(bd), None, ctypes.byref(xp),
                                          None, ctypes.byref(Y), ctypes.byref(E), common)
            self._lib.cholmod_free_dense(ctypes.byref(Y), common)
            self._lib.cholmod_free_dense(ctypes.byref(E), common)
            if not ok or ctypes.addressof(xp.contents) != ctypes.addressof(xd):
                raise CholmodError("cholmod_solve2 failed (out of memory)")
            out[:, a:b] = X
        except BaseException as exc:  # noqa: BLE001 - handed to the calling thread
            failed.append(exc)

    def solve(self, F) -> np.ndarray:
        """A^-1 F for F of shape (n,) or (n, k), C-contiguous float64 of F's shape.

        k of at least 2 x :data:`SPLIT_MIN_COLUMNS` is solved as blocks of columns on as many threads as
        the process has cores (``FRFCAL_THREADS``; one in a worker process), one BLAS thread each.
        """
        F = np.asarray(F, dtype=float)
        if F.ndim not in (1, 2) or F.shape[0] != self.n:
            raise ValueError(f"right-hand side of shape {F.shape} for a factor of order {self.n}")
        vector = F.ndim == 1
        F2 = F.reshape(self.n, -1)
        k = F2.shape[1]
        out = np.empty((self.n, k))
        if k == 0:
            return out
        parts = max(1, min(data_threads(), k // SPLIT_MIN_COLUMNS))
        failed: list = []
        with self._lock:
            while len(self._commons) < parts:
                self._commons.append(_common(self._lib))
            if parts == 1:
                self._solve_block(F2, out, 0, k, 0, failed)
            else:
                edges = np.linspace(0, k, parts + 1).astype(int)
                with blas_threads(1):
                    threads = [threading.Thread(target=self._solve_block,
                                                args=(F2, out, int(edges[i]), int(edges[i + 1]), i, failed))
                               for i in range(1, parts)]
                    for t in threads:
                        t.start()
                    self._solve_block(F2, out, int(edges[0]), int(edges[1]), 0, failed)
                    for t in threads:
                        t.join()
        if failed:
            raise failed[0]
        return out.reshape(F.shape) if vector else out

    __call__ = solve


def _release_numeric(lib, pointer: int, commons) -> None:
    _free_factor(lib, pointer, commons[0])
    _finish(lib, commons)
