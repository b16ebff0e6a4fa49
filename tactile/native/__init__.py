"""The native kernels (EMD and OMP sparse codes in C), called through ctypes on numpy arrays.

The C sources beside this file (``tactile_native.h`` gives the entry points) are compiled by
the package's own build into one shared library, ``_kernels*.so`` here, when a C compiler is
there; without one the package installs without it and :func:`available` is False (the
portable path: the torch and ONNX implementations). ``TACTILE_NATIVE=0`` in the environment
(or ``false``, ``off``, ``no``) disables the library as if it were absent (:func:`disabled_by_env`).

The kernels compute in float64 whatever the array type, row by row: a row's result does not
depend on the batch it is in. :func:`emd` matches PyEMD ``EMD(FIXE=n_sifts)`` and the toolkit's
torch ``EMD`` module; :func:`omp` matches scikit-learn's ``orthogonal_mp_gram`` (the
``SparseCoder``'s OMP). No torch here: numpy only.
"""

from __future__ import annotations

import ctypes
import os
import sys
from functools import cache
from pathlib import Path

import numpy as np

from tactile.contract_keys import MAX_IMFS, MAX_SIFTS
from tactile.errors import ConfigError, TactileError

__all__ = ["NativeError", "available", "disabled_by_env", "emd", "library_path", "omp"]

ABI = 1
"""The C library's ``tactile_native_abi()`` this wrapper speaks."""
_HERE = Path(__file__).resolve().parent
_OK, _EINVAL, _ENOMEM, _ENONFINITE = 0, 1, 2, 3


class NativeError(TactileError):
    """The native library is missing, of another ABI, or failed (out of memory)."""


_OFF, _ON = {"0", "false", "off", "no"}, {"", "1", "true", "on", "yes"}
_warned: set[str] = set()


def disabled_by_env() -> bool:
    """Whether ``TACTILE_NATIVE`` turns the library off: ``0``, ``false``, ``off`` or ``no``
    (any case). ``1``, ``true``, ``on``, ``yes``, empty or unset leave it on; any other value leaves
    it on too, said once on stderr (a typo must not stop a board's label stream)."""
    value = os.environ.get("TACTILE_NATIVE", "").strip()
    if value.lower() in _OFF:
        return True
    if value.lower() not in _ON and value not in _warned:
        _warned.add(value)
        from tactile.cli import prefix  # the command's name while one runs

        print(f"{prefix('tactile: ')}TACTILE_NATIVE={value!r} is not one of 0/false/off/no "
              "(kernels off) or 1/true/on/yes: the native kernels stay on", file=sys.stderr)
    return False


def library_path() -> Path | None:
    """The built library's path, or None (not built, or turned off: :func:`disabled_by_env`)."""
    if disabled_by_env():
        return None
    found = sorted(_HERE.glob("_kernels*.so")) + sorted(_HERE.glob("_kernels*.pyd"))
    return found[0] if found else None


@cache
def _load(path: Path) -> ctypes.CDLL:
    lib = ctypes.CDLL(str(path))
    lib.tactile_native_abi.restype = ctypes.c_int
    if lib.tactile_native_abi() != ABI:
        raise NativeError(f"{path.name}: ABI {lib.tactile_native_abi()}, this wrapper needs {ABI}")
    p, i64, i32 = ctypes.c_void_p, ctypes.c_int64, ctypes.c_int32
    for name in ("tactile_emd_f64", "tactile_emd_f32"):
        fn = getattr(lib, name)
        fn.argtypes = [p, i64, i64, i32, i32, p, p, p]
        fn.restype = ctypes.c_int
    for name in ("tactile_omp_f64", "tactile_omp_f32"):
        fn = getattr(lib, name)
        fn.argtypes = [p, i64, i64, p, p, i64, i64, p]
        fn.restype = ctypes.c_int
    return lib


def _lib() -> ctypes.CDLL:
    path = library_path()
    if path is None:
        if disabled_by_env():
            raise NativeError("the native kernels are turned off "
                              f"(TACTILE_NATIVE={os.environ.get('TACTILE_NATIVE', '').strip()})")
        raise NativeError("the native kernels are not built (no C compiler at install time)")
    return _load(path)


def available() -> bool:
    """True when the native library is built, enabled and loads."""
    try:
        _lib()
    except (NativeError, OSError):
        return False
    return True


def _ptr(a: np.ndarray) -> int:
    return a.ctypes.data


