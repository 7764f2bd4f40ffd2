"""Input validation for the numpy geometry API: shapes, dtype and finiteness, raising GeometryError."""

from __future__ import annotations

from typing import Sequence

import numpy as np

from umi_aug.errors import GeometryError

__all__ = ["as_float", "as_generator", "fmt_trailing"]


def fmt_trailing(trailing: Sequence[int]) -> str:
    return "[..., " + ", ".join(str(d) for d in trailing) + "]" if trailing else "[...]"


def as_float(x, name: str, func: str, trailing: Sequence[int] = ()) -> np.ndarray:
    """Convert ``x`` to a float64 array and check its trailing shape and finiteness.

    Raises :class:`GeometryError` naming ``func``, the argument ``name``, its shape and the expected shape.
    """
    try:
        arr = np.asarray(x, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise GeometryError(f"{func}: `{name}` could not be converted to a float array ({exc})") from exc
    k = len(trailing)
    if arr.ndim < k or tuple(arr.shape[arr.ndim - k:]) != tuple(trailing):
        raise GeometryError(
            f"{func}: `{name}` has shape {tuple(arr.shape)}; expected {fmt_trailing(trailing)}"
        )
    if not np.isfinite(arr).all():
        bad = int(np.size(arr) - np.count_nonzero(np.isfinite(arr)))
        raise GeometryError(f"{func}: `{name}` (shape {tuple(arr.shape)}) has {bad} non-finite value(s)")
    return arr


def as_generator(rng, func: str) -> np.random.Generator:
    """A ``numpy.random.Generator`` from a Generator or an integer seed (same seed → same stream)."""
    if isinstance(rng, np.random.Generator):
        return rng
    if isinstance(rng, (int, np.integer)) and not isinstance(rng, bool):
        if int(rng) < 0:
            raise GeometryError(f"{func}: `rng` seed must be >= 0, got {rng}")
        return np.random.default_rng(int(rng))
    raise GeometryError(f"{func}: `rng` must be a numpy.random.Generator or an int seed, got {type(rng).__name__}")
