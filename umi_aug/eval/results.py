"""The results folder of an evaluation run: ``run.json`` (what was evaluated), ``results.jsonl`` (one line per
finished configuration, appended as each finishes), ``summary.json``.

``results.jsonl`` is append-only: every record is ONE ``write`` of one complete line followed by ``fsync``; a
line cut short by a killed process (no trailing newline or invalid JSON) is dropped when the file is read again
(and the file is rewritten atomically without it), so a rerun skips exactly the configurations that finished.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from pathlib import Path
from typing import Any

from umi_aug.errors import EvalError
from umi_aug.io_utils import atomic_write_text

__all__ = ["file_sha256", "ResultsLog", "check_run_key"]

log = logging.getLogger(__name__)


def file_sha256(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def check_run_key(out_dir: Path, key: dict[str, Any]) -> None:
    """Write ``run.json`` with ``key`` (what determines the rollouts), or check that an existing one matches.

    Raises:
        EvalError: ``out_dir`` holds results of a different run (names the differing keys).
    """
    path = out_dir / "run.json"
    if path.exists():
        try:
            old = json.loads(path.read_text())
        except (OSError, ValueError) as exc:
            raise EvalError(f"{path}: unreadable ({exc}); delete it together with results.jsonl or choose "
                            f"another out_dir") from exc
        diff = {k: (old.get(k), key.get(k)) for k in set(old) | set(key) if old.get(k) != key.get(k)}
        if diff:
            raise EvalError(f"{out_dir}: holds results of a different evaluation (run.json differs in "
                            + ", ".join(f"{k}: {a!r} → {b!r}" for k, (a, b) in sorted(diff.items()))
                            + "); choose another out_dir or delete that folder")
        return
    out_dir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(path, json.dumps(key, indent=1, sort_keys=True))


class ResultsLog:
    """``results.jsonl`` of one run: read finished records, append new ones."""

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)

    def read(self) -> dict[int, dict[str, Any]]:
        """Finished records by configuration index (first record wins; a cut-off last line is dropped)."""
        if not self.path.exists():
            return {}
        raw = self.path.read_bytes()
        records: dict[int, dict[str, Any]] = {}
        good: list[bytes] = []
        dropped = 0
        for line in raw.split(b"\n"):
            if not line.strip():
                continue
            try:
                rec = json.loads(line)
                cfg = int(rec["config"])
            except (ValueError, KeyError, TypeError):
                dropped += 1
                continue
            if cfg in records:
                dropped += 1
                continue
            records[cfg] = rec
            good.append(line)
        if dropped or (raw and not raw.endswith(b"\n")):
            log.warning("%s: dropped %d incomplete/duplicate line(s) (interrupted run)", self.path, dropped)
            atomic_write_text(self.path, "".join(g.decode() + "\n" for g in good))
        return records

    def append(self, rec: dict[str, Any]) -> None:
        """Append one record as a single write of one line, then fsync."""
        line = (json.dumps(rec, sort_keys=True, allow_nan=False) + "\n").encode()
        fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        try:
            os.write(fd, line)
            os.fsync(fd)
        finally:
            os.close(fd)
