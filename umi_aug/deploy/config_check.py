"""One check shared by the deploy config blocks."""

from __future__ import annotations

from typing import Any, Iterable, Mapping

from umi_aug.errors import DeployError

__all__ = ["reject_unknown_keys"]


def reject_unknown_keys(m: Mapping[str, Any], known: Iterable[str], where: str) -> None:
    """Raise :class:`DeployError` naming the config block and the keys it does not know."""
    known = set(known)
    extra = sorted(set(m) - known)
    if extra:
        raise DeployError(f"{where}: unknown key(s) {extra}; known: {sorted(known)}")