def _float_array(name: str, a, ndim: int, dtype=None) -> np.ndarray:
    """``a`` as a C-ordered float32/float64 array of ``ndim`` dimensions (one-line errors)."""
    if not isinstance(a, np.ndarray):
        raise ConfigError(f"{name} must be a numpy array, got {type(a).__name__}")
    if a.dtype not in (np.float32, np.float64):
        raise ConfigError(f"{name} must be float32 or float64, got {a.dtype}")
    if a.ndim != ndim:
        raise ConfigError(f"{name} must have {ndim} dimensions, got shape {a.shape}")
    return np.ascontiguousarray(a, dtype=dtype or a.dtype)


def _int_setting(name: str, value, hi: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ConfigError(f"{name} must be an int, got {type(value).__name__}")
    if not 1 <= value <= hi:
        raise ConfigError(f"{name}={value} is out of range: allowed 1..{hi}")
    return int(value)


def _check(status: int, what: str) -> None:
    if status == _ENONFINITE:
        raise ConfigError(f"{what} input contains NaN or inf")
    if status == _ENOMEM:
        raise NativeError(f"{what}: out of memory")
    if status != _OK:
        raise NativeError(f"{what}: the native kernel refused its arguments (status {status})")


def emd(x: np.ndarray, n_imfs: int = 4, n_sifts: int = 10):
    """Fixed-shape EMD of every row, as the torch ``EMD`` module computes it.

    Args:
        x: (batch, length) float32 or float64, finite.
        n_imfs: IMF slots, 1..16; n_sifts: sifts per IMF, 1..1000.

    Returns:
        imfs (batch, n_imfs, length) in x's dtype, zero past ``n_valid``; residue
        (batch, length), ``x`` minus the IMFs' sum; n_valid (batch,) int64. Rows shorter than
        3 samples have no IMFs.

    Raises:
        ConfigError: wrong type, shape or setting, or NaN/inf in ``x``.
        NativeError: no library (:func:`available`) or out of memory.
    """
    x = _float_array("EMD input", x, 2)
    n_imfs = _int_setting("EMD n_imfs", n_imfs, MAX_IMFS)
    n_sifts = _int_setting("EMD n_sifts", n_sifts, MAX_SIFTS)
    lib = _lib()
    batch, length = x.shape
    imfs = np.zeros((batch, n_imfs, length), dtype=x.dtype)
    residue = np.zeros((batch, length), dtype=x.dtype)
    n_valid = np.zeros(batch, dtype=np.int64)
    fn = lib.tactile_emd_f32 if x.dtype == np.float32 else lib.tactile_emd_f64
    status = fn(_ptr(x), batch, length, n_imfs, n_sifts, _ptr(imfs), _ptr(residue),
                _ptr(n_valid))
    _check(status, "EMD")
    return imfs, residue, n_valid


def omp(x: np.ndarray, dictionary: np.ndarray, gram: np.ndarray, n_nonzero: int) -> np.ndarray:
    """OMP codes of every row, as scikit-learn's ``orthogonal_mp_gram(gram, dictionary @ x.T,
    n_nonzero_coefs=n_nonzero)`` and the toolkit's ``SparseCoder`` compute them.

    Args:
        x: (rows, features) float32 or float64; dictionary: (atoms, features) and gram:
            (atoms, atoms) (``dictionary @ dictionary.T``), converted to x's dtype.
        n_nonzero: atoms per code, 1..atoms.

    Returns:
        codes (rows, atoms) in x's dtype, at most ``n_nonzero`` non-zero per row. The early
        exits use the epsilon of x's dtype, as scikit-learn's do.

    Raises:
        ConfigError: wrong type, shape or setting, or NaN/inf in any input.
        NativeError: no library or out of memory.
    """
    x = _float_array("OMP input", x, 2)
    d = _float_array("OMP dictionary", dictionary, 2, x.dtype)
    g = _float_array("OMP gram", gram, 2, x.dtype)
    atoms, features = d.shape
    if atoms < 1 or features < 1:
        raise ConfigError(f"OMP dictionary of shape {d.shape}: must be (atoms, features)")
    if x.shape[1] != features:
        raise ConfigError(f"OMP input has {x.shape[1]} features, the dictionary {features}")
    if g.shape != (atoms, atoms):
        raise ConfigError(f"OMP gram of shape {g.shape}: must be ({atoms}, {atoms})")
    n_nonzero = _int_setting("OMP n_nonzero", n_nonzero, atoms)
    lib = _lib()
    codes = np.zeros((x.shape[0], atoms), dtype=x.dtype)
    fn = lib.tactile_omp_f32 if x.dtype == np.float32 else lib.tactile_omp_f64
    _check(fn(_ptr(x), x.shape[0], features, _ptr(d), _ptr(g), atoms, n_nonzero, _ptr(codes)),
           "OMP")
    return codes
