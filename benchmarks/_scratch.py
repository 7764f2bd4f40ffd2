"""A benchmark's scratch folder, claimed with a marker file so that a script which empties or replaces what is in
it never touches a folder of the user's."""

from __future__ import annotations

from pathlib import Path


def claim_scratch_folder(work: Path, marker_name: str, what_happens: str) -> str | None:
    """Create ``work`` (or accept it: empty, or marked by this benchmark before) and mark it; returns None, or the
    one-line error when ``work`` is a non-empty folder the benchmark did not make (``what_happens``: what the
    benchmark does to its contents, for the message)."""
    marker = work / marker_name
    if work.exists() and any(work.iterdir()) and not marker.exists():
        return (f"error: --work {work}: exists, is not empty and was not made by this benchmark (no {marker_name}); "
                f"{what_happens}: choose a new folder")
    work.mkdir(parents=True, exist_ok=True)
    marker.touch()
    return None


def real_episode_missing(dataset: Path) -> str | None:
    """None, or the one-line error when the real UMI demonstration (``../shared/realdata``) is not at ``dataset``."""
    if dataset.exists():
        return None
    return f"error: {dataset}: the real demonstration is not here (../shared/realdata is absent)"
