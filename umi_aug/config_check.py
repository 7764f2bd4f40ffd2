"""The config-validation helpers every stage shares (issue #33 item 4): unknown keys and positive numbers.

Each stage keeps its own error type (``umi_aug.errors``) and its own message wording; these helpers hold the rule
once. This module imports nothing of the package, so any stage can use it without an upward import.
"""

from __future__ import annotations

import math
from typing import Any, Iterable, Mapping

__all__ = ["reject_unknown_keys", "is_positive", "require_positive"]


def reject_unknown_keys(m: Mapping[str, Any], known: Iterable[str], where: str, error: type[Exception]) -> None:
    """Raise ``error`` naming the config block ``where`` and the keys of ``m`` it does not know.

    Message: ``"<where>: unknown key(s) [...]; known: [...]"`` (both lists sorted).
    """
    known = set(known)
    extra = sorted(set(m) - known)
    if extra:
        raise error(f"{where}: unknown key(s) {extra}; known: {sorted(known)}")


def is_positive(value: float, *, allow_zero: bool = False) -> bool:
    """True when the real number ``value`` is finite and > 0 (>= 0 with ``allow_zero``); NaN and ±inf are not
    (a Python ``int`` is always finite, however large)."""
    finite = isinstance(value, int) or math.isfinite(value)
    return finite and (value > 0 or (allow_zero and value == 0))


def require_positive(where: str, obj: Any, keys: Iterable[str], error: type[Exception]) -> None:
    """Raise ``error`` for the first attribute of ``obj`` among ``keys`` that is not an ``int``/``float`` > 0.

    Message: ``"<where>.<key>=<value!r> must be a number > 0"``.
    """
    for k in keys:
        v = getattr(obj, k)
        if not (isinstance(v, (int, float)) and is_positive(v)):
            raise error(f"{where}.{k}={v!r} must be a number > 0")
