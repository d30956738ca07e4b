"""Argument checks shared by the model functions: each raises ValueError naming the argument."""

from __future__ import annotations

import math
import numbers

import numpy as np


def as_points(arr, name: str, width: int) -> np.ndarray:
    """Return ``arr`` as a float64 array of shape (n, width), or raise ValueError naming it."""
    a = arr if isinstance(arr, np.ndarray) else np.asarray(arr)
    if a.ndim != 2 or a.shape[1] != width:
        raise ValueError(f"{name} must have shape (n, {width}), got {a.shape}")
    if a.dtype != np.float64:
        if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
            raise ValueError(f"{name} must be a real numeric array, got dtype {a.dtype}")
        a = a.astype(np.float64)
    return a


def as_scalar(value, name: str) -> float:
    """Return a real scalar (finite or not) as float, or raise ValueError naming it."""
    if isinstance(value, float):
        return value
    if isinstance(value, numbers.Real) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, np.ndarray) and value.shape == () and value.dtype.kind in "fiu":
        return float(value)
    raise ValueError(f"{name} must be a real scalar, got {type(value).__name__} {value!r}")


def finite_scalar(value, name: str) -> float:
    """Return a finite real scalar as float, or raise ValueError naming it."""
    v = as_scalar(value, name)
    if not math.isfinite(v):
        raise ValueError(f"{name} must be finite, got {v}")
    return v


def finite_vector(value, name: str, length: int) -> np.ndarray:
    """Return a finite float64 vector of the given length (a new read-only array)."""
    try:
        a = np.array(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name} must be a numeric vector of length {length}: {exc}") from None
    if a.shape != (length,):
        raise ValueError(f"{name} must have shape ({length},), got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise ValueError(f"{name} must be finite, got {a.tolist()}")
    a.flags.writeable = False
    return a


def as_float_array(value, name: str) -> np.ndarray:
    """Return a real float64 array of any shape, or raise ValueError naming it."""
    a = value if isinstance(value, np.ndarray) else np.asarray(value)
    if a.dtype != np.float64:
        if a.dtype.kind not in "fiu":
            raise ValueError(f"{name} must be real numeric, got dtype {a.dtype}")
        a = a.astype(np.float64)
    return a


def check_keys(data, keys, prefix: str = '', name: str | None = None) -> None:
    """Raise ValueError unless ``data`` is a mapping with exactly ``keys``.

    The message names the key as ``prefix + key`` (missing or unknown), or the mapping as
    ``name`` (default: ``prefix`` without its dot, else ``'model'``).
    """
    if not isinstance(data, dict):
        name = name or prefix.rstrip('.') or 'model'
        raise ValueError(f"{name} must be a mapping, got {type(data).__name__}")
    for key in keys:
        if key not in data:
            raise ValueError(f"missing key {prefix}{key}")
    for key in data:
        if key not in keys:
            raise ValueError(f"unknown key {prefix}{key}")


def unit_vector(value, name: str, length: int, what: str) -> np.ndarray:
    """Return a finite vector scaled to unit norm over its first three entries (read-only).

    ``what`` names the part that must be non-zero in the error (e.g. ``'normal (a, b, c)'``).
    """
    a = finite_vector(value, name, length)
    norm = float(np.linalg.norm(a[:3]))
    if norm < 1e-12:
        raise ValueError(f"{name} must have a non-zero {what}")
    a = a / norm
    a.flags.writeable = False
    return a
